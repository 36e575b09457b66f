"""``mkv fit``: fit a shape-from-motion (eigenspace) policy to teacher recordings.

::

    mkv fit DATA.npz [MORE.npz ...] --out POLICY.npz [--rank N] [--solver ppca|lstsq|ridge]
            [--features default|raw] [--history K] [--traces D,D] [--prev-action MODE]
            [--encoding signed|onehot] [--thresholds learned|fixed] [--spectrum PNG]
"""

from __future__ import annotations

import argparse
import os

from sfm_learn.cli.common import (
    CliError,
    check_output_path,
    check_outputs,
    check_png_path,
    int_in_range,
    load_dataset,
    non_negative_int,
)

_SOLVERS = ("ppca", "lstsq", "ridge", "ols")


def _decays(text: str):
    try:
        vals = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected decays like 0.5,0.8, got {text!r}") from None
    if not all(0.0 <= v < 1.0 for v in vals):
        raise argparse.ArgumentTypeError(f"decays must be in [0, 1), got {text!r}")
    return vals



def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", nargs="+", metavar="DATA.npz",
                   help="teacher recordings (mkv record); several are stacked; at least "
                        "features + commands + 1 steps in all (35 by default, 13 for --preset "
                        "paper)")
    p.add_argument("--out", required=True, metavar="POLICY.npz",
                   help="policy file to write (must end in .npz; run it as "
                        "--policy sfm:POLICY.npz)")
    p.add_argument("--preset", choices=("default", "paper", "ols"), default="default",
                   help="default: this package's features and solver (docs/sfm.md); paper: "
                        "exactly the paper's configuration (raw channels, least-squares "
                        "projection, fixed +-0.5 quantisation); ols: ordinary least squares on "
                        "the default features (the baseline). Options below override parts")
    p.add_argument("--rank", type=int, default=None, metavar="N",
                   help="kept eigenvectors (default: the largest adjacent singular-value ratio)")
    p.add_argument("--solver", choices=_SOLVERS, default=None,
                   help="how the run-time projection solves the coefficients (preset default "
                        "ppca: the probabilistic-PCA conditional mean; lstsq is the paper's "
                        "plain least squares; ols skips the eigenspace: the baseline)")
    p.add_argument("--rank-rtol", type=float, default=1e-3, metavar="R",
                   help="singular values below R * s_1 never count for the rank (default 1e-3)")
    p.add_argument("--features", choices=("default", "raw"), default=None,
                   help="default: sensors, decaying traces and the previous command; raw: the "
                        "sensors only (default: the preset's). --history/--traces/--prev-action "
                        "override parts")
    p.add_argument("--history", type=non_negative_int, default=None, metavar="K",
                   help="stack the K previous observations")
    p.add_argument("--traces", type=_decays, default=None, metavar="D,D",
                   help="decay factors of exponential traces, e.g. 0.5,0.8 ('' for none)")
    p.add_argument("--prev-action", choices=("none", "signed", "onehot"), default=None,
                   help="the previous command as a feature: none, signed (-1/0/+1 per "
                        "command) or onehot (default: as --features; signed for default, "
                        "none for raw)")
    p.add_argument("--encoding", choices=("signed", "onehot"), default="signed",
                   help="command columns of the training matrix (default signed: -1/0/+1)")
    p.add_argument("--thresholds", choices=("learned", "fixed"), default=None,
                   help="quantisation of signed commands: learned on the training data "
                        "(preset default) or fixed at -0.5/+0.5 (preset paper)")
    p.add_argument("--min-support", type=int_in_range(0, 10_000_000), default=None, metavar="N",
                   help="hold a sensor channel constant when it leaves its resting value in "
                        "fewer than N training rows (preset default: 5; paper: 0)")
    p.add_argument("--spectrum", metavar="PNG", help="also plot the singular-value spectrum")


def feature_spec_from_args(args, names):
    """The FeatureSpec named by ``--features`` with the ``--history/--traces/--prev-action``
    overrides."""
    from dataclasses import replace

    from mkv_env.features import FeatureSpec, default_feature_spec
    from sfm_learn.eigenspace.policy import PRESETS

    features = args.features or PRESETS[args.preset]["features"]
    spec = (default_feature_spec(names) if features == "default"
            else FeatureSpec(obs_names=tuple(names)))
    over = {}
    if args.history is not None:
        over["history"] = args.history
    if args.traces is not None:
        over["trace_decays"] = args.traces
    if args.prev_action is not None:
        over["prev_action"] = args.prev_action
    return replace(spec, **over) if over else spec


