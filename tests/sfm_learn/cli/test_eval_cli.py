"""``mkv eval`` with several policies, worker processes, bootstrap intervals, Markdown and plots."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

import sfm_learn.evaluation
import sfm_learn.reporting.plots
from mkv_env.policies import PolicySpecError
from sfm_learn.cli import eval as eval_cli
from sfm_learn.cli import main

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("MPLBACKEND", "Agg")

KEYS = {"env", "policy", "episodes", "seed", "metrics", "metrics_ci"}
JAM = ["eval", "--env", "MKVJam-v0", "--quiet"]

# The child handles SIGINT as in a terminal even when this test run was started as a background
# job, where POSIX shells ignore SIGINT and children inherit that (the CLI would then never see it).
TERMINAL_SIGINT = "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler)"


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_several_policies_json_list_markdown_and_plot(capsys, tmp_path):
    out, png = tmp_path / "e.json", tmp_path / "e.png"
    code, text, err = run(capsys, *JAM, "--policy", "teacher", "--policy", "random",
                          "--policy", "teacher:backoff_s=2", "--episodes", "3", "--seed", "4",
                          "--json", str(out), "--plot", str(png))
    assert code == 0, err
    docs = json.loads(out.read_text())
    assert [d["policy"] for d in docs] == ["teacher", "random", "teacher:backoff_s=2"]
    for d in docs:
        assert set(d) == KEYS and d["episodes"] == 3 and d["seed"] == 4
        assert set(d["metrics_ci"]) == set(d["metrics"])
        for key, value in d["metrics"].items():
            if value is not None:
                low, high = d["metrics_ci"][key]
                assert low <= value <= high
    lines = text.splitlines()
    assert lines[0].startswith("**MKVJam-v0**, 3 episodes per policy on env seeds 4..6")
    rows = [ln for ln in lines if ln.startswith("| ")]
    assert len(rows) == 1 + 3 and "| escape rate |" in rows[0]
    assert rows[2].startswith("| random | ") and " [" in rows[2]
    assert f"wrote {out}" in text and f"wrote {png}" in text
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_one_policy_gives_one_object(capsys, tmp_path):
    out = tmp_path / "e.json"
    code, _, err = run(capsys, "eval", "--env", "MKV-v0", "--env-kwargs",
                       '{"max_episode_steps": 30}', "--policy", "random", "--episodes", "2",
                       "--json", str(out))
    assert code == 0, err
    doc = json.loads(out.read_text())
    assert set(doc) == KEYS
    assert doc["metrics_ci"]["escape_rate"] is None and doc["metrics"]["escape_rate"] is None
    assert len(doc["metrics_ci"]["distance_m"]) == 2


def test_workers_do_not_change_the_file(capsys, tmp_path):
    args = [*JAM, "--policy", "teacher", "--policy", "random", "--episodes", "6", "--seed", "30"]
    assert run(capsys, *args, "--json", str(tmp_path / "a.json"))[0] == 0
    assert run(capsys, *args, "--json", str(tmp_path / "b.json"), "--workers", "2")[0] == 0
    assert (tmp_path / "a.json").read_bytes() == (tmp_path / "b.json").read_bytes()


@pytest.mark.parametrize("extra,match", [
    (["--policy", "teacher", "--workers", "0"], "positive integer"),
    (["--policy", "teacher", "--workers", "many"], "positive integer"),
    (["--policy", "teacher", "--workers", str(eval_cli.max_workers() + 1)], "at most"),
    (["--policy", "teacher", "--policy", "nosuch"], "unknown policy spec 'nosuch'"),
    (["--policy", "teacher", "--policy", "random", "--policy", "script:/no/such.txt"],
     "not found"),
    (["--policy", "teacher", "--policy", "teacher:wings=1"], "bad teacher option"),
    (["--policy", "random", "--policy", "random"], "--policy random given more than once"),
    (["--policy", "teacher", "--plot", "/no/such/dir/p.png"], "does not exist"),
    (["--policy", "teacher", "--plot", "p.unknownext"], "unsupported file type"),
])
def test_bad_input_is_one_line(capsys, tmp_path, extra, match):
    out = tmp_path / "e.json"
    code, _, err = run(capsys, *JAM, "--episodes", "2", "--json", str(out), *extra)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith("mkv eval: error:") and match in lines[0], lines[0]
    assert not out.exists()


def test_unwritable_plot_directory(capsys, tmp_path, monkeypatch):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    if os.access(locked, os.W_OK):  # root: pretend, for this directory only
        real = os.access
        monkeypatch.setattr(os, "access", lambda p, mode, **kw: False
                            if os.path.abspath(p) == str(locked) else real(p, mode, **kw))
    try:
        code, _, err = run(capsys, *JAM, "--policy", "teacher", "--episodes", "1",
                           "--plot", str(locked / "p.png"))
    finally:
        locked.chmod(0o700)
    assert code == 2 and "not writable" in err and len(err.strip().splitlines()) == 1


def test_missing_matplotlib_is_one_line(capsys, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib.backend_bases", None)
    code, _, err = run(capsys, *JAM, "--policy", "teacher", "--episodes", "1",
                       "--plot", str(tmp_path / "p.png"))
    assert code == 2 and "needs matplotlib" in err and len(err.strip().splitlines()) == 1


def test_no_partial_output_when_plotting_fails(capsys, tmp_path, monkeypatch):
    def broken(evaluations, path):
        raise OSError(28, "No space left on device", path)

    monkeypatch.setattr(sfm_learn.reporting.plots, "plot_evaluations", broken)
    out, png = tmp_path / "e.json", tmp_path / "e.png"
    code, _, err = run(capsys, *JAM, "--policy", "teacher", "--episodes", "1",
                       "--json", str(out), "--plot", str(png))
    assert code == 2 and "No space left" in err
    assert os.listdir(tmp_path) == []


def test_no_partial_json_when_a_worker_fails(capsys, tmp_path, monkeypatch):
    def failing(*args, **kwargs):
        raise PolicySpecError("policy file vanished")

    monkeypatch.setattr(sfm_learn.evaluation, "evaluate_many", failing)
    out = tmp_path / "e.json"
    code, _, err = run(capsys, *JAM, "--policy", "teacher", "--episodes", "1",
                       "--json", str(out))
    assert code == 2 and "vanished" in err
    assert os.listdir(tmp_path) == []


def test_sigint_stops_the_workers_and_writes_nothing(tmp_path):
    psutil = pytest.importorskip("psutil")
    out = tmp_path / "e.json"
    cmd = [sys.executable, "-c", f"{TERMINAL_SIGINT}; from sfm_learn.cli import main; "
           "sys.exit(main())",
           *JAM, "--policy", "teacher", "--episodes", "20000", "--workers", "2",
           "--json", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, SDL_VIDEODRIVER="dummy"),
                            start_new_session=True)
    parent = psutil.Process(proc.pid)
    deadline = time.monotonic() + 90  # generous: a loaded CI machine starts workers slowly
    workers = []
    while time.monotonic() < deadline and proc.poll() is None:
        workers = [c for c in parent.children(recursive=True) if c.cpu_times().user > 0.2]
        if len(workers) >= 2:
            break
        time.sleep(0.1)
    assert len(workers) >= 2, "workers never got going"
    children = parent.children(recursive=True)
    os.killpg(proc.pid, signal.SIGINT)  # as Ctrl-C in a terminal: the whole process group
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err, err
    assert os.listdir(tmp_path) == []
    gone, alive = psutil.wait_procs(children, timeout=10)
    assert not alive
