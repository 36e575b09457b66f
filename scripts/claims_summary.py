"""Per learner and budget over training sets, and paired comparisons (issue 26), from a sweep.

    python scripts/claims_summary.py SWEEP_DIR > docs/claims_20_sets.md

Reads ``SWEEP_DIR/rows/*.json`` (``mkv sweep``): escape rate on MKVJam-v1 and distance on
MKV-v1 per (learner, budget, training seed). Prints the mean with a percentile-bootstrap interval
over training sets (2,000 resamples, seeded), the median, the 10th percentile and the failure
rate (escape < 0.8 or distance < 10 m), then paired differences of the escape rate over the same
training sets (and the same evaluation seeds), with "no clear difference" unless the paired
interval excludes 0.
"""

from __future__ import annotations

import collections
import glob
import json
import os
import sys

import numpy as np

PAIRS = (("sfm", "bc"), ("sfm", "dagger"), ("bc", "dagger"), ("sfm", "sfm-ols"),
         ("sfm", "sfm-paper"))


def boot(v, rng, n=2000):
    means = [np.mean(rng.choice(v, len(v))) for _ in range(n)]
    return np.percentile(means, [2.5, 97.5])


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1 or not os.path.isdir(os.path.join(argv[0], "rows")):
        sys.exit("usage: claims_summary.py SWEEP_DIR (a folder with rows/*.json)")
    by = collections.defaultdict(dict)
    for f in glob.glob(os.path.join(argv[0], "rows", "*.json")):
        with open(f) as fh:
            r = json.load(fh)
        if r.get("status") != "ok":
            continue
        m = r["metrics"]
        by[(r["learner"], r["budget"])][r["seed"]] = (m["MKVJam-v1"]["escape_rate"],
                                                      m["MKV-v1"]["distance_m"])
    rng = np.random.default_rng(0)
    print("| learner | budget | sets | escape mean [bootstrap 95%] | median | p10 | distance m "
          "mean | failure rate (escape < 0.8 or distance < 10 m) |")
    print("|---|---|---|---|---|---|---|---|")
    for (learner, budget) in sorted(by):
        d = by[(learner, budget)]
        e = np.array([d[s][0] for s in sorted(d)])
        dist = np.array([d[s][1] for s in sorted(d)])
        lo, hi = boot(e, rng)
        fail = (e < 0.8) | (dist < 10)
        print(f"| {learner} | {budget} | {len(e)} | {e.mean():.3f} [{lo:.3f}, {hi:.3f}] | "
              f"{np.median(e):.3f} | {np.percentile(e, 10):.3f} | {dist.mean():.2f} | "
              f"{fail.mean():.2f} ({int(fail.sum())}/{len(e)}) |")
    print("\n| pair | budget | paired mean difference in escape [bootstrap 95%] | verdict |")
    print("|---|---|---|---|")
    budgets = sorted({b for _, b in by})
    for a, c in PAIRS:
        for b in budgets:
            da, dc = by.get((a, b), {}), by.get((c, b), {})
            seeds = sorted(set(da) & set(dc))
            if not seeds:
                continue
            diff = np.array([da[s][0] - dc[s][0] for s in seeds])
            lo, hi = boot(diff, rng)
            verdict = (f"{a} higher" if lo > 0 else f"{c} higher" if hi < 0
                       else "no clear difference")
            print(f"| {a} - {c} | {b} | {diff.mean():+.3f} [{lo:+.3f}, {hi:+.3f}] "
                  f"(n={len(seeds)}) | {verdict} |")


if __name__ == "__main__":
    main()
