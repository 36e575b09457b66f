"""``mkv train-ppo``: Stable-Baselines3 PPO on the env reward (:mod:`sfm_learn.baselines.ppo`).

::

    mkv train-ppo --env MKVJam-v0 --timesteps 100000 --out ppo.zip [--seed 0] [--n-envs 2]
                  [--vec sync|async] [--eval-every STEPS] [--eval-episodes 10]
                  [--eval-seed 10000] [--checkpoint-dir DIR] [--env-kwargs JSON] [--quiet]
"""

from __future__ import annotations

import argparse
import os

from sfm_learn.baselines.ppo import DEFAULTS, check_env, fmt_point, planned_timesteps, save, train
from sfm_learn.cli.common import (
    CliError,
    add_env_arguments,
    add_quiet_argument,
    check_output_path,
    check_outputs,
    episodes_type,
    n_envs_type,
    non_negative_float,
    one_line,
    positive_float,
    positive_int,
    progress_for,
    seed,
    timesteps_type,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_env_arguments(p, required=True)
    p.add_argument(
        "--timesteps",
        type=timesteps_type,
        required=True,
        metavar="T",
        help="env steps to train on (rounded up to whole rollouts)",
    )
    p.add_argument("--out", required=True, metavar="PPO.zip")
    p.add_argument(
        "--seed",
        type=seed,
        default=0,
        metavar="S",
        help="seeds torch, the policy and the envs (env i starts at S+i); default 0",
    )
    p.add_argument(
        "--n-envs", type=n_envs_type, default=2, metavar="N", help="parallel envs (default 2)"
    )
    p.add_argument(
        "--vec",
        choices=("sync", "async"),
        default="sync",
        help="sync: envs stepped in this process (default, fastest on 2 cores); "
        "async: one subprocess per env",
    )
    p.add_argument(
        "--eval-every",
        type=positive_int,
        default=None,
        metavar="STEPS",
        help="evaluate every STEPS env steps (default: a tenth of the budget)",
    )
    p.add_argument(
        "--eval-episodes",
        type=episodes_type,
        default=10,
        metavar="N",
        help="episodes per evaluation (default 10)",
    )
    p.add_argument(
        "--eval-seed",
        type=seed,
        default=10_000,
        metavar="S",
        help="evaluation episode i uses env seed S+i (default 10000)",
    )
    p.add_argument(
        "--checkpoint-dir",
        default=None,
        metavar="DIR",
        help="also write DIR/ppo_<steps>.zip at every evaluation",
    )
    g = p.add_argument_group("PPO hyperparameters")
    g.add_argument(
        "--n-steps",
        type=positive_int,
        default=DEFAULTS["n_steps"],
        metavar="N",
        help=f"rollout steps per env (default {DEFAULTS['n_steps']})",
    )
    g.add_argument(
        "--batch-size",
        type=positive_int,
        default=DEFAULTS["batch_size"],
        metavar="B",
        help=f"minibatch size (default {DEFAULTS['batch_size']})",
    )
    g.add_argument(
        "--n-epochs",
        type=positive_int,
        default=DEFAULTS["n_epochs"],
        metavar="K",
        help=f"epochs per rollout (default {DEFAULTS['n_epochs']})",
    )
    g.add_argument(
        "--lr",
        type=positive_float,
        default=DEFAULTS["learning_rate"],
        metavar="LR",
        help=f"Adam learning rate (default {DEFAULTS['learning_rate']})",
    )
    g.add_argument(
        "--ent-coef",
        type=non_negative_float,
        default=DEFAULTS["ent_coef"],
        metavar="C",
        help=f"entropy coefficient (default {DEFAULTS['ent_coef']})",
    )
    add_quiet_argument(p)


def run(args) -> int:
    check_output_path(args.out)
    check_outputs([], [args.out])
    d = args.checkpoint_dir
    if d:
        if os.path.exists(d) and not os.path.isdir(d):
            raise CliError(f"checkpoint directory {d} exists and is not a directory")
        parent = os.path.dirname(os.path.abspath(d))
        if not os.path.isdir(parent):
            raise CliError(f"checkpoint directory parent {parent} does not exist")
    try:
        check_env(args.env, args.env_kwargs)  # one-line error before torch is imported
    except ValueError as e:
        raise CliError(one_line(e)) from None
    if d:
        os.makedirs(d, exist_ok=True)
    hp = {
        "n_steps": args.n_steps,
        "batch_size": args.batch_size,
        "n_epochs": args.n_epochs,
        "learning_rate": args.lr,
        "ent_coef": args.ent_coef,
    }
    total = planned_timesteps(args.timesteps, args.n_envs, args.n_steps)
    with progress_for(args, total, f"train-ppo {args.env}", unit="step") as bar:
        log = None if args.quiet else bar.write
        model, meta = train(
            args.env,
            args.timesteps,
            seed=args.seed,
            n_envs=args.n_envs,
            vec=args.vec,
            env_kwargs=args.env_kwargs,
            eval_every=args.eval_every,
            eval_episodes=args.eval_episodes,
            eval_seed=args.eval_seed,
            checkpoint_dir=args.checkpoint_dir,
            hyperparameters=hp,
            progress=bar,
            log=log,
        )
    save(model, meta, args.out)
    rate = meta["timesteps"] / meta["train_wall_s"] if meta["train_wall_s"] > 0 else float("nan")
    print(
        f"{meta['timesteps']} env steps in {meta['train_wall_s']:.1f} s "
        f"({rate:.0f} steps/s; evaluation {meta['eval_wall_s']:.1f} s more)"
    )
    first, last = meta["learning_curve"][0], meta["final_eval"]
    seeds = f"{args.eval_seed}..{args.eval_seed + args.eval_episodes - 1}"
    print(f"evaluation, {args.eval_episodes} episodes on seeds {seeds}, deterministic actions:")
    print(f"  before training {fmt_point(first)}")
    print(f"  after training  {fmt_point(last)}")
    print(f"wrote {args.out}")
    return 0
