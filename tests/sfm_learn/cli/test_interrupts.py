"""Every long command answers Ctrl-C with one line and exit 130, writes nothing
partial and leaves no process behind, whether the signal goes to the whole process group (Ctrl-C
in a terminal) or to the main process alone (``kill -INT``).

Each command is started in its own session and signalled once it has used about 2 s of CPU
(itself and its children): past its imports, inside its work, workers starting or running."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

psutil = pytest.importorskip("psutil")

# The child handles SIGINT as in a terminal even when this test run was started as a background
# job, where POSIX shells ignore SIGINT and children inherit that.
TERMINAL_SIGINT = "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler)"
# the console scripts' own launchers (pyproject's [project.scripts])
MKV = f"{TERMINAL_SIGINT}; from mkv_sfm_launch import mkv; sys.exit(mkv())"
CALIB = f"{TERMINAL_SIGINT}; from mkv_sfm_launch import calib; sys.exit(calib())"
CPU_BEFORE_SIGNAL_S = 2.0

SWEEP = {"name": "interrupt", "teacher_env": "MKV-v1", "env": ["MKVJam-v1"],
         "eval": {"episodes": 200, "seed": 4_200_000}, "seeds": list(range(8)),
         "learners": {"sfm": {}}, "budgets": {"sfm": [20_000]}}


@pytest.fixture(scope="module")
def raw_csv(tmp_path_factory):
    """A 300,000-row calib log for ``calib fit`` to stream (written once: a second of CPU)."""
    raw = tmp_path_factory.mktemp("interrupts") / "raw.csv"
    rng = np.random.default_rng(0)
    Z = rng.normal(size=(300_000, 8))
    np.savetxt(raw, Z, delimiter=",", header=",".join(f"z{i}" for i in range(8)),
               comments="", fmt="%.6f")
    return raw


def _commands(tmp, raw):
    """name -> (python -c program, argv, the output it must not leave)."""
    (tmp / "spec.json").write_text(json.dumps(SWEEP))
    jam = ["--env", "MKVJam-v1"]
    data = tmp / "teacher.npz"
    return {
        "mkv eval": (MKV, ["eval", *jam, "--policy", "teacher", "--episodes", "20000",
                           "--workers", "2", "--json", str(tmp / "out.json")], "out.json"),
        "mkv sweep": (MKV, ["sweep", str(tmp / "spec.json"), "--out", str(tmp / "sweep"),
                            "--workers", "2", "--quiet"], None),
        "mkv record": (MKV, ["record", "--env", "MKV-v1", "--policy", "teacher", "--episodes",
                             "2000", "--out", str(tmp / "out.npz"), "--quiet"], "out.npz"),
        "mkv train-ppo": (MKV, ["train-ppo", *jam, "--timesteps", "1000000", "--out",
                                str(tmp / "out.zip"), "--quiet"], "out.zip"),
        "mkv train-bc": (MKV, ["train-bc", str(data), "--epochs", "100000", "--min-updates",
                               "0", "--out", str(tmp / "out.zip"), "--quiet"], "out.zip"),
        "mkv train-dagger": (MKV, ["train-dagger", "--env", "MKV-v1", "--steps", "200000",
                                   "--out", str(tmp / "out.zip"), "--quiet"], "out.zip"),
        "mkv demo": (MKV, ["demo", "--out", str(tmp / "demo"), "--quiet"], "demo"),
        "calib fit": (CALIB, ["fit", str(raw), "--dof", "3", "--bias", "--chunk-rows", "2000",
                              "--out", str(tmp / "out.json"), "--quiet"], "out.json"),
        "calib trials": (CALIB, ["trials", "--out", str(tmp / "trials"), "--seeds", "100000",
                                 "--no-plots", "--quiet"], "trials"),
    }


def _cpu(proc):
    try:
        t = proc.cpu_times()
        total = t.user + t.system
        for c in proc.children(recursive=True):
            ct = c.cpu_times()
            total += ct.user + ct.system
        return total
    except psutil.NoSuchProcess:
        return 0.0


@pytest.mark.parametrize("to", ["group", "main"])
@pytest.mark.parametrize("name", ["mkv eval", "mkv sweep", "mkv record", "mkv train-ppo",
                                  "mkv train-bc", "mkv train-dagger", "mkv demo", "calib fit",
                                  "calib trials"])
def test_ctrl_c_is_one_line_exit_130_nothing_written_no_process_left(name, to, tmp_path,
                                                                     raw_csv):
    if name in ("mkv train-ppo", "mkv train-bc", "mkv train-dagger", "mkv demo"):
        pytest.importorskip("stable_baselines3")
    prog, argv, output = _commands(tmp_path, raw_csv)[name]
    if name == "mkv train-bc":  # a small teacher dataset to clone from
        from mkv_env import dataset as ds
        from mkv_env.recorder import record

        ds.save(record("MKV-v0", "teacher", episodes=4, seed=0,
                       env_kwargs={"max_episode_steps": 150}), tmp_path / "teacher.npz")
    before = set(os.listdir(tmp_path))
    proc = subprocess.Popen([sys.executable, "-c", prog, *argv], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env=dict(os.environ, SDL_VIDEODRIVER="dummy"), cwd=tmp_path)
    p = psutil.Process(proc.pid)
    deadline = time.monotonic() + 120
    while proc.poll() is None and _cpu(p) < CPU_BEFORE_SIGNAL_S and time.monotonic() < deadline:
        time.sleep(0.05)
    assert proc.poll() is None, f"{name} ended before the signal: make its work longer"
    children = p.children(recursive=True)
    if to == "group":
        os.killpg(proc.pid, signal.SIGINT)
    else:
        os.kill(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    lines = err.splitlines()
    assert len(lines) == 1 and "interrupted" in lines[0], err
    if output is not None:
        assert not (tmp_path / output).exists()
    else:  # the sweep keeps its finished rows (it resumes): only whole JSON rows
        rows = tmp_path / "sweep" / "rows"
        for f in (os.listdir(rows) if rows.exists() else []):
            assert f.endswith(".json") and not f.startswith("."), f
            json.loads((rows / f).read_text())
    assert set(os.listdir(tmp_path)) - before - {"sweep"} == set()
    _, alive = psutil.wait_procs(children, timeout=15)
    assert not alive, [c.cmdline() for c in alive]


@pytest.mark.parametrize("to", ["group", "main"])
@pytest.mark.parametrize("prog,name", [(MKV, "mkv"), (CALIB, "calib")])
def test_ctrl_c_while_the_command_package_imports_is_one_line(prog, name, to, tmp_path):
    """The console scripts import their package before main runs (numpy, scipy, gymnasium: a
    few tenths of a second); a Ctrl-C then was a KeyboardInterrupt traceback from inside scipy.
    Here the launcher's import is made slow (a module that sleeps, imported first) and the
    signal sent once the import has begun."""
    slow = tmp_path / "slow"
    slow.mkdir()
    (slow / "mkv_sfm_slow_import.py").write_text("import time\ntime.sleep(30)\n")
    hook = ("import importlib, sys; real = importlib.import_module\n"
            "def slow(name, *a, **k):\n"
            "    print('importing', flush=True)\n"
            "    real('mkv_sfm_slow_import')\n"
            "    return real(name, *a, **k)\n"
            "importlib.import_module = slow\n")
    code = prog.replace("; from mkv_sfm_launch", f"; exec({hook!r}); from mkv_sfm_launch")
    proc = subprocess.Popen([sys.executable, "-c", code, "--help"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env=dict(os.environ, PYTHONPATH=f"{slow}{os.pathsep}"
                                     f"{os.environ.get('PYTHONPATH', '')}"))
    assert proc.stdout.readline().strip() == "importing"
    (os.killpg if to == "group" else os.kill)(proc.pid, signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert err.splitlines() == [f"{name}: interrupted; no output written"], err
