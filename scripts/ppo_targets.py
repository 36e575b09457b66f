"""The PPO targets, checked on the rows of a sample-efficiency sweep.

    python scripts/ppo_targets.py SWEEP_DIR [--seeds 3]

* MKVJam-v1: escape rate >= 0.8, median over the first ``--seeds`` PPO seeds, within 1,000,000
  env steps (the first budget where it holds is printed);
* MKV-v1: distance >= 0.7x the teacher's and stuck fraction <= 2x the teacher's (the teacher
  measured here on the sweep's own evaluation seeds and episode count).

Prints every seed's value, so a median that hides a failed seed is visible.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
from collections import defaultdict

import mkv_env  # noqa: F401
from sfm_learn.evaluation import evaluate
from sfm_learn.experiments.sweep import read_rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sweep_dir")
    ap.add_argument("--seeds", type=int, default=3, help="PPO seeds the median is over")
    args = ap.parse_args()
    with open(os.path.join(args.sweep_dir, "spec.json"), encoding="utf-8") as f:
        spec = json.load(f)
    seeds = spec["seeds"][: args.seeds]
    ev = spec["eval"]
    rows = [r for r in read_rows(args.sweep_dir) if r.get("status") == "ok"]
    by = defaultdict(dict)   # (learner, env, metric) -> {budget: {seed: value}}
    for r in rows:
        if r["kind"] != "ppo" or r["seed"] not in seeds:
            continue
        for env_id, m in r["metrics"].items():
            for k, v in m.items():
                by[(r["learner"], env_id, k)].setdefault(r["budget"], {})[r["seed"]] = v
    teacher = evaluate("MKV-v1", "teacher", ev["episodes"], ev["seed"], n_boot=0).metrics
    print(f"teacher on MKV-v1 ({ev['episodes']} episodes, seeds {ev['seed']}..): distance "
          f"{teacher['distance_m']:.2f} m, stuck fraction {teacher['stuck_fraction']:.4f}")

    def show(learner, env_id, metric, ok, target):
        first = None
        for b, vals in sorted(by.get((learner, env_id, metric), {}).items()):
            if len(vals) < len(seeds):
                print(f"  {b:>9,} steps: only seeds {sorted(vals)} finished")
                continue
            med = statistics.median(vals.values())
            hit = ok(med)
            first = first or (b if hit else None)
            print(f"  {b:>9,} steps: median {med:.4f} "
                  f"(seeds {', '.join(f'{s}: {v:.4f}' for s, v in sorted(vals.items()))})"
                  f"{'  <- meets ' + target if hit else ''}")
        return first

    for learner in [n for n, lr in spec["learners"].items() if lr["kind"] == "ppo"]:
        for env_id, metric, ok, target in (
                ("MKVJam-v1", "escape_rate", lambda v: v >= 0.8, "escape >= 0.8"),
                ("MKV-v1", "distance_m", lambda v: v >= 0.7 * teacher["distance_m"],
                 f"distance >= {0.7 * teacher['distance_m']:.2f} m"),
                ("MKV-v1", "stuck_fraction", lambda v: v <= 2 * teacher["stuck_fraction"],
                 f"stuck <= {2 * teacher['stuck_fraction']:.4f}")):
            if (learner, env_id, metric) not in by:
                continue
            print(f"{learner}, {metric} on {env_id}, median of seeds {seeds}:")
            first = show(learner, env_id, metric, ok, target)
            print(f"  -> {target}: " + (f"first met at {first:,} env steps" if first
                                        else "not met at any budget"))


if __name__ == "__main__":
    main()
