"""``mkv eval``: evaluate policies on the same seeded episodes (see :mod:`sfm_learn.evaluation`)."""

from __future__ import annotations

import argparse

from sfm_learn.cli import (
    _add_env_args,
    _add_quiet,
    _positive_int,
    _seed,
    atomic_write_text,
    check_env_and_policy,
    check_output_path,
    progress_for,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    _add_env_args(p, required=True)
    p.add_argument("--policy", required=True, metavar="SPEC")
    p.add_argument("--episodes", type=_positive_int, required=True, metavar="N")
    p.add_argument("--seed", type=_seed, default=0, metavar="S")
    p.add_argument("--json", metavar="OUT.json", help="also write the metrics as JSON")
    _add_quiet(p)


def run(args) -> int:
    from sfm_learn.evaluation import evaluate, format_table

    if args.json:
        check_output_path(args.json, "JSON output")
    check_env_and_policy(args.env, args.env_kwargs, args.policy)
    with progress_for(args, args.episodes, f"eval {args.policy}") as bar:
        result = evaluate(args.env, args.policy, args.episodes, args.seed, args.env_kwargs,
                          on_episode=lambda i, n: bar.update(1))
    print(format_table([result]))
    if args.json:
        atomic_write_text(args.json, result.to_json())
        print(f"wrote {args.json}")
    return 0
