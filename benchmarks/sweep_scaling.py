"""Sweep throughput: the local backend with 1 worker against Ray with 2 workers, same 40 jobs.

Each job records teacher data, fits an SfM policy and evaluates it (the sweep's smallest jobs:
the ratio shows what Ray adds on top of real work, not an empty-task overhead). Jobs/s for each,
the ratio (target >= 1.6 on a 2-core machine), per-job cost, and the CPU other processes took
while it ran (a loaded machine under-reports the ratio).

    python benchmarks/sweep_scaling.py [--rounds 2]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time

import psutil

from sfm_learn.experiments import sweep

SPEC = {
    "name": "scaling",
    "teacher_env": "MKV-v1",
    "env": ["MKVJam-v1"],
    "eval": {"episodes": 10, "seed": 6_000_000},
    "seeds": [0, 1, 2, 3],
    "learners": {"sfm": {}, "sfm-paper": {"preset": "paper"}},
    "budgets": {"sfm": [600, 900, 1200, 1500, 1800], "sfm-paper": [600, 900, 1200, 1500, 1800]},
}


def other_cpu(since: dict) -> float:
    """CPU seconds used by processes outside this process tree since ``since``."""
    me = {psutil.Process().pid, *(c.pid for c in psutil.Process().children(recursive=True))}
    total = 0.0
    for p in psutil.process_iter(["pid", "cpu_times"]):
        if p.info["pid"] in me or p.info["cpu_times"] is None:
            continue
        t = p.info["cpu_times"]
        total += (t.user + t.system) - since.get(p.info["pid"], 0.0)
    return total


def cpu_snapshot() -> dict:
    return {p.info["pid"]: p.info["cpu_times"].user + p.info["cpu_times"].system
            for p in psutil.process_iter(["pid", "cpu_times"]) if p.info["cpu_times"]}


def one(backend: str, workers: int) -> tuple[float, float]:
    spec = sweep.check_spec(SPEC)
    with tempfile.TemporaryDirectory() as d:
        snap = cpu_snapshot()
        t0 = time.perf_counter()
        counts = sweep.run_sweep(spec, d, backend=backend, workers=workers)
        wall = time.perf_counter() - t0
        assert counts["ok"] == 40, counts
        return 40 / wall, other_cpu(snap)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    from sfm_learn.evaluation.ray_eval import init_ray

    init_ray(None, 2)   # started once, outside the timing (a cluster is up before a sweep)
    local, on_ray, other = [], [], []
    for r in range(args.rounds):   # alternating rounds
        rate, oc = one("local", 1)
        local.append(rate)
        other.append(oc)
        rate, oc = one("ray", 2)
        on_ray.append(rate)
        other.append(oc)
        print(f"round {r}: local 1 worker {local[-1]:.2f} jobs/s, ray 2 workers "
              f"{on_ray[-1]:.2f} jobs/s", flush=True)
    lm, rm = statistics.median(local), statistics.median(on_ray)
    print(f"median: local 1 worker {lm:.2f} jobs/s ({1 / lm:.2f} s/job), ray 2 workers "
          f"{rm:.2f} jobs/s: ratio {rm / lm:.2f} (target >= 1.6); other processes' CPU "
          f"during the runs: {statistics.median(other):.1f} s per run (median)")


if __name__ == "__main__":
    main()
