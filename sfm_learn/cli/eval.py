"""``mkv eval``: evaluate policies on the same seeded episodes (see :mod:`sfm_learn.evaluation`).

::

    mkv eval --env MKVJam-v0 --policy teacher [--policy random ...] --episodes N [--seed S]
             [--workers N] [--backend local|ray] [--address ADDR] [--json OUT.json]
             [--plot OUT.png] [--env-kwargs JSON] [--quiet]

Every ``--policy`` runs episodes with env seeds ``S .. S+N-1``. Stdout gets a Markdown table
(one row per policy, one column per metric, ``value [low, high]`` with a bootstrap confidence
interval). ``--json`` writes one evaluation object for one policy, a list in ``--policy`` order
for several; ``--plot`` writes a bar plot with the intervals as error bars (needs matplotlib).
All specs, the env and the output paths are checked before any episode runs; files are written
only when everything has run (an error or Ctrl-C leaves none).
"""

from __future__ import annotations

import argparse
import os

from sfm_common.files import atomic_write_text
from sfm_learn.cli.common import (
    POLICY_HELP,
    CliError,
    add_env_arguments,
    add_quiet_argument,
    add_trust_argument,
    apply_trust,
    check_env_and_policies,
    check_output_path,
    check_outputs,
    check_writable,
    episodes_type,
    positive_int,
    progress_for,
    seed,
    spec_path,
)

#: The largest ``--workers`` with ``--backend ray``: Ray tasks in flight on a cluster, whose CPUs
#: are not this machine's (the same bound as ``mkv sweep --workers``).
MAX_RAY_WORKERS = 256


def max_workers() -> int:
    """The largest ``--workers`` accepted for local worker processes: 4 per CPU."""
    return 4 * (os.cpu_count() or 1)


def _workers(text: str) -> int:
    v = positive_int(text)
    if v > MAX_RAY_WORKERS:
        raise argparse.ArgumentTypeError(
            f"expected at most {MAX_RAY_WORKERS} (Ray tasks in flight), got {text!r}")
    return v


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_env_arguments(p, required=True)
    p.add_argument("--policy", required=True, action="append", metavar="SPEC",
                   help=POLICY_HELP + "; repeat to compare several on the same seeds "
                        "(each spec at most once)")
    p.add_argument("--episodes", type=episodes_type, required=True, metavar="N",
                   help="episodes per policy")
    p.add_argument("--seed", type=seed, default=0, metavar="S",
                   help="episode i uses env seed S+i (default 0)")
    p.add_argument("--workers", type=_workers, default=1, metavar="N",
                   help="worker processes (default 1: run in this process; at most 4 per CPU) "
                        "or, with --backend ray, Ray tasks in flight (at most "
                        f"{MAX_RAY_WORKERS}); the numbers do not depend on it")
    p.add_argument("--backend", choices=("local", "ray"), default="local",
                   help="local: processes on this machine (default); ray: the same work units "
                        "as Ray tasks (the scale extra); identical numbers")
    p.add_argument("--address", default=None, metavar="ADDR",
                   help="with --backend ray: a Ray cluster address (default: start Ray here "
                        "with --workers CPUs)")
    p.add_argument("--json", metavar="OUT.json",
                   help="also write the metrics and confidence intervals as JSON")
    p.add_argument("--plot", metavar="OUT.png",
                   help="also write a bar plot of every metric (needs matplotlib)")
    add_quiet_argument(p)
    add_trust_argument(p)


def _check_plot(path: str) -> None:
    check_output_path(path, "plot")
    try:
        from matplotlib.backend_bases import FigureCanvasBase
    except ImportError:
        raise CliError("--plot needs matplotlib (pip install 'mkv-sfm[plots]')") from None
    ext = os.path.splitext(path)[1].lstrip(".").lower()
    formats = FigureCanvasBase.get_supported_filetypes()
    if ext not in formats:
        raise CliError(f"plot {path}: unsupported file type {ext or '(none)'!r}; use one of "
                       + ", ".join(sorted(formats)))


def run(args) -> int:
    apply_trust(args)
    from sfm_learn.evaluation import evaluate_many, evaluations_json
    from sfm_learn.reporting.tables import format_markdown

    specs = [s.strip() for s in args.policy]
    seen = set()
    for s in specs:
        if s in seen:
            raise CliError(f"--policy {s} given more than once")
        seen.add(s)
    outputs = [p for p in (args.json, args.plot) if p]
    check_outputs([spec_path(s) for s in specs], outputs)
    if args.json:
        check_output_path(args.json, "JSON output")
        check_writable(args.json, "JSON output")
    if args.plot:
        _check_plot(args.plot)
        check_writable(args.plot, "plot")
    check_env_and_policies(args.env, args.env_kwargs, specs)
    if args.backend == "local" and args.workers > max_workers():
        raise CliError(f"--workers: expected at most {max_workers()} (4 per CPU) for local "
                       f"worker processes, got {args.workers}; a Ray cluster takes more "
                       "(--backend ray --address HOST:PORT)")
    if args.address is not None and args.backend != "ray":
        raise CliError("--address is for --backend ray")
    if args.address is not None and not args.address.strip():
        raise CliError("--address is empty; give HOST:PORT of a Ray cluster or leave it out")
    if args.backend == "ray":
        from sfm_learn.evaluation.ray_eval import check_workers_fit, init_ray

        try:
            ray = init_ray(args.address, args.workers)  # one-line error before any episode
            check_workers_fit(ray, args.workers)
        except ValueError as e:
            raise CliError(str(e)) from None

    desc = f"eval {specs[0]}" if len(specs) == 1 else f"eval {len(specs)} policies"
    with progress_for(args, args.episodes * len(specs), desc) as bar:
        results = evaluate_many(args.env, specs, args.episodes, args.seed, args.env_kwargs,
                                workers=args.workers, on_episode=lambda p, i, n: bar.update(1),
                                backend=args.backend, address=args.address)
    print(format_markdown(results))
    if args.plot:
        from sfm_learn.reporting.plots import plot_evaluations

        plot_evaluations(results, args.plot)
    if args.json:
        try:
            atomic_write_text(args.json, evaluations_json(results))
        except BaseException:
            if args.plot and os.path.exists(args.plot):
                os.unlink(args.plot)  # all or nothing
            raise
    for path in outputs:
        print(f"wrote {path}")
    return 0
