"""The SfM studies of docs/sfm.md: feature sets, the paper's configuration, OLS, and the kept rank,
each over several teacher training sets, evaluated on env seeds never used while developing.

    .venv/bin/python scripts/sfm_study.py [--sets 5] [--jam 100] [--wander 20] [--workers 2]
                                          [--out study_out] [--quick]

Writes OUT/features.md, OUT/rank_default.md, OUT/rank_paper.md, OUT/rank_study.png and
OUT/summary.json (means, [min..max], the teacher on the same seeds), and prints the tables.
Training sets: 20 MKV-v1 teacher episodes each, env seeds 0.., 100.., 200.., ...; held-out runs
500..504; evaluation env seeds 2,000,000.. (the demo's).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

from mkv_env.recorder import record
from sfm_common.files import atomic_write_text
from sfm_common.progress import progress
from sfm_learn.evaluation import evaluate
from sfm_learn.evaluation.study import COLUMNS, FEATURE_CONFIGS, rank_configs, run_study
from sfm_learn.reporting.plots import plot_rank_study
from sfm_learn.reporting.tables import study_markdown


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", type=int, default=5, help="training sets (default 5)")
    ap.add_argument("--jam", type=int, default=100, help="MKVJam-v1 episodes per fit")
    ap.add_argument("--wander", type=int, default=20, help="MKV-v1 episodes per fit")
    ap.add_argument("--seed", type=int, default=2_000_000, help="first evaluation env seed")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default="study_out")
    ap.add_argument("--quick", action="store_true", help="2 sets, few episodes, few ranks")
    args = ap.parse_args()
    if args.quick:
        args.sets, args.jam, args.wander = 2, 10, 2
    os.makedirs(args.out, exist_ok=True)
    t0 = time.time()
    trains = [record("MKV-v1", "teacher", 20, 100 * k) for k in range(args.sets)]
    held = record("MKV-v1", "teacher", 5, 500)
    names = trains[0].sensor_names
    teacher_jam = evaluate("MKVJam-v1", "teacher", args.jam, args.seed, n_boot=0).metrics
    teacher_w = evaluate("MKV-v1", "teacher", args.wander, args.seed, n_boot=0).metrics
    ranks = (1, 8, 30) if args.quick else None
    jobs = {"features": list(FEATURE_CONFIGS),
            "rank_default": rank_configs(names, "default", ranks),
            "rank_paper": rank_configs(names, "paper", ranks)}
    total = sum(len(c) for c in jobs.values()) * args.sets * (args.jam + args.wander)
    results = {}
    with progress(total, "studies", unit="ep") as bar:
        for key, configs in jobs.items():
            results[key] = run_study(trains, held, configs, jam_episodes=args.jam,
                                     wander_episodes=args.wander, seed=args.seed,
                                     workers=args.workers, on_episode=lambda: bar.update(1))
            text = study_markdown(results[key])
            atomic_write_text(os.path.join(args.out, f"{key}.md"), text + "\n")
            print(f"\n{key} ({time.time() - t0:.0f} s)\n{text}", flush=True)
    plot_rank_study({"default": results["rank_default"], "paper": results["rank_paper"]},
                    os.path.join(args.out, "rank_study.png"),
                    teacher={"escape_rate": teacher_jam["escape_rate"],
                             "distance_m": teacher_w["distance_m"]},
                    title=f"Kept rank n: mean over {args.sets} training sets, [min, max] shaded;"
                          f" env seeds {args.seed}..")
    summary = {
        "teacher": {"escape_rate": teacher_jam["escape_rate"],
                    "distance_m": teacher_w["distance_m"],
                    "stuck_fraction": teacher_w["stuck_fraction"]},
        "training_seeds": [100 * k for k in range(args.sets)],
        "eval_seed": args.seed, "jam_episodes": args.jam, "wander_episodes": args.wander,
        "studies": {key: {c.key: {col: res.values[i, :, j].tolist()
                                  for j, col in enumerate(COLUMNS)} | {
                                      "rule_rank": res.rule_rank[i].tolist()}
                          for i, c in enumerate(res.configs)}
                    for key, res in results.items()},
    }
    atomic_write_text(os.path.join(args.out, "summary.json"), json.dumps(summary, indent=1))
    print(f"\nTeacher on the same seeds: MKVJam-v1 escape rate {teacher_jam['escape_rate']:.3f} "
          f"({args.jam} episodes); MKV-v1 distance {teacher_w['distance_m']:.1f} m, stuck "
          f"{teacher_w['stuck_fraction']:.3f} ({args.wander} episodes). {time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
