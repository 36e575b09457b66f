"""Ray's C++ client writes a warning line to file descriptor 2 for every failed try to reach a
cluster (about 20 before it gives up): while ``init_ray`` connects, those lines are held and
dropped when it fails, so the one-line error is the only line; kept when it succeeds."""

import os

import pytest

from sfm_learn.evaluation.ray_eval import _c_stderr_held


def test_c_level_lines_are_dropped_when_the_block_fails(capfd):
    with pytest.raises(ConnectionError), _c_stderr_held():
        os.write(2, b"[W gcs_client.cc:210] Failed to get cluster ID from GCS server\n")
        raise ConnectionError("Failed to connect to Ray cluster")
    assert capfd.readouterr().err == ""
    os.write(2, b"after\n")  # the descriptor is the terminal's again
    assert capfd.readouterr().err == "after\n"


def test_c_level_lines_are_written_back_when_the_block_succeeds(capfd):
    with _c_stderr_held():
        os.write(2, b"a note from Ray\n")
    assert capfd.readouterr().err == "a note from Ray\n"
