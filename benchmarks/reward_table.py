"""Returns of the teacher and of degenerate policies: does an MK-V reward encode the task?

A reward encodes the task when the intended behaviour (the scripted teacher: wander, back out of
jams) earns clearly the most and the degenerate behaviours (standing still, circling forever,
reversing forever) clearly the least. Each policy runs the same seeded episodes (never used for
training or tuning: seeds 3,000,000..); mean return with its 95% bootstrap interval, plus distance,
stuck fraction and escape rate.

    python benchmarks/reward_table.py [--episodes 100] [--workers 2] [--out docs/rewards.md]
"""

from __future__ import annotations

import argparse

import mkv_env  # noqa: F401  (registers the ids)
from sfm_learn.evaluation import evaluate_many

POLICIES = [("teacher", "teacher"), ("random", "random"), ("stand still", "const:still"),
            ("circle forever", "const:circle"), ("reverse forever", "const:reverse"),
            ("forward forever", "const:forward")]
ENVS = ["MKV-v1", "MKVJam-v1", "MKV-v0", "MKVJam-v0"]
SEED = 3_000_000


def table(env_id: str, episodes: int, workers: int) -> list[str]:
    evs = evaluate_many(env_id, [s for _, s in POLICIES], episodes, SEED, workers=workers)
    lines = [f"### {env_id}", "",
             "| policy | mean return [95% CI] | distance m | stuck fraction | escape rate |",
             "|---|---|---|---|---|"]
    for (name, _), ev in zip(POLICIES, evs, strict=True):
        m, ci = ev.metrics, ev.metrics_ci
        lo, hi = ci["mean_return"]
        esc = "-" if m.get("escape_rate") is None else f"{m['escape_rate']:.2f}"
        lines.append(f"| {name} | {m['mean_return']:.2f} [{lo:.2f}, {hi:.2f}] | "
                     f"{m['distance_m']:.2f} | {m['stuck_fraction']:.3f} | {esc} |")
    return lines + [""]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--envs", nargs="+", default=ENVS)
    args = ap.parse_args()
    for env_id in args.envs:
        print("\n".join(table(env_id, args.episodes, args.workers)), flush=True)


if __name__ == "__main__":
    main()
