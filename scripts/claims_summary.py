"""Per learner and budget over training sets, and paired comparisons, from sweeps.

    python scripts/claims_summary.py SWEEP_DIR [SWEEP_DIR ...] > docs/claims_20_sets.md
    python scripts/claims_summary.py --bundle OUT.json SWEEP_DIR [SWEEP_DIR ...]

Reads ``SWEEP_DIR/rows/*.json`` (``mkv sweep``) and prints the tables and the claim sentences of
:mod:`sfm_learn.experiments.claims`. ``--bundle`` instead writes the rows (policy paths dropped)
with the specs as the package's reference file (``sfm_learn/experiments/reference/claims.json``),
from which ``mkv demo`` and the README's claims are generated.
"""

from __future__ import annotations

import argparse
import datetime
import glob
import json
import os
import sys

from sfm_common.files import atomic_write_text
from sfm_learn.experiments.claims import claim_sentences, tables


def read_rows(folder: str) -> list[dict]:
    if not os.path.isdir(os.path.join(folder, "rows")):
        sys.exit(f"claims_summary.py: {folder} has no rows/ folder (a mkv sweep --out folder)")
    rows = []
    for f in sorted(glob.glob(os.path.join(folder, "rows", "*.json"))):
        with open(f, encoding="utf-8") as fh:
            r = json.load(fh)
        r.pop("policy", None)
        rows.append(r)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sweeps", nargs="+", metavar="SWEEP_DIR")
    ap.add_argument("--bundle", metavar="OUT.json", help="write the reference bundle instead")
    args = ap.parse_args(argv)
    rows, specs = [], []
    for d in args.sweeps:
        rows += read_rows(d)
        with open(os.path.join(d, "spec.json"), encoding="utf-8") as fh:
            specs.append(json.load(fh))
    if args.bundle:
        from sfm_learn.evaluation import evaluate

        ev = specs[0]["eval"]
        if any(s["eval"] != ev for s in specs):
            sys.exit("claims_summary.py: the sweeps were evaluated on different seeds")
        teacher = {e: {k: v for k, v in evaluate(e, "teacher", ev["episodes"], ev["seed"],
                                                  workers=2).metrics.items()}
                   for e in sorted({e for s in specs for e in s["env"]})}
        about = (f"Rows of {', '.join(s.get('name', '?') for s in specs)}, run with "
                 f"`mkv sweep ... --workers 2` on a 2-core machine on "
                 f"{datetime.date.today().isoformat()} (policy paths dropped). The README's and "
                 "`mkv demo`'s claims are generated from them by sfm_learn.experiments.claims.")
        atomic_write_text(args.bundle, json.dumps({"about": about, "specs": specs, "rows": rows,
                                                   "teacher": teacher},
                                                  indent=1, sort_keys=True) + "\n")
        print(f"wrote {args.bundle}: {len(rows)} rows")
        return 0
    print(tables(rows))
    print("\n".join(claim_sentences(rows)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
