"""Command line: ``calib fit``, ``calib apply``, ``calib trials`` (DESIGN.md section 6).

Bad input ends the command with exit status 2 and one line on stderr, ``calib: error: ...``.
Calibration warnings (poor excitation, hyperboloid, mirror ambiguity) are printed as one line
each, ``calib: warning: ...``, and do not change the exit status.
"""

from __future__ import annotations

import argparse
import sys
import warnings

from sfm_common.cli import OneLineParser, UsageError, int_in_range, one_line, positive_float
from sfm_common.files import check_distinct, check_writable_target

from .result import CalibrationError, CalibrationWarning


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="calib",
                      description="Least-squares and shape-from-motion calibration.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=OneLineParser)

    f = sub.add_parser("fit", help="calibrate from raw readings of a load moved over orientations")
    f.add_argument("raw", metavar="RAW.csv")
    f.add_argument("--dof", type=int, choices=(2, 3, 6), required=True)
    f.add_argument("--bias", action="store_true", help="estimate the sensor offsets too")
    f.add_argument(
        "--known",
        metavar="KNOWN.csv",
        help="known loads: channel columns plus Fx,Fy[,Fz][,Tx,Ty,Tz]",
    )
    f.add_argument(
        "--method",
        choices=("paper", "centered", "joint"),
        default="centered",
        help="bias route (default centered; paper needs p >= r+1 channels; joint fits the "
        "magnitude rows and --known pairs together)",
    )
    f.add_argument("--known-sigma", type=positive_float, metavar="S",
                   help="joint: accuracy of each known load component (load units)")
    f.add_argument("--magnitude-sigma", type=positive_float, metavar="S",
                   help="joint: accuracy of the load magnitude of each row (load units)")
    f.add_argument("--known-samples", type=int_in_range(1, 10**9), metavar="N",
                   help="joint: each known reading averages N readings (1: single readings; "
                   "a rig's samples per pose); instead of --known-sigma")
    f.add_argument(
        "--magnitude",
        type=positive_float,
        help="load magnitude, sets the scale when no known loads are given",
    )
    f.add_argument(
        "--drop-nonfinite",
        action="store_true",
        help="drop rows containing NaN/inf instead of failing (count reported)",
    )
    f.add_argument(
        "--bootstrap",
        metavar="B",
        type=int_in_range(2, 100_000),
        help="add percentile intervals of offset and C from B resampled refits",
    )
    f.add_argument("--seed", type=int_in_range(0, 2**32 - 1), default=0,
                   help="seed of the bootstrap resampling (default 0)")
    f.add_argument("--quiet", action="store_true",
                   help="no progress bars (bootstrap, --chunk-rows passes)")
    f.add_argument("--chunk-rows", metavar="N", type=int_in_range(1, 2**31 - 1),
                   help="stream RAW.csv N rows at a time (never all in memory) through the "
                   "statistics of the fit: for logs larger than memory")
    f.add_argument("--out", metavar="CAL.json", required=True)

    a = sub.add_parser("apply", help="convert raw readings to loads")
    a.add_argument("cal", metavar="CAL.json")
    a.add_argument("raw", metavar="RAW.csv")
    a.add_argument("--drop-nonfinite", action="store_true")
    a.add_argument("--out", metavar="LOADS.csv", required=True)

    t = sub.add_parser("trials", help="the paper's Trials 1-4, Table 1 and figures")
    t.add_argument("--out", metavar="DIR", default="calib_trials")
    t.add_argument("--seeds", type=int_in_range(1, 100_000), default=200,
                   help="seeds per trial (default 200)")
    t.add_argument("--no-plots", action="store_true")
    t.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv=None) -> int:
    """Entry point of the ``calib`` console script; returns the exit status."""
    try:
        args = _parser().parse_args(argv)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", CalibrationWarning)
            if args.command == "fit":
                msg = _fit(args)
            elif args.command == "apply":
                msg = _apply(args)
            else:
                msg = _trials(args)
        for w in caught:
            if issubclass(w.category, CalibrationWarning):
                print(f"calib: warning: {w.message}", file=sys.stderr)
        print(msg)
        return 0
    except UsageError as e:
        print(f"calib: error: {e.prog}: {one_line(e)}", file=sys.stderr)
        return 2
    except (CalibrationError, ValueError) as e:
        print(f"calib: error: {one_line(e)}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"calib: error: {e.filename or ''}: {e.strerror}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("calib: interrupted", file=sys.stderr)
        return 130


def _check_outputs(inputs, out) -> None:
    """The output must not be an input, nor an existing non-regular file (one-line error)."""
    try:
        check_distinct(inputs, [out])
        check_writable_target(out)
    except ValueError as e:
        raise CalibrationError(one_line(e)) from None


def _fit(args) -> str:
    from .bias import fit_bias
    from .ft6 import fit_ft6
    from .io import read_csv, save_calibration, split_known
    from .sfm import fit_sfm

    _check_outputs([args.raw, args.known], args.out)
    if args.method != "joint" or args.dof == 6:
        given = [flag for flag, v in (("--known-sigma", args.known_sigma),
                                      ("--magnitude-sigma", args.magnitude_sigma),
                                      ("--known-samples", args.known_samples)) if v is not None]
        if given:
            raise CalibrationError(f"{given[0]} is an option of --method joint (with --dof 2 or "
                                   "3); without it nothing would use it")
    if args.chunk_rows:
        if args.bootstrap:
            raise CalibrationError("--chunk-rows is not supported with --bootstrap")
        from .io import CSVSource

        # each pass of the fit reads the file again (a bar per pass on a terminal)
        Z = CSVSource(args.raw, args.chunk_rows, progress=not args.quiet)
        channels = Z.header
    else:
        channels, Z = read_csv(args.raw)
    known_Z = known_M = None
    if args.known:
        kh, kd = read_csv(args.known)
        known_Z, known_M = split_known(kh, kd, channels, args.dof)
    if args.dof == 6:
        if known_Z is None:
            raise CalibrationError("--dof 6 needs --known with at least 6 known loads (see docs)")

        def fit(Z, drop=args.drop_nonfinite):
            return fit_ft6(Z, known_Z, known_M, bias=args.bias, method=args.method,
                           drop_nonfinite=drop)
    elif args.method == "joint":
        from .joint import fit_joint

        if known_Z is None:
            raise CalibrationError("--method joint needs --known with at least 2 known loads")

        def fit(Z, drop=args.drop_nonfinite):
            return fit_joint(Z, known_Z, known_M, args.dof, magnitude=args.magnitude,
                             known_sigma=args.known_sigma,
                             magnitude_sigma=args.magnitude_sigma, drop_nonfinite=drop,
                             known_samples=args.known_samples)
    elif args.bias:

        def fit(Z, drop=args.drop_nonfinite):
            return fit_bias(Z, args.dof, method=args.method, known_Z=known_Z, known_M=known_M,
                            magnitude=args.magnitude, drop_nonfinite=drop)
    else:

        def fit(Z, drop=args.drop_nonfinite):
            return fit_sfm(Z, args.dof, known_Z=known_Z, known_M=known_M,
                           magnitude=args.magnitude, drop_nonfinite=drop)
    cal = fit(Z)
    if args.bootstrap:
        from sfm_common.progress import progress as progress_bar

        from ._validate import check_matrix
        from .bootstrap import bootstrap_intervals

        Zc, _ = check_matrix(Z, args.raw, args.drop_nonfinite)
        with progress_bar(args.bootstrap, "bootstrap", unit="fit",
                          enabled=False if args.quiet else None) as bar:
            cal.diagnostics["bootstrap"] = bootstrap_intervals(
                lambda z: fit(z, False), Zc, cal, args.bootstrap, seed=args.seed,
                align=known_Z is None, progress=bar)
    save_calibration(args.out, cal, channels)
    d = cal.diagnostics
    dropped = d.get("n_dropped_nonfinite", 0)
    cov = d.get("coverage") or {}
    note = f", dropped {dropped} non-finite row(s)" if dropped else ""
    return (
        f"wrote {args.out}: {cal.method}, dof {cal.dof}, {cal.n_channels} channels, "
        f"{d.get('n_samples')} samples{note}; rank gap {d.get('rank_gap', float('nan')):.3g}, "
        f"coverage isotropy {cov.get('isotropy', float('nan')):.2f}"
        + (f", offset stderr <= {d['offset_stderr_max_rel_span']:.2%} of span"
           if "offset_stderr_max_rel_span" in d else "")
        + (f", bootstrap {args.bootstrap}" if args.bootstrap else "")
    )


def _apply(args) -> str:
    from ._validate import check_matrix
    from .io import load_calibration, load_columns, read_csv, write_csv

    _check_outputs([args.cal, args.raw], args.out)
    cal, cal_channels = load_calibration(args.cal)
    header, Z = read_csv(args.raw)
    if cal_channels:
        missing = [c for c in cal_channels if c not in header]
        if missing:
            raise CalibrationError(f"{args.raw} lacks calibrated channel(s) {missing}")
        Z = Z[:, [header.index(c) for c in cal_channels]]
    elif Z.shape[1] != cal.n_channels:
        raise CalibrationError(
            f"{args.raw} has {Z.shape[1]} columns, calibration expects {cal.n_channels}"
        )
    Z, dropped = check_matrix(Z, args.raw, args.drop_nonfinite)
    loads = cal.apply(Z)
    write_csv(args.out, load_columns(cal.dof), loads)
    note = f" (dropped {dropped} non-finite row(s))" if dropped else ""
    return f"wrote {args.out}: {len(loads)} rows of {','.join(load_columns(cal.dof))}{note}"


def _trials(args) -> str:
    from .trials import trial_summary, write_report

    res = write_report(args.out, seeds=args.seeds, plots=not args.no_plots, progress=not args.quiet)
    parts = []
    for t in (2, 3, 4):
        s = trial_summary(res["trials"][t], t)
        parts.append(
            f"T{t} offset err {s['centered']['median']:.3g} vs paper {s['paper_reported']:.3g}"
        )
    return f"wrote {args.out}/trials.md; " + "; ".join(parts)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
