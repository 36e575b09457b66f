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


@pytest.mark.skipif(not hasattr(signal, "pthread_sigmask"), reason="POSIX signal masks")
def test_children_ignore_sigint_holds_a_ctrl_c_and_children_start_with_it_blocked():
    from sfm_common.workers import children_ignore_sigint

    reached_end = []
    # Python's own Ctrl-C handler, whatever the test was launched under (a background job of a
    # shell without job control starts with SIGINT ignored, and Python then keeps it ignored)
    launched = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            with children_ignore_sigint():
                os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C while processes would be starting
                time.sleep(0.05)
                reached_end.append(True)  # not interrupted inside the block
    finally:
        signal.signal(signal.SIGINT, launched)
    assert reached_end == [True]

    # an ignored SIGINT (a background job) stays ignored: nothing is raised
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with children_ignore_sigint():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
    finally:
        signal.signal(signal.SIGINT, before)

    # a fresh interpreter (no forkserver running yet): a worker of the forkserver started
    # inside the block ignores SIGINT (bit 2 of SigIgn) before any initializer runs
    code = """
import multiprocessing as mp, signal, sys, time
from sfm_common.workers import children_ignore_sigint
if __name__ == "__main__":
    ctx = mp.get_context("forkserver")
    with children_ignore_sigint(ctx):
        c = ctx.Process(target=time.sleep, args=(3,))
        c.start()
    time.sleep(0.5)  # past the forked child's restoring the server's original handlers
    with open(f"/proc/{c.pid}/status") as f:
        st = {l.split(":")[0]: int(l.split()[1], 16) for l in f
              if l.startswith(("SigIgn", "SigBlk"))}
    c.terminate(); c.join()
    bit = 1 << (signal.SIGINT - 1)
    sys.exit(0 if (st["SigIgn"] | st["SigBlk"]) & bit else 1)
"""
    import multiprocessing as mp

    if "forkserver" not in mp.get_all_start_methods() or not os.path.exists("/proc/self/status"):
        return
    assert subprocess.run([sys.executable, "-c", code], timeout=60).returncode == 0
