"""Which features does the linear SfM policy need? (issue: "report which feature set ... and why").

Fits the policy with several feature sets / solvers on 20-episode teacher recordings of MKV-v0
(three training sets: env seeds 0.., 100.., 200..), then measures for each fit

* open loop on held-out teacher runs (MKV-v0 seeds 500..504): drive agreement, steer timing;
* closed loop: escape rate on MKVJam-v0 (seeds 1000..1099), stuck fraction and distance on MKV-v0
  (seeds 1000..1019),

and prints a Markdown table of the means over the three training sets (min..max in brackets for
the escape rate), next to the teacher's numbers on the same seeds. Run:

    .venv/bin/python scripts/sfm_feature_study.py [--quick]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import numpy as np

from mkv_env.recorder import record
from sfm_learn.compare import compare
from sfm_learn.evaluation import evaluate
from sfm_learn.features import FeatureSpec
from sfm_learn.policy import fit_policy

NO_CURRENTS = ("drive_ticks", "roller_ticks", "steer_angle", "compass", "bump_front_left",
               "bump_front_right", "bump_rear", "battery")
NO_BUMPS = ("drive_ticks", "roller_ticks", "steer_angle", "compass", "drive_current",
            "steer_current", "battery")
T = (0.5, 0.8)
CONFIGS = [
    # name, feature kwargs, fit kwargs
    ("sensors only (paper)", {}, {}),
    ("sensors, lstsq solver", {}, {"solver": "lstsq"}),
    ("sensors + prev command", {"prev_action": "signed"}, {}),
    ("sensors + traces", {"trace_decays": T}, {}),
    ("sensors + traces + prev (default)", {"trace_decays": T, "prev_action": "signed"}, {}),
    ("default, lstsq solver", {"trace_decays": T, "prev_action": "signed"}, {"solver": "lstsq"}),
    ("default, one-hot commands", {"trace_decays": T, "prev_action": "signed"},
     {"encoding": "onehot"}),
    ("sensors + 2-step history + prev", {"history": 2, "prev_action": "signed"}, {}),
    ("default without currents", {"channels": NO_CURRENTS, "trace_decays": T,
                                  "prev_action": "signed"}, {}),
    ("default without bumps", {"channels": NO_BUMPS, "trace_decays": T,
                               "prev_action": "signed"}, {}),
]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one training set, fewer eval seeds")
    args = ap.parse_args()
    train_seeds = [0] if args.quick else [0, 100, 200]
    n_jam, n_wander = (40, 5) if args.quick else (100, 20)
    tmp = tempfile.mkdtemp()
    t0 = time.time()
    trains = [record("MKV-v0", "teacher", 20, s) for s in train_seeds]
    held = record("MKV-v0", "teacher", 5, 500)
    teacher_jam = evaluate("MKVJam-v0", "teacher", n_jam, 1000).metrics
    teacher_w = evaluate("MKV-v0", "teacher", n_wander, 1000).metrics
    print(f"recorded {len(trains)} x 20 training episodes; teacher: MKVJam escape "
          f"{teacher_jam['escape_rate']:.2f}, MKV-v0 stuck {teacher_w['stuck_fraction']:.3f}, "
          f"distance {teacher_w['distance_m']:.1f} m ({time.time() - t0:.0f} s)",
          file=sys.stderr)
    names = tuple(trains[0].sensor_names)
    rows = []
    for name, fkw, kw in CONFIGS:
        res = []
        for tr in trains:
            pol = fit_policy(tr, FeatureSpec(obs_names=names, **fkw), **kw)
            m = compare(pol, held).metrics
            ej = evaluate("MKVJam-v0", pol, n_jam, 1000).metrics
            ew = evaluate("MKV-v0", pol, n_wander, 1000).metrics
            res.append((pol.n_components, pol.projector.n_known_, m["drive"], m["steer_timing"],
                        ej["escape_rate"], ew["stuck_fraction"], ew["distance_m"]))
        r = np.array(res, dtype=float)
        rows.append((name, r))
        print(f"{name}: done ({time.time() - t0:.0f} s)", file=sys.stderr)
    print(f"Teacher on the same seeds: MKVJam-v0 escape rate {teacher_jam['escape_rate']:.2f} "
          f"({n_jam} episodes); MKV-v0 stuck fraction {teacher_w['stuck_fraction']:.3f}, "
          f"distance {teacher_w['distance_m']:.1f} m ({n_wander} episodes).\n")
    print("| features / fit | rank n / known | drive agr. | steer timing | MKVJam escape "
          "[min..max] | MKV-v0 stuck | MKV-v0 distance [m] |")
    print("|---|---|---|---|---|---|---|")
    for name, r in rows:
        m = r.mean(axis=0)
        print(f"| {name} | {m[0]:.0f} / {m[1]:.0f} | {m[2]:.3f} | {m[3]:.3f} | {m[4]:.2f} "
              f"[{r[:, 4].min():.2f}..{r[:, 4].max():.2f}] | {m[5]:.3f} | {m[6]:.1f} |")
    print(f"\n{len(train_seeds)} training sets of 20 MKV-v0 teacher episodes (env seeds "
          f"{', '.join(f'{s}..{s + 19}' for s in train_seeds)}); held-out open-loop runs: seeds "
          f"500..504; total {time.time() - t0:.0f} s.")
    os.rmdir(tmp)
    return 0


if __name__ == "__main__":
    sys.exit(main())
