"""``mkv compare``: replay an SfM policy on recorded teacher runs; the paper's Figure 3.

::

    mkv compare DATA.npz POLICY.npz [--plot fig3.png] [--spectrum PNG] [--episode I] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

from sfm_common.files import atomic_write_text
from sfm_learn.cli.common import (
    CliError,
    check_output_path,
    check_outputs,
    check_png_path,
    load_dataset,
    non_negative_int,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", metavar="DATA.npz", help="held-out teacher recording")
    p.add_argument("policy", metavar="POLICY.npz", help="policy from mkv fit")
    p.add_argument("--plot", metavar="fig3.png", help="write the paper's Figure 3")
    p.add_argument("--spectrum", metavar="PNG",
                   help="write the spectrum plot (default with --plot: <plot>_spectrum.png)")
    p.add_argument("--episode", type=non_negative_int, default=None, metavar="I",
                   help="episode shown in the figure (default: the one with most back-offs)")
    p.add_argument("--json", metavar="OUT.json", help="also write the metrics as JSON")
    p.add_argument("--mode", choices=("free_running", "teacher_forced"), default="free_running",
                   help="replay drawn in the figure (default free_running: the policy's own "
                        "previous commands feed its features; both are in the table and JSON)")


def _default_episode(cmp) -> int:
    """The episode with the most reverse commands started (the most escapes to look at)."""
    best, best_n = 0, -1
    for i, sl in enumerate(cmp.episode_slices):
        d = cmp.teacher[sl, 0]
        n = int(np.sum((d[1:] == 0) & (d[:-1] != 0)))
        if n > best_n:
            best, best_n = i, n
    return best


def run(args) -> int:
    from sfm_learn.eigenspace.policy import PolicyFileError, SfMPolicy
    from sfm_learn.evaluation.compare import compare
    from sfm_learn.reporting.tables import comparison_table

    spectrum = args.spectrum
    if args.plot:
        check_png_path(args.plot, "plot")
        if spectrum is None:
            spectrum = args.plot[:-4] + "_spectrum.png"
    if spectrum:
        check_png_path(spectrum, "spectrum plot")
    if args.json:
        check_output_path(args.json, "JSON output")
    check_outputs([args.data, args.policy], [args.json, args.plot, spectrum])
    data = load_dataset(args.data)
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
    print(f"{args.policy} replayed on {args.data}: {data.n_episodes} episodes, "
          f"{data.n_steps} steps"
          + ("  [WARNING: this dataset was used to fit the policy; agreement is in-sample]"
             if in_sample else ""))
    print(comparison_table(cmp))
    if args.json:
        doc = {"data": os.path.basename(args.data), "policy": os.path.basename(args.policy),
               "in_sample": in_sample, **cmp.to_dict()}
        atomic_write_text(args.json, json.dumps(doc, indent=2) + "\n")
        print(f"wrote {args.json}")
    if args.plot or spectrum:
        from sfm_learn.evaluation.compare import agreement
        from sfm_learn.reporting.plots import MatplotlibMissing, plot_figure3, plot_spectrum

        try:
            if args.plot:
                ep = _default_episode(cmp) if args.episode is None else args.episode
                if ep >= len(cmp.episode_slices):
                    raise CliError(f"--episode {ep} is out of range: the dataset has "
                                   f"{len(cmp.episode_slices)} episodes")
                sl = cmp.episode_slices[ep]
                t = np.arange(sl.stop - sl.start) * cmp.control_period_s
                bumps = data["bumped"][sl] if "bumped" in data else None
                mine = cmp.actions[args.mode][sl]
                plot_figure3(t, cmp.teacher[sl], mine, args.plot,
                             metrics=agreement(cmp.teacher[sl], mine), bumps=bumps,
                             policy_label=f"SfM policy ({args.mode.replace('_', '-')})",
                             title=f"Teacher vs shape-from-motion commands, held-out "
                                   f"{data.metadata.get('env_id')} run (seed "
                                   f"{int(data['episode_seeds'][ep])}); the policy "
                                   + ("drives its own features (free-running)"
                                      if args.mode == "free_running" else
                                      "is fed the teacher's previous command"))
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