def run(args) -> int:
    from sfm_learn.eigenspace.policy import (
        PRESETS,
        check_fit_rows,
        check_fit_size,
        fit_columns,
        fit_policy,
    )
    from sfm_learn.reporting.tables import spectrum_lines

    check_output_path(args.out)
    if not args.out.lower().endswith(".npz"):
        raise CliError(f"output {args.out} must end in .npz")
    if args.spectrum:
        check_png_path(args.spectrum, "spectrum plot")
    check_outputs(args.data, [args.out, args.spectrum])
    datasets = [load_dataset(p) for p in args.data]
    names = list(datasets[0].sensor_names)
    for path, d in zip(args.data[1:], datasets[1:], strict=True):
        if list(d.sensor_names) != names:
            raise CliError(f"{path} has sensors {list(d.sensor_names)}, {args.data[0]} has "
                           f"{names}: cannot stack them")
    spec = feature_spec_from_args(args, names)
    if args.rank is not None and not 1 <= args.rank <= spec.n_features + 2:
        raise CliError(f"--rank must be in [1, {spec.n_features + 2}] for {spec.n_features} "
                       f"features and 2 commands, got {args.rank}")
    rows = sum(d.n_steps for d in datasets)
    what = (f"dataset {args.data[0]}" if len(args.data) == 1
            else f"datasets {', '.join(args.data)} (together)")
    try:  # before anything is fitted or written (min_fit_rows says why this minimum)
        check_fit_size(rows, fit_columns(spec, args.encoding))  # too many columns: say that first
        check_fit_rows(rows, spec, args.encoding, what)
    except ValueError as e:
        raise CliError(str(e)) from None
    solver = args.solver or PRESETS[args.preset]["solver"]
    thresholds = args.thresholds or PRESETS[args.preset]["thresholds"]
    min_support = (PRESETS[args.preset]["min_support"] if args.min_support is None
                   else args.min_support)
    try:
        policy = fit_policy(datasets, spec, n_components=args.rank, solver=solver,
                            rank_rtol=args.rank_rtol, encoding=args.encoding,
                            thresholds=thresholds, min_support=min_support)
    except ValueError as e:
        raise CliError(str(e).splitlines()[0]) from None
    proj = policy.projector
    tr = policy.training
    print(f"preset {args.preset}: fitted on {tr['rows']} steps ({tr['episodes']} episodes of "
          + ", ".join(sorted({str(d['env_id']) for d in tr['datasets']}))
          + f") in {tr['wall_s']:.3f} s")
    print(f"features ({spec.n_features}): " + ", ".join(spec.feature_names))
    if tr["rare_channels"]:
        print("held constant (fewer than " + str(min_support) + " active rows): "
              + ", ".join(f"{c} ({n} rows)" for c, n in tr["rare_channels"].items()))
    print("\n".join(spectrum_lines(proj.singular_values_, proj.n_components_,
                                   proj.rank_floor_)))
    how = "given" if args.rank is not None else "largest adjacent ratio"
    print(f"chosen rank n = {proj.n_components_} of {proj.n_features_in_} ({how}); "
          f"solver {solver}; floor {proj.rank_floor_:.3g}"
          + ("" if solver != "ols" else " (ols ignores the kept components)"))
    if policy.encoding == "signed":
        from mkv_env.actions import VALUE_NAMES

        for name, (lo, hi) in zip(spec.action_names, policy.thresholds, strict=True):
            low, _, high = VALUE_NAMES.get(name, ("reverse/left", "off", "forward/right"))
            print(f"{name}: {low} below {lo:+.3f}, {high} above {hi:+.3f}")
    policy.save(args.out)
    print(f"wrote {args.out}")
    if args.spectrum:
        from sfm_learn.reporting.plots import MatplotlibMissing, plot_spectrum

        try:
            plot_spectrum(proj.singular_values_, proj.n_components_, args.spectrum,
                          floor=proj.rank_floor_,
                          title=f"SfM spectrum: {os.path.basename(args.out)}")
        except MatplotlibMissing as e:
            raise CliError(str(e)) from None
        print(f"wrote {args.spectrum}")
    return 0
