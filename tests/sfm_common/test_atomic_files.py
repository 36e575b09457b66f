"""Atomic writes: the target appears whole or not at all."""

import os
import stat

import pytest

from sfm_common.files import atomic_path, atomic_write_bytes, atomic_write_text


def test_write_replaces_the_target_with_usual_permissions(tmp_path):
    target = tmp_path / "a.txt"
    target.write_text("old")
    atomic_write_text(target, "new")
    assert target.read_text() == "new"
    mask = os.umask(0o022)
    os.umask(mask)
    assert stat.S_IMODE(target.stat().st_mode) == 0o666 & ~mask
    assert os.listdir(tmp_path) == ["a.txt"]


def test_an_error_while_writing_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "a.bin"
    atomic_write_bytes(target, b"old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        assert tmp.endswith(".bin") and os.path.dirname(tmp) == str(tmp_path)
        with open(tmp, "wb") as f:
            f.write(b"half")
        raise RuntimeError("interrupted")
    assert target.read_bytes() == b"old"
    assert os.listdir(tmp_path) == ["a.bin"]


def test_suffix_can_be_chosen_for_writers_that_read_it(tmp_path):
    with atomic_path(tmp_path / "plot", ".png") as tmp:
        assert tmp.endswith(".png")
        open(tmp, "w").close()
    assert (tmp_path / "plot").exists()
