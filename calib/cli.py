"""Command line: ``calib fit``, ``apply``, ``evaluate``, ``plan``, ``trials`` (docs/design.md
section 6).

Bad input ends the command with exit status 2 and one line on stderr, ``calib: error: ...``.
Calibration warnings (poor excitation, hyperboloid, mirror ambiguity) are printed as one line
each, ``calib: warning: ...``, and do not change the exit status. A fit that
:func:`calib.verdict.reliability.assess` finds unreliable (not converged, implausible magnitude or
known residuals, failed held-out check) ends with exit status 3 and one line, ``calib: unreliable:
...``, and writes nothing, unless ``--allow-unreliable`` (then it is written, the reasons are
warnings and in ``diagnostics["reliability"]``).
"""

from __future__ import annotations

import argparse
import sys
import warnings

import numpy as np

from calib.data.result import CalibrationError, CalibrationWarning
from sfm_common.cli import (
    OneLineParser,
    UsageError,
    caused_by_interrupt,
    int_in_range,
    interrupts_not_lost,
    one_line,
    positive_float,
)
from sfm_common.files import check_distinct, check_writable_target


class Unreliable(Exception):
    """The fit ran but is unreliable (exit status 3)."""


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="calib",
                      description="Least-squares and shape-from-motion calibration.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=OneLineParser,
                           help="the command to run (calib COMMAND --help lists its options)")

    f = sub.add_parser("fit", help="calibrate from raw readings of a load moved over orientations")
    f.add_argument("raw", metavar="RAW.csv",
                   help="raw readings: a header of channel names, one row per reading (with "
                   "--method least_squares also each row's load columns)")
    f.add_argument("--dof", type=int, choices=(2, 3, 6), required=True,
                   help="load components: 2 (Fx,Fy), 3 (Fx,Fy,Fz) or 6 (Fx..Tz: needs --known "
                   "with at least 6 known loads, or --method least_squares)")
    f.add_argument("--bias", action="store_true", help="estimate the sensor offsets too")
    f.add_argument(
        "--known",
        metavar="KNOWN.csv",
        help="known loads: channel columns plus Fx,Fy[,Fz][,Tx,Ty,Tz]",
    )
    f.add_argument(
        "--method",
        choices=("paper", "centered", "joint", "least_squares"),
        default=None,
        help="bias route. Default: joint (the maximum-likelihood fit of the magnitude rows and "
        "the --known pairs together) with --bias, --dof 2 or 3 and at least 2 known loads; "
        "centered otherwise. centered and paper (needs p >= r+1 channels) are the closed-form "
        "shape-from-motion routes; least_squares: every row of RAW.csv has its load in "
        "Fx,Fy[,Fz][,Tx,Ty,Tz] columns",
    )
    f.add_argument("--cv", choices=("poses",),
                   help="poses: leave-one-pose-out error over the known poses (joint, "
                   "least_squares), in the summary and diagnostics['cv_poses']")
    f.add_argument("--model", choices=("affine", "channel", "quadratic", "auto"), default=None,
                   help="least_squares and joint on static poses: affine, every channel "
                   "straightened by its own square, a free square per channel, or auto "
                   "(default: the lowest leave-one-pose-out error of the identifiable ones)")
    f.add_argument("--drift", choices=("none", "linear", "auto"), default=None,
                   help="least_squares and joint on static poses: a load drift linear in the "
                   "row order (joint: each row at its pose's mean time, so creep within a pose "
                   "is not drift), fitted and then dropped (default: auto, as --model, for "
                   "least_squares; none for joint, whose few known poses cannot choose it "
                   "reliably: docs/calib.md)")
    f.add_argument("--robust", action="store_true",
                   help="joint and least_squares on static poses: leave out rows more than 5 "
                   "robust standard deviations from their pose's median (spikes); joint on "
                   "logs without static poses: leave out readings far from the fitted model")
    f.add_argument("--allow-unreliable", action="store_true",
                   help="write a fit that the reliability checks reject (exit 0, warnings)")
    f.add_argument("--holdout-factor", type=positive_float, metavar="F", default=None,
                   help="held-out check: leave-one-pose-out rms may be at most F times the "
                   "in-sample residual (default 20)")
    f.add_argument("--known-sigma", type=positive_float, metavar="S",
                   help="joint: accuracy of each stated load component (load units; a "
                   "robot's kinematics): weighs the known loads, widens the predicted held-out "
                   "error")
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
    f.add_argument("--out", metavar="CAL.json", required=True,
                   help="calibration to write (JSON: the fit, the channel names, its "
                   "diagnostics); not written when unreliable unless --allow-unreliable")

    a = sub.add_parser("apply", help="convert raw readings to loads")
    a.add_argument("cal", metavar="CAL.json", help="calibration written by calib fit")
    a.add_argument("raw", metavar="RAW.csv",
                   help="raw readings with a header; the calibrated channels are picked by "
                   "name, other columns ignored (a CAL.json without channel names: "
                   "exactly its channel columns, in order)")
    a.add_argument("--drop-nonfinite", action="store_true",
                   help="drop readings with NaN/inf in a calibrated channel instead of "
                   "failing (LOADS.csv then has fewer rows; count reported)")
    a.add_argument("--out", metavar="LOADS.csv", required=True,
                   help="loads to write, one row per reading: columns Fx,Fy[,Fz][,Tx,Ty,Tz] "
                   "by the calibration's dof")

    e = sub.add_parser("evaluate", help="held-out load error of a calibration on test readings")
    e.add_argument("cal", metavar="CAL.json", help="calibration written by calib fit")
    e.add_argument("test", metavar="TEST.csv",
                   help="readings; with load columns (Fx,Fy[,Fz]...) each row's load, "
                   "else --known gives the loads of its poses")
    e.add_argument("--known", metavar="KNOWN.csv",
                   help="pose readings and loads: each static pose of TEST.csv takes the load "
                   "of the known reading it lies nearest to")
    e.add_argument("--drop-nonfinite", action="store_true",
                   help="drop rows of TEST.csv with NaN/inf in any column instead of failing "
                   "(count reported)")

    pl = sub.add_parser("plan", help="which rig poses get the known loads, and the accuracy "
                        "to expect (Cramer-Rao bound)")
    pl.add_argument("poses", metavar="POSES.csv",
                    help="candidate pose directions: columns Fx,Fy,Fz (or ux,uy,uz), one row "
                    "per pose")
    pl.add_argument("--known-loads", type=int_in_range(2, 199), default=4, metavar="K",
                    help="how many poses get a known load (default 4)")
    pl.add_argument("--samples", type=int_in_range(1, 10**7), default=100, metavar="N",
                    help="readings per pose (default 100)")
    pl.add_argument("--magnitude", type=positive_float, default=1.0,
                    help="load magnitude (default 1)")
    pl.add_argument("--noise", type=positive_float, metavar="S",
                    help="per-reading noise (counts); with --sensitivity: absolute errors")
    pl.add_argument("--sensitivity", type=positive_float, metavar="G",
                    help="counts per load unit of the sensor (isotropic model)")

    t = sub.add_parser("trials", help="the paper's Trials 1-4, Table 1 and figures")
    t.add_argument("--out", metavar="DIR", default="calib_trials",
                   help="folder for trials.md and the figures, created if missing (default "
                   "calib_trials)")
    t.add_argument("--seeds", type=int_in_range(1, 100_000), default=200,
                   help="seeds per trial (default 200)")
    t.add_argument("--no-plots", action="store_true",
                   help="write trials.md only, no PNG figures (they need matplotlib)")
    t.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _named(message, args) -> str:
    """A fit's message with each ``channel N`` (an index into the fitted log's channels) given
    its name from the CSV header: ``channel 2 (g3)``."""
    import re

    names = getattr(args, "channel_names", None)
    text = str(message)
    if not names:
        return text

    def name(m):
        i = int(m.group(1))
        return f"{m.group(0)} ({names[i]})" if 0 <= i < len(names) else m.group(0)

    return re.sub(r"\bchannel (\d+)\b", name, text)


