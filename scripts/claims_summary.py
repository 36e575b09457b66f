"""Per learner and budget over training sets, and paired comparisons, from sweeps.

    python scripts/claims_summary.py SWEEP_DIR [SWEEP_DIR ...] > docs/claims_20_sets.md
    python scripts/claims_summary.py --bundle OUT.json SWEEP_DIR [SWEEP_DIR ...]
    python scripts/claims_summary.py SWEEP_DIR [...] --check CHECK_DIR [CHECK_DIR ...]
    python scripts/claims_summary.py --bundled [--check CHECK_DIR ...]   # the published rows

Reads ``SWEEP_DIR/rows/*.json`` (``mkv sweep``) and prints the tables and the claim sentences of
:mod:`sfm_learn.experiments.claims`. ``--bundle`` instead writes the rows (policy paths dropped)
with the specs as the package's reference file (``sfm_learn/experiments/reference/claims.json``),
from which ``mkv demo`` and the README's claims are generated. ``--check`` instead compares the
claims of SWEEP_DIR with a check sweep's rows (the same spec on new training seeds and a new
evaluation bank): which published levels' intervals cover the check's values, which published
rankings held (:func:`sfm_learn.experiments.claims.check`).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys

from sfm_common.files import atomic_write_text
from sfm_learn.experiments.claims import check, check_report, claim_sentences, tables


def read_rows(folder: str) -> list[dict]:
    """The usable rows of a ``mkv sweep --out`` folder (:func:`sfm_learn.experiments.sweep.
    read_rows`: regular files only, damaged ones named on stderr and left out), policy paths
    dropped."""
    from sfm_learn.experiments.sweep import read_rows as sweep_rows

    if not os.path.isdir(os.path.join(folder, "rows")):
        sys.exit(f"claims_summary.py: {folder} has no rows/ folder (a mkv sweep --out folder)")
    damaged: list = []
    rows = sweep_rows(folder, damaged)
    for name, why in damaged:
        print(f"claims_summary.py: {folder}/rows/{name} left out: {why}", file=sys.stderr)
    for r in rows:
        r.pop("policy", None)
        r.pop("_file", None)
    return rows


def read_spec(folder: str) -> dict:
    path = os.path.join(folder, "spec.json")
    if not os.path.isfile(path):
        sys.exit(f"claims_summary.py: {folder} has no spec.json (a mkv sweep --out folder)")
    try:
        with open(path, encoding="utf-8") as fh:
            spec = json.load(fh)
    except (OSError, ValueError) as e:
        sys.exit(f"claims_summary.py: {path} is not a sweep spec ({type(e).__name__})")
    if not isinstance(spec, dict) or not isinstance(spec.get("eval"), dict):
        sys.exit(f"claims_summary.py: {path} is not a sweep spec")
    return spec


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sweeps", nargs="*", metavar="SWEEP_DIR",
                    help="mkv sweep --out folders (default with --bundled: none)")
    ap.add_argument("--bundled", action="store_true",
                    help="the package's bundled claims rows (the published ones) as SWEEP_DIR")
    ap.add_argument("--bundle", metavar="OUT.json", help="write the reference bundle instead")
    ap.add_argument("--check", nargs="+", metavar="CHECK_DIR",
                    help="compare the claims with a check sweep's rows instead")
    args = ap.parse_args(argv)
    if args.check and args.bundle:
        ap.error("--check and --bundle do not go together")
    if not args.sweeps and not args.bundled:
        ap.error("give SWEEP_DIR or --bundled")
    if args.bundled and args.bundle:
        ap.error("--bundled rows are already the bundle")
    rows, specs = [], []
    if args.bundled:
        from sfm_learn.experiments.claims import load_reference

        doc = load_reference()
        rows, specs = list(doc["rows"]), list(doc["specs"])
    for d in args.sweeps:
        rows += read_rows(d)
        specs.append(read_spec(d))
    if args.check:
        print(check_report(check(rows, [r for d in args.check for r in read_rows(d)])))
        return 0
    if args.bundle:
        from sfm_learn.evaluation import evaluate
        from sfm_learn.evaluation.records import aggregate
        from sfm_learn.experiments.sweep import bank_seeds

        ev = specs[0]["eval"]  # the teacher on the first sweep's episodes (every bank)
        teacher = {}
        for e in sorted({e for s in specs for e in s["env"]}):
            records = [r for first in bank_seeds(ev)
                       for r in evaluate(e, "teacher", ev["episodes"], first, workers=2).records]
            teacher[e] = aggregate(records)
        about = (f"Rows of {', '.join(s.get('name', '?') for s in specs)}, run with "
                 f"`mkv sweep ... --workers 2` on a 2-core machine on "
                 f"{datetime.date.today().isoformat()} (policy paths dropped). The README's and "
                 "`mkv demo`'s claims are generated from them by sfm_learn.experiments.claims.")
        atomic_write_text(args.bundle, json.dumps({"about": about, "specs": specs, "rows": rows,
                                                   "teacher": teacher, "teacher_eval": ev},
                                                  indent=1, sort_keys=True) + "\n")
        print(f"wrote {args.bundle}: {len(rows)} rows")
        return 0
    print(tables(rows))
    print("\n".join(claim_sentences(rows)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
