"""``mkv train-dagger``: DAgger with the scripted teacher as the queried expert
(:mod:`sfm_learn.baselines.dagger`).

::

    mkv train-dagger --env MKV-v1 --rounds 4 --steps 12000 --out dagger.zip [--seed 0]
                     [--epochs 30] [--env-kwargs JSON] [--quiet]
"""

from __future__ import annotations

import argparse

from sfm_learn.baselines import dagger
from sfm_learn.baselines.bc import MIN_UPDATES
from sfm_learn.baselines.dagger import DEFAULTS, check_budget, save
from sfm_learn.cli.common import (
    CliError,
    add_env_arguments,
    add_quiet_argument,
    check_env_and_policies,
    check_output_path,
    check_outputs,
    int_in_range,
    one_line,
    positive_float,
    positive_int,
    progress_for,
    seed,
)

rounds_type = int_in_range(1, 100)
steps_type = int_in_range(2, 10_000_000)
updates_type = int_in_range(0, 10_000_000)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_env_arguments(p, required=True)
    p.add_argument("--out", required=True, metavar="DAGGER.zip",
                   help="model zip to write: an SB3 PPO zip holding the final policy, plus "
                        "mkv_meta.json (PPO.load reads it; run it as "
                        "--policy dagger:DAGGER.zip)")
    p.add_argument("--steps", type=steps_type, default=12_000, metavar="N",
                   help="teacher queries (labelled steps) over all rounds (default 12000); at "
                        "least 32 x rounds + 1, so round 0's fit has features + 1 rows")
    p.add_argument("--rounds", type=rounds_type, default=DEFAULTS["rounds"], metavar="R",
                   help=f"rounds; round 0 is the teacher driving (default {DEFAULTS['rounds']})")
    p.add_argument("--seed", type=seed, default=0, metavar="S",
                   help="episode seeds S + 1000*round + i; network seeds (default 0)")
    p.add_argument("--epochs", type=positive_int, default=DEFAULTS["epochs"], metavar="N",
                   help=f"epochs per round's refit (default {DEFAULTS['epochs']})")
    p.add_argument("--min-updates", type=updates_type, default=MIN_UPDATES, metavar="N",
                   help="at least N minibatch updates per refit: more epochs on small data "
                        f"(default {MIN_UPDATES}; 0: exactly --epochs)")
    p.add_argument("--lr", type=positive_float, default=DEFAULTS["lr"], metavar="LR",
                   help=f"Adam learning rate (default {DEFAULTS['lr']})")
    add_quiet_argument(p)


def run(args) -> int:
    check_output_path(args.out)
    check_outputs([], [args.out])
    check_env_and_policies(args.env, args.env_kwargs, ["teacher"])
    try:  # before any episode runs (dagger.min_steps says why this minimum)
        check_budget(args.env, args.steps, args.rounds, args.env_kwargs, what="--steps")
    except ValueError as e:
        raise CliError(one_line(e)) from None
    with progress_for(args, args.rounds, f"train-dagger {args.env}", unit="round") as bar:
        def on_round(r, info):
            bar.update(1)
            if not args.quiet:
                bar.write(f"round {r}: {info['driver']} drove {info['rows']} steps "
                          f"({info['episodes']} episodes), teacher agreed with "
                          f"{info['agreement']:.3f}; refit on {info['total_rows']} rows")
        try:
            # through the module: a test's monkeypatch of dagger.train is seen and never kept
            policy, meta = dagger.train(args.env, args.steps, rounds=args.rounds, seed=args.seed,
                                        env_kwargs=args.env_kwargs, epochs=args.epochs,
                                        lr=args.lr, on_round=on_round,
                                        min_updates=args.min_updates)
        except ValueError as e:
            raise CliError(one_line(e)) from None
    save(policy, meta, args.out)
    print(f"DAgger: {meta['teacher_steps']} teacher queries in {args.rounds} rounds; "
          f"wrote {args.out}")
    return 0
