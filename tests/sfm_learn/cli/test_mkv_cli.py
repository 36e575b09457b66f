"""The ``mkv`` command line: record, eval, play, and one-line errors for user mistakes."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from mkv_env import dataset as ds
from sfm_learn.cli import COMMANDS, main

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")

# The child handles SIGINT as in a terminal even when this test run was started as a background
# job, where POSIX shells ignore SIGINT and children inherit that (the CLI would then never see it).
TERMINAL_SIGINT = "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler)"


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_record_writes_a_valid_dataset_and_summary(capsys, tmp_path):
    out = tmp_path / "d.npz"
    code, text, err = run(capsys, "record", "--env", "MKVJam-v0", "--policy", "teacher",
                          "--episodes", "3", "--seed", "5", "--out", str(out))
    assert code == 0, err
    data = ds.load(out)
    assert data.n_episodes == 3 and list(data["episode_seeds"]) == [5, 6, 7]
    assert data.metadata["env_id"] == "MKVJam-v0" and data.metadata["policy"] == "teacher"
    assert f"{data.n_steps} steps" in text and "3 escapes" in text and "stuck fraction" in text
    assert f"wrote {out}" in text


def test_record_twice_gives_identical_files(capsys, tmp_path):
    args = ["record", "--env", "MKV-v0", "--env-kwargs", '{"max_episode_steps": 40}',
            "--policy", "random", "--episodes", "2", "--seed", "1", "--out"]
    assert run(capsys, *args, str(tmp_path / "a.npz"))[0] == 0
    assert run(capsys, *args, str(tmp_path / "b.npz"))[0] == 0
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()


def test_eval_table_and_json(capsys, tmp_path):
    out = tmp_path / "m.json"
    code, text, err = run(capsys, "eval", "--env", "MKVJam-v0", "--policy", "teacher",
                          "--episodes", "3", "--seed", "0", "--json", str(out))
    assert code == 0, err
    assert "escape rate" in text and "teacher" in text
    doc = json.loads(out.read_text())
    assert set(doc) == {"env", "policy", "episodes", "seed", "metrics", "metrics_ci"}
    assert set(doc["metrics"]) == {"escape_rate", "mean_escape_time_s", "distance_m",
                                   "stuck_fraction", "collisions_per_min", "mean_return"}
    assert set(doc["metrics_ci"]) == set(doc["metrics"])
    assert doc["episodes"] == 3 and doc["seed"] == 0 and 0 <= doc["metrics"]["escape_rate"] <= 1
    low, high = doc["metrics_ci"]["escape_rate"]
    assert low <= doc["metrics"]["escape_rate"] <= high


def test_eval_on_wander_env_has_null_escape_metrics(capsys, tmp_path):
    out = tmp_path / "m.json"
    code, _, err = run(capsys, "eval", "--env", "MKV-v0", "--env-kwargs",
                       '{"max_episode_steps": 30}', "--policy", "random", "--episodes", "2",
                       "--json", str(out))
    assert code == 0, err
    doc = json.loads(out.read_text())
    m, ci = doc["metrics"], doc["metrics_ci"]
    assert m["escape_rate"] is None and m["mean_escape_time_s"] is None
    assert ci["escape_rate"] is None and ci["mean_escape_time_s"] is None
    assert m["distance_m"] is not None and ci["distance_m"][0] <= m["distance_m"]


def test_eval_script_policy(capsys, tmp_path):
    script = tmp_path / "s.txt"
    script.write_text("0 forward off\n1.0 reverse left\n")
    code, text, err = run(capsys, "eval", "--env", "MKVJam-v0", "--policy", f"script:{script}",
                          "--episodes", "2")
    assert code == 0, err
    assert f"script:{script}" in text


def test_play_writes_png_frames_headless(capsys, tmp_path):
    frames = tmp_path / "frames"
    code, text, err = run(capsys, "play", "--policy", "teacher", "--env", "MKVJam-v0",
                          "--seed", "1", "--max-steps", "3", "--out", str(frames))
    assert code == 0, err
    files = sorted(os.listdir(frames))
    assert 2 <= len(files) <= 4 and all(f.endswith(".png") for f in files)
    with open(frames / files[0], "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"


def test_play_writes_a_gif(capsys, tmp_path):
    pytest.importorskip("PIL")
    gif = tmp_path / "p.gif"
    code, _, err = run(capsys, "play", "--policy", "random", "--max-steps", "3",
                       "--out", str(gif))
    assert code == 0, err
    assert gif.read_bytes()[:6] in (b"GIF89a", b"GIF87a")


def test_play_writes_an_mp4_through_record_video(capsys, tmp_path):
    pytest.importorskip("moviepy")
    mp4 = tmp_path / "run.mp4"
    code, text, err = run(capsys, "play", "--policy", "teacher", "--env", "MKVJam-v1",
                          "--seed", "2", "--max-steps", "12", "--out", str(mp4))
    assert code == 0, err
    assert mp4.read_bytes()[4:8] == b"ftyp"  # an MP4 container
    assert "RecordVideo" in text and "Overwriting" not in err
    assert sorted(os.listdir(tmp_path)) == ["run.mp4"]  # the scratch folder is gone


@pytest.mark.parametrize("argv,match", [
    (["eval", "--env", "Nope-v0", "--policy", "teacher", "--episodes", "2"], "Nope-v0"),
    (["eval", "--env", "MKV-v0", "--policy", "bogus", "--episodes", "2"], "unknown policy"),
    (["eval", "--env", "MKV-v0", "--policy", "script:/no/such.txt", "--episodes", "1"],
     "not found"),
    (["eval", "--env", "MKV-v0", "--policy", "teacher", "--episodes", "0"], "positive integer"),
    (["eval", "--env", "MKV-v0", "--policy", "teacher", "--episodes", "two"],
     "positive integer"),
    (["eval", "--env", "MKV-v0", "--policy", "teacher", "--episodes", "1", "--seed", "-1"],
     "non-negative"),
    (["eval", "--env", "MKV-v0", "--env-kwargs", "{bad", "--policy", "teacher",
      "--episodes", "1"], "JSON"),
    (["eval", "--env", "MKV-v0", "--env-kwargs", '{"n_clutter": -1}', "--policy", "teacher",
      "--episodes", "1"], "n_clutter"),
    (["eval", "--env", "MKV-v0", "--env-kwargs", '{"wings": 2}', "--policy", "teacher",
      "--episodes", "1"], "wings"),
    (["record", "--env", "MKV-v0", "--policy", "teacher", "--episodes", "1",
      "--out", "/no/such/dir/d.npz"], "does not exist"),
    (["record", "--env", "MKV-v0", "--policy", "teacher", "--episodes", "1"], "--out"),
    (["play", "--policy", "teacher:wings=1"], "bad teacher option"),
    (["frobnicate"], "invalid choice"),
    ([], "required"),
])
def test_user_mistakes_give_one_line_and_exit_2(capsys, argv, match):
    code, out, err = run(capsys, *argv)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith("mkv") and "error:" in lines[0] and match in lines[0]


def test_bad_script_file_is_one_line(capsys, tmp_path):
    script = tmp_path / "s.txt"
    script.write_text("0 forward off\n0.5 forward sideways\n")
    code, _, err = run(capsys, "eval", "--env", "MKV-v0", "--policy", f"script:{script}",
                       "--episodes", "1")
    assert code == 2 and len(err.strip().splitlines()) == 1 and ":2:" in err


def test_extension_points_exist():
    names = [c.name for c in COMMANDS]
    assert names[:3] == ["record", "eval", "play"]


def test_sigint_leaves_no_partial_file(tmp_path):
    out = tmp_path / "big.npz"
    cmd = [sys.executable, "-c", f"{TERMINAL_SIGINT}; from sfm_learn.cli import main; "
           "print('ready', flush=True); sys.exit(main())",
           "record", "--env", "MKV-v0", "--policy", "teacher", "--episodes", "2000",
           "--seed", "0", "--out", str(out), "--quiet"]
    env = dict(os.environ, SDL_VIDEODRIVER="dummy")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
                            text=True)
    assert proc.stdout.readline().strip() == "ready"  # imports done: main() handles SIGINT
    time.sleep(1.0)  # well inside the recording loop (2000 episodes take minutes)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err
    assert os.listdir(tmp_path) == []


def test_console_script_runs(tmp_path):
    exe = os.path.join(os.path.dirname(sys.executable), "mkv")
    if not os.path.exists(exe):
        pytest.skip("mkv console script not installed")
    r = subprocess.run([exe, "eval", "--env", "MKV-v0", "--policy", "nope", "--episodes", "1"],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.count("\n") == 1


def test_library_warnings_before_a_one_line_error_are_dropped(monkeypatch, capsys):
    """A warning raised by a library while a command runs (Gymnasium's "MKV-v0 is out
    of date") is shown when the command succeeds and dropped when it fails: the one-line error
    is then the only line on stderr."""
    import argparse
    import warnings

    from sfm_learn.cli import app
    from sfm_learn.cli.common import CliError

    def run(ok):
        def _run(args):
            warnings.warn("the library says something", DeprecationWarning, stacklevel=1)
            if not ok:
                raise CliError("it failed")
            return 0
        return _run

    for ok in (False, True):
        parser = argparse.ArgumentParser()
        parser.set_defaults(_run=run(ok), _prog="mkv x")
        monkeypatch.setattr(app, "build_parser", lambda p=parser: p)
        with warnings.catch_warnings(record=True) as shown:
            warnings.simplefilter("always")
            code = app.main([])
        err = capsys.readouterr().err
        said = [str(w.message) for w in shown]
        if ok:  # shown (after the command: held until then)
            assert code == 0 and said == ["the library says something"]
        else:
            assert code == 2 and said == [] and err == "mkv x: error: it failed\n"