def main(argv=None) -> int:
    """Entry point of the ``calib`` console script; returns the exit status."""
    try:
        args = _parser().parse_args(argv)
        with warnings.catch_warnings(record=True) as caught, interrupts_not_lost():
            warnings.simplefilter("always", CalibrationWarning)
            if args.command == "fit":
                msg = _fit(args)
            elif args.command == "evaluate":
                msg = _evaluate(args)
            elif args.command == "plan":
                msg = _plan(args)
            elif args.command == "apply":
                msg = _apply(args)
            else:
                msg = _trials(args)
        for w in caught:
            if issubclass(w.category, CalibrationWarning):
                print(f"calib: warning: {_named(w.message, args)}", file=sys.stderr)
        print(msg)
        return 0
    except UsageError as e:
        print(f"calib: error: {one_line(e)}", file=sys.stderr)  # the message names the command
        return 2
    except Unreliable as e:
        print(f"calib: unreliable: {_named(one_line(e), args)}", file=sys.stderr)
        return 3
    except (CalibrationError, ValueError) as e:
        print(f"calib: error: {one_line(e)}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"calib: error: {e.filename or ''}: {e.strerror}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("calib: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # a Ctrl-C that Python wrapped: a hook, an extension's import
        if not caused_by_interrupt(e):
            raise
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
    from calib.data.io import read_csv, save_calibration, split_known
    from calib.estimators.bias import fit_bias
    from calib.estimators.ft6 import fit_ft6
    from calib.estimators.sfm import fit_sfm

    _check_outputs([args.raw, args.known], args.out)
    # the default route: the maximum-likelihood joint fit wherever it applies;
    # a known file with fewer than 2 loads falls back to centered once it is read
    default_method = args.method is None
    if default_method:
        args.method = "joint" if args.bias and args.known and args.dof in (2, 3) else "centered"
    if args.method != "joint" or args.dof == 6:
        given = [flag for flag, v in (("--known-sigma", args.known_sigma),
                                      ("--magnitude-sigma", args.magnitude_sigma),
                                      ("--known-samples", args.known_samples)) if v is not None]
        if given:
            raise CalibrationError(f"{given[0]} is an option of --method joint (with --dof 2 or "
                                   "3); without it nothing would use it")
    if args.method == "least_squares":
        for flag, v in (("--known", args.known), ("--bias", args.bias or None),
                        ("--magnitude", args.magnitude), ("--chunk-rows", args.chunk_rows),
                        ("--bootstrap", args.bootstrap)):
            if v:
                raise CalibrationError(f"{flag} is not an option of --method least_squares "
                                       "(RAW.csv holds every row's load)")
    if args.chunk_rows:
        if args.bootstrap:
            raise CalibrationError("--chunk-rows is not supported with --bootstrap")
        if args.cv:
            raise CalibrationError("--chunk-rows is not supported with --cv")
        from calib.data.io import CSVSource

        # each pass of the fit reads the file again (a bar per pass on a terminal)
        Z = CSVSource(args.raw, args.chunk_rows, progress=not args.quiet)
        channels = Z.header
    else:
        channels, Z = read_csv(args.raw)
    if args.method not in ("joint", "least_squares") or args.dof == 6:
        for flag, v, plain in (("--model", args.model, "affine"),
                               ("--drift", args.drift, "none")):
            if v not in (None, plain):
                raise CalibrationError(f"{flag} {v} is an option of --method least_squares or "
                                       "joint (dof 2 or 3)")
    if args.robust and args.method not in ("joint", "least_squares"):
        raise CalibrationError("--robust is an option of --method joint or least_squares")
    if args.cv and args.method not in ("joint", "least_squares"):
        raise CalibrationError("--cv poses needs --method joint or least_squares (known loads "
                               "at the poses)")
    known_Z = known_M = None
    if args.method == "least_squares":
        return _fit_least_squares(args, channels, Z)
    args.channel_names = list(channels)  # messages name the channels (_named)
    if args.known:
        kh, kd = read_csv(args.known)
        known_Z, known_M = split_known(kh, kd, channels, args.dof)
        if default_method and args.method == "joint" and len(known_Z) < 2:
            given = [flag for flag, v in (
                ("--known-samples", args.known_samples), ("--known-sigma", args.known_sigma),
                ("--magnitude-sigma", args.magnitude_sigma), ("--model", args.model),
                ("--drift", args.drift), ("--robust", args.robust), ("--cv", args.cv))
                if v not in (None, False)]
            if given:
                raise CalibrationError(f"{given[0]} needs the joint route, which needs at least "
                                       f"2 known loads ({args.known} has {len(known_Z)})")
            args.method = "centered"
    if args.dof == 6:
        if known_Z is None:
            raise CalibrationError("--dof 6 needs --known with at least 6 known loads (see docs)")

        def fit(Z, drop=args.drop_nonfinite, cv=False):
            return fit_ft6(Z, known_Z, known_M, bias=args.bias, method=args.method,
                           drop_nonfinite=drop)
    elif args.method == "joint":
        from calib.routes.joint import fit_joint

        if known_Z is None:
            raise CalibrationError("--method joint needs --known with at least 2 known loads")

        def fit(Z, drop=args.drop_nonfinite, cv=False):
            return fit_joint(Z, known_Z, known_M, args.dof, magnitude=args.magnitude,
                             known_sigma=args.known_sigma,
                             magnitude_sigma=args.magnitude_sigma, drop_nonfinite=drop,
                             known_samples=args.known_samples, cv=cv,
                             model=args.model or "auto", drift=args.drift or "none",
                             robust=args.robust)
    elif args.bias:

        def fit(Z, drop=args.drop_nonfinite, cv=False):
            return fit_bias(Z, args.dof, method=args.method, known_Z=known_Z, known_M=known_M,
                            magnitude=args.magnitude, drop_nonfinite=drop)
    else:

        def fit(Z, drop=args.drop_nonfinite, cv=False):
            return fit_sfm(Z, args.dof, known_Z=known_Z, known_M=known_M,
                           magnitude=args.magnitude, drop_nonfinite=drop)
    cal = fit(Z, cv=args.cv == "poses")
    if args.bootstrap:
        from calib.data.validate import check_matrix
        from calib.verdict.bootstrap import bootstrap_intervals
        from sfm_common.progress import progress as progress_bar

        Zc, _ = check_matrix(Z, args.raw, args.drop_nonfinite)
        with progress_bar(args.bootstrap, "bootstrap", unit="fit",
                          enabled=False if args.quiet else None) as bar:
            cal.diagnostics["bootstrap"] = bootstrap_intervals(
                lambda z: fit(z, False), Zc, cal, args.bootstrap, seed=args.seed,
                align=known_Z is None, progress=bar)
    if known_Z is not None and args.dof != 6 and cal.diagnostics.get("joint", {}).get(
            "route") != "poses" and not args.chunk_rows:
        from calib.data.validate import check_matrix
        from calib.routes.crosscheck import crosscheck

        cc = crosscheck(cal, check_matrix(Z, args.raw, args.drop_nonfinite)[0], known_Z,
                        known_M)
        if cc is not None:
            cal.diagnostics["crosscheck"] = cc
    status = _reliability(args, cal, known_Z, known_M)
    save_calibration(args.out, cal, channels)
    return _summary(args, cal, status)


def _reliability(args, cal, known_Z, known_M) -> str:
    """Assess the fit (calib.verdict.reliability), record it in its diagnostics; raise Unreliable
    unless --allow-unreliable. Returns the summary's reliability words."""
    from calib.data.result import warn
    from calib.estimators.forward.misfit import DIRECTION_ALPHA
    from calib.verdict.reliability import HOLDOUT_FACTOR, assess

    problems = assess(cal, known_Z, known_M, args.known_sigma,
                      holdout_factor=args.holdout_factor or HOLDOUT_FACTOR)
    cal.diagnostics["reliability"] = {"reliable": not problems, "problems": problems}
    if problems and not args.allow_unreliable:
        raise Unreliable("; ".join(problems) + "; nothing written (--allow-unreliable writes "
                         "it anyway)")
    for p in problems:
        warn(f"unreliable: {p}")
    if problems:
        return "UNRELIABLE (written: --allow-unreliable)"
    dm = (cal.diagnostics.get("joint") or {}).get("direction_misfit")
    if isinstance(dm, dict) and dm.get("tested") and dm["p_value"] < DIRECTION_ALPHA:
        # the verdict's ratio takes the misfit for noise (docs/calib.md, "Gauges that are not
        # linear"): the word says how far it goes, as the warning does
        return ("reliable only as far as an affine sensor goes: this one reads as not linear in "
                "the load, so its error has no stated upper end (calib evaluate on known loads "
                "left out of the fit measures it)")
    pe = (cal.diagnostics.get("joint") or {}).get("predicted_error")
    if isinstance(pe, dict) and pe.get("no_upper_end_because") == "readings far from the model":
        return ("reliable as far as the readings named in the warning are noise: its error has "
                "no stated upper end (--robust leaves them out)")
    return "reliable"


def _summary(args, cal, status) -> str:
    d = cal.diagnostics
    dropped = d.get("n_dropped_nonfinite", 0)
    cov = d.get("coverage") or {}
    note = f", dropped {dropped} non-finite row(s)" if dropped else ""
    parts = []
    if "rank_gap" in d:
        parts.append(f"rank gap {d['rank_gap']:.3g}")
    if "isotropy" in cov:
        parts.append(f"coverage isotropy {cov['isotropy']:.2f}")
    if cal.method == "least_squares" and "residual_rms" in d:
        parts.append(f"residual rms {d['residual_rms']:.4g}")
    return (
        f"wrote {args.out}: {cal.method}, dof {cal.dof}, {cal.n_channels} channels, "
        f"{d.get('n_samples')} samples{note}; " + ", ".join(parts)
        + (f", offset stderr <= {d['offset_stderr_max_rel_span']:.2%} of span"
           if "offset_stderr_max_rel_span" in d else "")
        + (f", bootstrap {args.bootstrap}" if args.bootstrap else "")
        + (f", {d['joint']['n_poses']} poses found" if d.get("joint", {}).get("route") == "poses"
           else "")
        + (", no static poses: every reading its own pose (forward maximum-likelihood fit)"
           if d.get("joint", {}).get("route") == "forward" else "")
        + (", the channels' noise correlated (p {}): fitted in whitened channels".format(
            _p_text(d["joint"]["noise_correlation"]["p_value"]))
           if d.get("joint", {}).get("noise_correlation", {}).get("used") else "")
        + _serial(d)
        + _predicted(d)
        + (f" (each channel a degree-{d['joint']['index_model']['degree']} polynomial of its own "
           "signal)" if d.get("joint", {}).get("index_model", {}).get("used") else "")
        + (f", model {d['model_selection']['chosen']} "
           + ("(not selected: known loads inconsistent)" if "skipped" in d["model_selection"]
              else "(by leave-one-pose-out error)") if "model_selection" in d else "")
        + (f", leave-one-pose-out rms {d['cv_poses']['rms']:.4g} over "
           f"{d['cv_poses']['folds']} pose(s)" if "cv_poses" in d else "")
        + f"; {status}"
    )


def _p_text(p: float) -> str:
    """``= 3e-05``, or ``< 1e-300`` where the chi-square tail underflowed to 0."""
    return f"= {p:.1g}" if p > 0 else "< 1e-300"


def _serial(d) -> str:
    """The summary's note where the readings' noise is correlated along the log (forward fits:
    :func:`calib.verdict.serial.serial_correlation`), which widens the predicted error's
    interval."""
    sc = (d.get("joint") or {}).get("serial_correlation")
    if not isinstance(sc, dict):
        return ""
    rho = np.asarray(sc["rho"], float)[np.asarray(sc["correlated"], bool)]
    return (f", the readings' noise correlated along the log (lag-1 autocorrelation up to "
            f"{rho.max():.2f} on {len(rho)} channel(s)): fewer independent readings, the "
            "interval widened (a sensor not linear in the load reads the same way along a "
            "sweep's path, and then its error can lie above the interval: calib evaluate on "
            "known loads left out of the fit measures it)")


def _predicted(d) -> str:
    """The summary's predicted held-out error (forward fits), with its interval."""
    pe = (d.get("joint") or {}).get("predicted_error")
    if not isinstance(pe, dict):
        return ""
    lo, hi = pe["interval"]
    if pe.get("upper_bounded") is False:  # calib.verdict.predicted_error.one_sided
        lo, hi = pe["interval_if_linear"]
        why, were = (("some readings lie far from the fitted model (named above; --robust "
                      "leaves them out)", "were they noise")
                     if pe.get("no_upper_end_because") == "readings far from the model" else
                     ("the sensor reads as not linear in the load", "were it linear"))
        return (f", predicted held-out error at least {lo:.4g} (no upper end: {why}; {were}, "
                f"{pe['rms']:.4g} [{lo:.4g}, {hi:.4g}], {pe['coverage']:.0%} interval, "
                f"{pe['ratio']:.2f}x least squares with every load known)")
    return (f", predicted held-out error {pe['rms']:.4g} [{lo:.4g}, {hi:.4g}] "
            f"({pe['coverage']:.0%} interval; {pe['ratio']:.2f}x least squares with every load "
            "known)")


def _fit_least_squares(args, channels, Z) -> str:
    from calib.data.io import LOAD_COLUMNS, load_columns, save_calibration
    from calib.data.validate import check_matrix
    from calib.estimators.models import choose, fit_model, leave_one_pose_out_ls
    from calib.estimators.rig.poses import find_poses

    cols = load_columns(args.dof)
    missing = [c for c in cols if c not in channels]
    if missing:
        raise CalibrationError(f"{args.raw} lacks load column(s) {missing} (--method "
                               "least_squares needs every row's load)")
    idx = [channels.index(c) for c in cols]
    sens = [i for i, c in enumerate(channels) if c not in LOAD_COLUMNS]
    data, _ = check_matrix(Z, args.raw, args.drop_nonfinite)
    Zs, Ms = data[:, sens], data[:, idx]
    labels = find_poses(Zs)
    if args.robust:
        if labels is None:
            raise CalibrationError(f"--robust: {args.raw} is not a static-pose log (no poses "
                                   "found)")
        from calib.estimators.rig.poses import reject_outliers

        labels, _ = reject_outliers(Zs, labels)
        Zs, Ms, labels = Zs[labels >= 0], Ms[labels >= 0], labels[labels >= 0]
    if args.cv and labels is None:
        raise CalibrationError(f"--cv poses: {args.raw} is not a static-pose log (no poses "
                               "found)")
    model, drift = args.model or "auto", args.drift or "auto"
    table = {}
    if labels is None:  # every row its own load: identifiability by rows, no selection
        model = "affine" if model == "auto" else model
        drift = "none" if drift == "auto" else drift
        model, drift, _ = choose(None, len(Zs), Zs.shape[1], model, drift)
    else:
        n_poses = int(labels.max()) + 1
        model, drift, table = choose(
            lambda m, d: leave_one_pose_out_ls(Zs, Ms, labels, m, d), n_poses, Zs.shape[1],
            model, drift)
    cal = fit_model(Zs, Ms, model, drift)
    if table:
        cal.diagnostics["model_selection"] = table
    if args.cv:
        cal.diagnostics["cv_poses"] = leave_one_pose_out_ls(Zs, Ms, labels, model, drift)
    status = _reliability(args, cal, None, None)
    save_calibration(args.out, cal, [channels[i] for i in sens])
    return _summary(args, cal, status)


def _apply(args) -> str:
    from calib.data.io import load_calibration, load_columns, read_csv, write_csv
    from calib.data.validate import check_matrix

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


def _evaluate(args) -> str:
    from calib.data.io import LOAD_COLUMNS, load_calibration, load_columns, read_csv
    from calib.data.validate import check_matrix
    from calib.estimators.rig.poses import match_poses

    cal, cal_channels = load_calibration(args.cal)
    header, data = read_csv(args.test)
    cols = load_columns(cal.dof)
    channels = cal_channels or [c for c in header if c not in LOAD_COLUMNS]
    missing = [c for c in channels if c not in header]
    if missing:
        raise CalibrationError(f"{args.test} lacks calibrated channel(s) {missing}")
    if len(channels) != cal.n_channels:
        raise CalibrationError(f"{args.test} has {len(channels)} channel columns, the "
                               f"calibration expects {cal.n_channels}")
    data, dropped = check_matrix(data, args.test, args.drop_nonfinite)
    Z = data[:, [header.index(c) for c in channels]]
    has_loads = all(c in header for c in cols)
    note = ""
    if has_loads and not args.known:
        M = data[:, [header.index(c) for c in cols]]
    elif args.known:
        if has_loads:
            raise CalibrationError(f"{args.test} has load columns and --known was given: "
                                   "use one source of loads")
        kh, kd = read_csv(args.known)
        miss = [c for c in channels + cols if c not in kh]
        if miss:
            raise CalibrationError(f"{args.known} lacks column(s) {miss}")
        Zk, _ = check_matrix(kd[:, [kh.index(c) for c in channels]], args.known)
        Mk = kd[:, [kh.index(c) for c in cols]]
        rows, which, n_poses = match_poses(Z, Zk)
        if not len(rows):
            raise CalibrationError(f"no pose of {args.test} lies clearly nearest to a known "
                                   f"reading of {args.known}")
        Z, M = Z[rows], Mk[which]
        note = (f" in {n_poses} pose(s) matched to known readings"
                f"{f', {len(data) - len(rows)} row(s) unmatched' if len(rows) < len(data) else ''}")
    else:
        raise CalibrationError(f"{args.test} has no load columns {cols}: give --known KNOWN.csv")
    err = cal.apply(Z) - M
    per_axis = np.sqrt(np.mean(err**2, axis=0))
    # the rms length of the error vector: the measure of the load rms beside it and of the fit's
    # predicted held-out error (its components' rms would be sqrt(dof) times smaller)
    total = float(np.sqrt(np.mean(np.sum(err**2, axis=1))))
    mag = float(np.sqrt(np.mean(np.sum(M**2, axis=1))))
    axes = ", ".join(f"{c} {v:.4g}" for c, v in zip(cols, per_axis, strict=True))
    drop = f", dropped {dropped} non-finite row(s)" if dropped else ""
    return (f"{args.test}: {len(Z)} row(s){note}{drop}; held-out load rms {total:.4g} "
            f"(error vector length, as the predicted held-out error; {total / mag:.2%} of the "
            f"load rms {mag:.4g}); per axis: {axes}")


def _plan(args) -> str:
    from calib.data.io import read_csv
    from calib.simulation.plan import plan

    header, data = read_csv(args.poses)
    for cols in (["Fx", "Fy", "Fz"], ["ux", "uy", "uz"]):
        if all(c in header for c in cols):
            break
    else:
        raise CalibrationError(f"{args.poses} needs columns Fx,Fy,Fz or ux,uy,uz")
    if (args.noise is None) != (args.sensitivity is None):
        raise CalibrationError("give --noise and --sensitivity together (or neither)")
    U = data[:, [header.index(c) for c in cols]]
    if not np.all(np.isfinite(U)):
        raise CalibrationError(f"{args.poses} has non-finite directions")
    res = plan(U, args.known_loads, magnitude=args.magnitude, samples=args.samples,
               noise=args.noise, sensitivity=args.sensitivity)
    rows = ", ".join(str(int(i) + 1) for i in res["known"])
    text = (f"{args.poses}: {res['poses']} poses, {res['k']} known loads: put them on pose rows "
            f"{rows} (1 = first data row). Predicted (Cramer-Rao bound, isotropic sensor, "
            f"{res['samples']} readings per pose): load error {res['ratio']:.2f}x least squares "
            f"with every load known ({res['ratio_first']:.2f}x with the first {res['k']} rows)"
            f"; on a new single reading, whose own noise adds to both, "
            f"{res['ratio_reading']:.2f}x ({res['ratio_reading_first']:.2f}x)")
    if "bound" in res:
        text += (f"; rms load error >= {res['bound']:.3g} (all known: "
                 f"{res['bound_all_known']:.3g}) in load units")
    return text + ("; the bound assumes a linear sensor: one that is not (a printed sensor "
                   "whose channels bend) can do worse, measured 1.0-1.9x on a real one "
                   "(docs/calib.md)")


def _trials(args) -> str:
    from calib.simulation.trials import trial_summary, write_report

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
