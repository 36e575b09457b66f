"""``mkv eval``: evaluate policies on the same seeded episodes (see :mod:`sfm_learn.evaluation`).

::

    mkv eval --env MKVJam-v0 --policy teacher [--policy random ...] --episodes N [--seed S]
             [--workers N] [--json OUT.json] [--plot OUT.png] [--env-kwargs JSON] [--quiet]

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

from mkv_env.files import atomic_write_text
from sfm_learn.cli import (
    CliError,
    _add_env_args,
    _add_quiet,
    _positive_int,
    _seed,
    check_output_path,
    progress_for,
)


def max_workers() -> int:
    """The largest ``--workers`` accepted: 4 per CPU."""
    return 4 * (os.cpu_count() or 1)


def _workers(text: str) -> int:
    v = _positive_int(text)
    if v > max_workers():
        raise argparse.ArgumentTypeError(
            f"expected at most {max_workers()} (4 per CPU), got {text!r}")
    return v


def add_arguments(p: argparse.ArgumentParser) -> None:
    _add_env_args(p, required=True)
    p.add_argument("--policy", required=True, action="append", metavar="SPEC",
                   help="teacher, teacher:key=value,..., random, script:PATH, sfm:PATH, "
                        "ppo:PATH, bc:PATH; repeat to compare several on the same seeds "
                        "(each spec at most once)")
    p.add_argument("--episodes", type=_positive_int, required=True, metavar="N",
                   help="episodes per policy")
    p.add_argument("--seed", type=_seed, default=0, metavar="S",
                   help="episode i uses env seed S+i (default 0)")
    p.add_argument("--workers", type=_workers, default=1, metavar="N",
                   help="worker processes (default 1: run in this process); the numbers do "
                        "not depend on it")
    p.add_argument("--json", metavar="OUT.json",
                   help="also write the metrics and confidence intervals as JSON")
    p.add_argument("--plot", metavar="OUT.png",
                   help="also write a bar plot of every metric (needs matplotlib)")
    _add_quiet(p)


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


def _check_writable(path: str, what: str) -> None:
    directory = os.path.dirname(os.path.abspath(path))
    if not os.access(directory, os.W_OK | os.X_OK):
        raise CliError(f"{what} directory {directory} is not writable")


def check_specs(env_id: str, env_kwargs: dict, specs: list[str]) -> None:
    """Fail fast: the env must build and every spec must load (a bad one named in one line)."""
    from mkv_env.policies import PolicySpecError, make_policy
    from mkv_env.recorder import make_env

    try:
        env = make_env(env_id, env_kwargs)
    except ValueError as e:
        raise CliError(str(e).splitlines()[0]) from None
    try:
        for spec in specs:
            try:
                make_policy(spec, env, seed=0)
            except PolicySpecError as e:
                text = str(e).splitlines()[0] if str(e).strip() else type(e).__name__
                if len(specs) > 1 and spec not in text:
                    text = f"--policy {spec}: {text}"
                raise CliError(text) from None
    finally:
        env.close()


def run(args) -> int:
    from sfm_learn.evaluation import evaluate_many, evaluations_json, format_markdown

    specs = [s.strip() for s in args.policy]
    seen = set()
    for s in specs:
        if s in seen:
            raise CliError(f"--policy {s} given more than once")
        seen.add(s)
    outputs = [p for p in (args.json, args.plot) if p]
    if len(outputs) == 2 and os.path.abspath(args.json) == os.path.abspath(args.plot):
        raise CliError("--json and --plot name the same file")
    if args.json:
        check_output_path(args.json, "JSON output")
        _check_writable(args.json, "JSON output")
    if args.plot:
        _check_plot(args.plot)
        _check_writable(args.plot, "plot")
    check_specs(args.env, args.env_kwargs, specs)

    desc = f"eval {specs[0]}" if len(specs) == 1 else f"eval {len(specs)} policies"
    with progress_for(args, args.episodes * len(specs), desc) as bar:
        results = evaluate_many(args.env, specs, args.episodes, args.seed, args.env_kwargs,
                                workers=args.workers, on_episode=lambda p, i, n: bar.update(1))
    print(format_markdown(results))
    if args.plot:
        from sfm_learn.evaluation import plot_evaluations

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
