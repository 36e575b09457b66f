"""``mkv fit`` and ``mkv compare``: fit a shape-from-motion policy; the paper's Figure 3.

::

    mkv fit DATA.npz [MORE.npz ...] --out POLICY.npz [--rank N] [--solver ppca|lstsq|ridge]
            [--features default|raw] [--history K] [--traces D,D] [--prev-action MODE]
            [--encoding signed|onehot] [--thresholds learned|fixed] [--spectrum PNG]
    mkv compare DATA.npz POLICY.npz [--plot fig3.png] [--spectrum PNG] [--episode I] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

from mkv_env.files import atomic_write_text
from sfm_learn.cli import CliError, _non_negative_int, check_output_path

_SOLVERS = ("ppca", "lstsq", "ridge")


# ---------------------------------------------------------------------- shared
def _load_dataset(path: str):
    from mkv_env.dataset import load

    if not os.path.exists(path):
        raise CliError(f"dataset {path} does not exist")
    return load(path)


def _decays(text: str):
    try:
        vals = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected decays like 0.5,0.8, got {text!r}") from None
    if not all(0.0 <= v < 1.0 for v in vals):
        raise argparse.ArgumentTypeError(f"decays must be in [0, 1), got {text!r}")
    return vals


def _png_path(path: str, what: str) -> None:
    check_output_path(path, what)
    if not path.lower().endswith(".png"):
        raise CliError(f"{what} {path} must end in .png")


def spectrum_lines(singular_values, rank: int, floor: float, limit: int = 60) -> list[str]:
    """The spectrum as text: index, singular value, adjacent ratio, the chosen rank marked."""
    s = np.asarray(singular_values, dtype=float)
    lines = ["   i   s_i          s_i/s_(i+1)"]
    for i in range(min(s.size, limit)):
        ratio = s[i] / s[i + 1] if i + 1 < s.size and s[i + 1] > 0 else float("nan")
        mark = "  <- n (largest ratio above the floor)" if i + 1 == rank else ""
        below = "  (below floor)" if s[i] <= floor else ""
        lines.append(f"  {i + 1:2d}   {s[i]:11.4g}  {ratio:10.3f}{mark}{below}")
    if s.size > limit:
        lines.append(f"  ... {s.size - limit} more")
    return lines


# ---------------------------------------------------------------------- fit
def add_fit_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", nargs="+", metavar="DATA.npz",
                   help="teacher recordings (mkv record); several are stacked")
    p.add_argument("--out", required=True, metavar="POLICY.npz")
    p.add_argument("--rank", type=int, default=None, metavar="N",
                   help="kept eigenvectors (default: the largest adjacent singular-value ratio)")
    p.add_argument("--solver", choices=_SOLVERS, default="ppca",
                   help="how the run-time projection solves the coefficients (default ppca: the "
                        "probabilistic-PCA conditional mean; lstsq is the paper's plain least "
                        "squares)")
    p.add_argument("--rank-rtol", type=float, default=1e-3, metavar="R",
                   help="singular values below R * s_1 never count for the rank (default 1e-3)")
    p.add_argument("--features", choices=("default", "raw"), default="default",
                   help="default: sensors, decaying traces and the previous command; raw: the "
                        "sensors only. --history/--traces/--prev-action override parts")
    p.add_argument("--history", type=_non_negative_int, default=None, metavar="K",
                   help="stack the K previous observations")
    p.add_argument("--traces", type=_decays, default=None, metavar="D,D",
                   help="decay factors of exponential traces, e.g. 0.5,0.8 ('' for none)")
    p.add_argument("--prev-action", choices=("none", "signed", "onehot"), default=None)
    p.add_argument("--encoding", choices=("signed", "onehot"), default="signed",
                   help="command columns of the training matrix (default signed: -1/0/+1)")
    p.add_argument("--thresholds", choices=("learned", "fixed"), default="learned",
                   help="quantisation of signed commands (default learned on the training data)")
    p.add_argument("--spectrum", metavar="PNG", help="also plot the singular-value spectrum")


def feature_spec_from_args(args, names):
    """The FeatureSpec named by ``--features`` with the ``--history/--traces/--prev-action``
    overrides."""
    from dataclasses import replace

    from sfm_learn.features import FeatureSpec, default_feature_spec

    spec = (default_feature_spec(names) if args.features == "default"
            else FeatureSpec(obs_names=tuple(names)))
    over = {}
    if args.history is not None:
        over["history"] = args.history
    if args.traces is not None:
        over["trace_decays"] = args.traces
    if args.prev_action is not None:
        over["prev_action"] = args.prev_action
    return replace(spec, **over) if over else spec


def run_fit(args) -> int:
    from sfm_learn.policy import fit_policy

    check_output_path(args.out)
    if not args.out.lower().endswith(".npz"):
        raise CliError(f"output {args.out} must end in .npz")
    if args.spectrum:
        _png_path(args.spectrum, "spectrum plot")
    datasets = [_load_dataset(p) for p in args.data]
    names = list(datasets[0].sensor_names)
    for path, d in zip(args.data[1:], datasets[1:], strict=True):
        if list(d.sensor_names) != names:
            raise CliError(f"{path} has sensors {list(d.sensor_names)}, {args.data[0]} has "
                           f"{names}: cannot stack them")
    spec = feature_spec_from_args(args, names)
    if args.rank is not None and not 1 <= args.rank <= spec.n_features + 2:
        raise CliError(f"--rank must be in [1, {spec.n_features + 2}] for {spec.n_features} "
                       f"features and 2 commands, got {args.rank}")
    try:
        policy = fit_policy(datasets, spec, n_components=args.rank, solver=args.solver,
                            rank_rtol=args.rank_rtol, encoding=args.encoding,
                            thresholds=args.thresholds)
    except ValueError as e:
        raise CliError(str(e).splitlines()[0]) from None
    proj = policy.projector
    tr = policy.training
    print(f"fitted on {tr['rows']} steps ({tr['episodes']} episodes of "
          + ", ".join(sorted({str(d['env_id']) for d in tr['datasets']}))
          + f") in {tr['wall_s']:.3f} s")
    print(f"features ({spec.n_features}): " + ", ".join(spec.feature_names))
    print("\n".join(spectrum_lines(proj.singular_values_, proj.n_components_,
                                   proj.rank_floor_)))
    how = "given" if args.rank is not None else "largest adjacent ratio"
    print(f"chosen rank n = {proj.n_components_} of {proj.n_features_in_} ({how}); "
          f"solver {args.solver}; floor {proj.rank_floor_:.3g}")
    if policy.encoding == "signed":
        for name, (lo, hi) in zip(spec.action_names, policy.thresholds, strict=True):
            print(f"{name}: reverse/left below {lo:+.3f}, forward/right above {hi:+.3f}")
    policy.save(args.out)
    print(f"wrote {args.out}")
    if args.spectrum:
        from sfm_learn.plots import MatplotlibMissing, plot_spectrum

        try:
            plot_spectrum(proj.singular_values_, proj.n_components_, args.spectrum,
                          floor=proj.rank_floor_,
                          title=f"SfM spectrum: {os.path.basename(args.out)}")
        except MatplotlibMissing as e:
            raise CliError(str(e)) from None
        print(f"wrote {args.spectrum}")
    return 0


# ---------------------------------------------------------------------- compare
def add_compare_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", metavar="DATA.npz", help="held-out teacher recording")
    p.add_argument("policy", metavar="POLICY.npz", help="policy from mkv fit")
    p.add_argument("--plot", metavar="fig3.png", help="write the paper's Figure 3")
    p.add_argument("--spectrum", metavar="PNG",
                   help="write the spectrum plot (default with --plot: <plot>_spectrum.png)")
    p.add_argument("--episode", type=_non_negative_int, default=None, metavar="I",
                   help="episode shown in the figure (default: the one with most back-offs)")
    p.add_argument("--json", metavar="OUT.json", help="also write the metrics as JSON")


def _default_episode(cmp) -> int:
    """The episode with the most reverse commands started (the most escapes to look at)."""
    best, best_n = 0, -1
    for i, sl in enumerate(cmp.episode_slices):
        d = cmp.teacher[sl, 0]
        n = int(np.sum((d[1:] == 0) & (d[:-1] != 0)))
        if n > best_n:
            best, best_n = i, n
    return best


def run_compare(args) -> int:
    from sfm_learn.compare import compare
    from sfm_learn.policy import PolicyFileError, SfMPolicy

    spectrum = args.spectrum
    if args.plot:
        _png_path(args.plot, "plot")
        if spectrum is None:
            spectrum = args.plot[:-4] + "_spectrum.png"
    if spectrum:
        _png_path(spectrum, "spectrum plot")
    if args.json:
        check_output_path(args.json, "JSON output")
    data = _load_dataset(args.data)
    try:
        policy = SfMPolicy.load(args.policy)
    except PolicyFileError as e:
        raise CliError(str(e)) from None
    try:
        cmp = compare(policy, data)
    except ValueError as e:
        raise CliError(str(e).splitlines()[0]) from None
    used = {d.get("sha256") for d in policy.training.get("datasets", [])}
    in_sample = data.metadata.get("content_sha256") in used
    m = cmp.metrics
    b = m["baseline"]
    print(f"{args.policy} replayed on {args.data}: {data.n_episodes} episodes, {m['steps']} steps"
          + ("  [WARNING: this dataset was used to fit the policy; agreement is in-sample]"
             if in_sample else ""))
    print(f"{'agreement':<28}{'SfM':>8}{'constant guess':>16}")
    print(f"{'drive':<28}{m['drive']:>8.3f}{b['drive']:>16.3f}")
    print(f"{'steer timing (steer or not)':<28}{m['steer_timing']:>8.3f}{b['steer_timing']:>16.3f}")
    d, bd = m["steer_direction"], b["steer_direction"]
    print(f"{'steer direction (both steer)':<28}"
          + (f"{d:>8.3f}{bd:>16.3f}" if d is not None else f"{'-':>8}{'-':>16}")
          + f"   over {m['steer_direction_steps']} steps")
    d = m["steer_direction_onset"]
    print(f"{'steer direction at onsets':<28}"
          + (f"{d:>8.3f}{0.5:>16.3f}" if d is not None else f"{'-':>8}{'-':>16}")
          + f"   over {m['steer_onsets']} teacher steer onsets (0.5 = coin)")
    d = m["steer_direction_backoff_onset"]
    print(f"{'  ... of escape turns':<28}"
          + (f"{d:>8.3f}{0.5:>16.3f}" if d is not None else f"{'-':>8}{'-':>16}")
          + f"   over {m['steer_backoff_onsets']} onsets while reversing (random side)")
    if args.json:
        doc = {"data": os.path.basename(args.data), "policy": os.path.basename(args.policy),
               "in_sample": in_sample, "metrics": m, "episodes": cmp.per_episode}
        atomic_write_text(args.json, json.dumps(doc, indent=2) + "\n")
        print(f"wrote {args.json}")
    if args.plot or spectrum:
        from sfm_learn.compare import agreement
        from sfm_learn.plots import MatplotlibMissing, plot_figure3, plot_spectrum

        try:
            if args.plot:
                ep = _default_episode(cmp) if args.episode is None else args.episode
                if ep >= len(cmp.episode_slices):
                    raise CliError(f"--episode {ep} is out of range: the dataset has "
                                   f"{len(cmp.episode_slices)} episodes")
                sl = cmp.episode_slices[ep]
                t = np.arange(sl.stop - sl.start) * cmp.control_period_s
                bumps = data["bumped"][sl] if "bumped" in data else None
                plot_figure3(t, cmp.teacher[sl], cmp.policy[sl], args.plot,
                             metrics=agreement(cmp.teacher[sl], cmp.policy[sl]), bumps=bumps,
                             title=f"Teacher vs shape-from-motion commands, held-out "
                                   f"{data.metadata.get('env_id')} run (seed "
                                   f"{int(data['episode_seeds'][ep])})")
                print(f"wrote {args.plot}")
            if spectrum:
                proj = policy.projector
                plot_spectrum(proj.singular_values_, proj.n_components_, spectrum,
                              floor=proj.rank_floor_,
                              title=f"singular values of the training matrix "
                                    f"({policy.training.get('rows')} steps); kept n = "
                                    f"{proj.n_components_}")
                print(f"wrote {spectrum}")
        except MatplotlibMissing as e:
            raise CliError(str(e)) from None
    return 0
