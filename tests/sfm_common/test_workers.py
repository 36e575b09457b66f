"""Workers die with their parent: a kill -9 of ``mkv sweep --workers 2`` leaves no process behind
within a few seconds (sfm_common/workers.py), even while its jobs would run for much longer. (A
resumed sweep is exact because rows are written atomically: tests/sfm_learn/experiments.)"""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

psutil = pytest.importorskip("psutil")

# jobs of a minute or more each (a long teacher recording): far longer than the test waits
SPEC = {
    "name": "kill", "teacher_env": "MKV-v1", "env": ["MKVJam-v1"],
    "eval": {"episodes": 3, "seed": 4_300_000}, "seeds": [0, 1],
    "learners": {"sfm": {}}, "budgets": {"sfm": [2_000_000]},
}


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_kill_9_of_a_sweep_leaves_no_worker_behind(tmp_path):
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps(SPEC))
    out = tmp_path / "out"
    code = ("import sys; from sfm_learn.cli import main; "
            f"sys.exit(main(['sweep', {str(spec)!r}, '--out', {str(out)!r}, '--workers', '2', "
            "'--quiet']))")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, env=dict(os.environ,
                                                                SDL_VIDEODRIVER="dummy"))
    main = psutil.Process(proc.pid)
    deadline = time.monotonic() + 120
    family = []
    while time.monotonic() < deadline:  # until both workers are at work
        family = main.children(recursive=True)
        if len(family) >= 3 and (out / "spec.json").is_file():
            break
        time.sleep(0.2)
    assert len(family) >= 3, "the sweep never started its workers"
    time.sleep(3.0)
    family = main.children(recursive=True)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    gone, alive = psutil.wait_procs(family, timeout=5)
    assert not alive, f"still running 5 s after kill -9 of the main process: {alive}"
    assert not list(out.glob("rows/*.json")), "a job finished: the test proved nothing"
