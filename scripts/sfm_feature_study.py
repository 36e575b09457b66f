"""Which features does the linear SfM policy need? (issue: "report which feature set ... and why").

Fits the policy with every configuration of :data:`sfm_learn.evaluation.study.CONFIGS` on three
20-episode
teacher recordings of MKV-v0 (env seeds 0.., 100.., 200..) and measures open-loop agreement on
held-out runs (seeds 500..504) and the closed loop (MKVJam-v0 seeds 1000..1099, MKV-v0 seeds
1000..1019); prints a Markdown table of means over the training sets next to the teacher's numbers
on the same seeds (the table in docs/sfm.md). Run:

    .venv/bin/python scripts/sfm_feature_study.py [--quick]
"""

from __future__ import annotations

import argparse
import sys
import time

from mkv_env.recorder import record
from sfm_learn.evaluation import evaluate
from sfm_learn.evaluation.study import feature_study
from sfm_learn.reporting.tables import study_markdown


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one training set, fewer eval seeds")
    args = ap.parse_args()
    train_seeds = [0] if args.quick else [0, 100, 200]
    n_jam, n_wander = (40, 5) if args.quick else (100, 20)
    t0 = time.time()
    trains = [record("MKV-v0", "teacher", 20, s) for s in train_seeds]
    held = record("MKV-v0", "teacher", 5, 500)
    teacher_jam = evaluate("MKVJam-v0", "teacher", n_jam, 1000).metrics
    teacher_w = evaluate("MKV-v0", "teacher", n_wander, 1000).metrics
    rows = feature_study(trains, held, jam_episodes=n_jam, wander_episodes=n_wander,
                         on_config=lambda name: print(f"{name}: done ({time.time() - t0:.0f} s)",
                                                      file=sys.stderr))
    print(f"Teacher on the same seeds: MKVJam-v0 escape rate {teacher_jam['escape_rate']:.2f} "
          f"({n_jam} episodes); MKV-v0 stuck fraction {teacher_w['stuck_fraction']:.3f}, "
          f"distance {teacher_w['distance_m']:.1f} m ({n_wander} episodes).\n")
    print(study_markdown(rows))
    print(f"\n{len(train_seeds)} training sets of 20 MKV-v0 teacher episodes (env seeds "
          f"{', '.join(f'{s}..{s + 19}' for s in train_seeds)}); held-out open-loop runs: seeds "
          f"500..504; total {time.time() - t0:.0f} s.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
