"""Evaluation worker processes: episodes per second of ``evaluate_many`` with 1 and 2 workers.

The scripted teacher on ``MKVJam-v0`` (``--jam-episodes``, short jam episodes) and on ``MKV-v0``
(``--episodes``, 60 s episodes), each measured with ``workers=1`` (in this process) and
``workers=2`` (worker processes, start-up and IPC included: the first 2-worker run also starts the
forkserver, as a one-shot ``mkv eval`` does) in the same run, alternating. The records of the two
must be identical. Target: 2 workers >= 1.7x the episodes per second of 1 on each env.

``--start-methods`` also times a tiny 2-worker evaluation (pool start-up and tear-down) with each
multiprocessing start method, each in a fresh interpreter (cold, as ``mkv eval`` is).

On a shared machine other jobs' load distorts the ratio: for every run the CPU time other jobs
took meanwhile is printed (Linux ``/proc/stat``), and so is the CPU time of all our processes
(the 2-worker runs' extra CPU time is their real overhead: start-up, IPC, smaller units).
``--rounds`` (2) alternating rounds; the best time of each is kept.

    python benchmarks/eval_workers.py [--jam-episodes 2400] [--episodes 300] [--rounds 2]
                                      [--start-methods]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

from sfm_learn.evaluation.runner import default_start_method, evaluate_many

TARGET = 1.7

_STARTUP_SNIPPET = """
import sys, time
t0 = time.perf_counter()
from sfm_learn.evaluation import evaluate_many
t1 = time.perf_counter()
evaluate_many("MKV-v0", ["teacher"], 8, 0, {"max_episode_steps": 2}, workers=2,
              start_method=sys.argv[1], n_boot=10)
print(f"{time.perf_counter() - t1:.3f}")
"""


def cpu_seconds() -> float:
    """CPU time of this process and every process it started (workers too: reaped by us with
    ``fork``, by the forkserver, a child of ours, otherwise; the latter needs psutil)."""
    t = os.times()
    total = t.user + t.system + t.children_user + t.children_system
    try:
        import psutil
    except ImportError:
        return total
    for child in psutil.Process().children():
        try:
            c = child.cpu_times()
            total += c.user + c.system + c.children_user + c.children_system
        except psutil.Error:
            pass
    return total


def machine_busy_seconds() -> float:
    """CPU seconds all processes on the machine have used since boot (Linux /proc/stat; NaN
    elsewhere): compared with our own, it shows how much other jobs took during a run."""
    try:
        with open("/proc/stat") as f:
            fields = [int(x) for x in f.readline().split()[1:]]
    except (OSError, ValueError):
        return float("nan")
    user, nice, system, idle, iowait, irq, softirq, steal = (fields + [0] * 8)[:8]
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def timed(env_id: str, episodes: int, workers: int, start_method: str | None):
    """Wall seconds, our CPU seconds (all our processes), other jobs' CPU seconds, and the
    evaluation."""
    m0, c0, t0 = machine_busy_seconds(), cpu_seconds(), time.perf_counter()
    ev = evaluate_many(env_id, ["teacher"], episodes, seed=0, workers=workers,
                       start_method=start_method)[0]
    wall, ours = time.perf_counter() - t0, cpu_seconds() - c0
    others = max(0.0, machine_busy_seconds() - m0 - ours)
    return wall, ours, others, ev


def startup_seconds(method: str) -> float:
    """Seconds for a tiny 2-worker evaluation in a fresh interpreter (after imports)."""
    out = subprocess.run([sys.executable, "-c", _STARTUP_SNIPPET, method], check=True,
                         capture_output=True, text=True).stdout
    return float(out.strip().splitlines()[-1])


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jam-episodes", type=int, default=2400, help="MKVJam-v0 episodes")
    ap.add_argument("--episodes", type=int, default=300, help="MKV-v0 episodes")
    ap.add_argument("--rounds", type=int, default=2, help="alternating rounds; best of each")
    ap.add_argument("--start-method", default=None,
                    help=f"multiprocessing start method (default {default_start_method()})")
    ap.add_argument("--start-methods", action="store_true",
                    help="also time pool start-up with fork, forkserver and spawn")
    args = ap.parse_args(argv)

    print(f"{os.cpu_count()} CPUs, load average before: {load()}; start method "
          f"{args.start_method or default_start_method()}")
    envs = (("MKVJam-v0", args.jam_episodes), ("MKV-v0", args.episodes))
    best = {(env_id, w): float("inf") for env_id, _ in envs for w in (1, 2)}
    cpu = {}
    steps = {}
    ok = True
    for r in range(args.rounds):  # alternate, so that other jobs' load hits both alike
        for env_id, n in envs:
            recs = {}
            for w in (1, 2):
                dt, dc, other, ev = timed(env_id, n, w, args.start_method)
                if dt < best[env_id, w]:
                    best[env_id, w], cpu[env_id, w] = dt, dc
                recs[w] = ev.records
                print(f"round {r + 1}: {env_id:<10} {w} worker{'s' * (w > 1)}: {dt:6.2f} s "
                      f"({n / dt:6.1f} episodes/s), CPU s: ours {dc:6.2f}, other jobs' "
                      f"{other:6.2f} (= {other / dt:.2f} cores)")
            if recs[1] != recs[2]:
                print(f"{env_id}: records differ between 1 and 2 workers")
                ok = False
            steps[env_id] = sum(x.steps for x in recs[1])
    rows = [(env_id, n, steps[env_id], best[env_id, 1], best[env_id, 2]) for env_id, n in envs]
    print(f"load average after: {load()}")
    print()
    print(f"{'env':<11}{'episodes':>9}{'steps':>9}{'1 worker':>10}{'ep/s':>8}"
          f"{'2 workers':>11}{'ep/s':>8}{'ratio':>7}")
    for env_id, n, n_steps, t1, t2 in rows:
        ratio = t1 / t2
        ok &= ratio >= TARGET
        print(f"{env_id:<11}{n:>9}{n_steps:>9}{t1:>9.2f}s{n / t1:>8.1f}{t2:>10.2f}s{n / t2:>8.1f}"
              f"{ratio:>7.2f}")
    print("CPU seconds (all processes) of those runs, 1 worker vs 2 workers: "
          + ", ".join(f"{e} {cpu[e, 1]:.2f} vs {cpu[e, 2]:.2f} "
                      f"({100 * (cpu[e, 2] / cpu[e, 1] - 1):+.0f}%)" for e, _ in envs)
          + "; with 2 idle cores the ratio would be about 2 x 1-worker CPU / 2-worker CPU.")
    ratios = ", ".join(f"{r[0]} {r[3] / r[4]:.2f}x" for r in rows)
    print(f"2 workers / 1 worker, episodes per second: {ratios}  (target >= {TARGET}: "
          f"{'met' if ok else 'MISSED'})")

    if args.start_methods:
        print()
        print("tiny 2-worker evaluation (8 two-step episodes) in a fresh interpreter, "
              "after imports:")
        import multiprocessing as mp

        for method in mp.get_all_start_methods():
            times = [startup_seconds(method) for _ in range(3)]
            print(f"  {method:<11} best {min(times):.3f} s  (all: "
                  + ", ".join(f"{t:.3f}" for t in times) + ")")
    return 0  # a benchmark reports (met / MISSED above); it fails only when it cannot measure


if __name__ == "__main__":
    sys.exit(main())
