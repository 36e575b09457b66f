"""``mkv train-ppo``: Stable-Baselines3 PPO on the env reward (:mod:`sfm_learn.baselines.ppo`).

::

    mkv train-ppo --env MKVJam-v1 --out ppo.zip [--timesteps T] [--seed 0] [--n-envs N]
                  [--hyperparams FILE] [--observation raw|features] [--vec sync|async]
                  [--eval-every STEPS] [--eval-episodes 10] [--eval-seed 10000]
                  [--checkpoint-dir DIR] [--env-kwargs JSON] [--quiet]

Settings come from an rl-zoo3-style hyperparameter file (the packaged
``sfm_learn/baselines/hyperparams/ppo.yml`` unless ``--hyperparams``): the entry of ``--env`` or
its ``default``; flags given on the command line override it.
"""

from __future__ import annotations

import argparse
import os

from sfm_learn.baselines.ppo import (
    OBSERVATIONS,
    check_env,
    fmt_point,
    load_hyperparameters,
    planned_timesteps,
    save,
    train,
)
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
        default=None,
        metavar="T",
        help="env steps to train on (rounded up to whole rollouts; default: the "
        "hyperparameter file's n_timesteps)",
    )
    p.add_argument(
        "--hyperparams",
        default=None,
        metavar="FILE",
        help="rl-zoo3-style YAML of settings per env id (default: the packaged ppo.yml)",
    )
    p.add_argument(
        "--observation",
        choices=OBSERVATIONS,
        default=None,
        help="raw: the rescaled sensors; features: plus decaying traces and the previous "
        "command, as SfM/BC see them (default: from the hyperparameter file)",
    )
    p.add_argument("--out", required=True, metavar="PPO.zip",
                   help="model zip to write: SB3's PPO zip plus mkv_meta.json "
                        "(PPO.load reads it; run it as --policy ppo:PPO.zip)")
    p.add_argument(
        "--seed",
        type=seed,
        default=0,
        metavar="S",
        help="seeds torch, the policy and the envs (env i starts at S+i); default 0",
    )
    p.add_argument(
        "--n-envs", type=n_envs_type, default=None, metavar="N",
        help="parallel envs (default: from the hyperparameter file)"
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
    p.add_argument(
        "--tensorboard",
        default=None,
        metavar="DIR",
        help="write TensorBoard logs (returns, losses, evaluations) to DIR/PPO_<seed>_<n>; "
        "watch with: tensorboard --logdir DIR (needs the tensorboard package)",
    )
    g = p.add_argument_group("PPO hyperparameters")
    g.add_argument(
        "--n-steps",
        type=positive_int,
        default=None,
        metavar="N",
        help="rollout steps per env (default: from the hyperparameter file)",
    )
    g.add_argument(
        "--batch-size",
        type=positive_int,
        default=None,
        metavar="B",
        help="minibatch size (default: from the hyperparameter file)",
    )
    g.add_argument(
        "--n-epochs",
        type=positive_int,
        default=None,
        metavar="K",
        help="epochs per rollout (default: from the hyperparameter file)",
    )
    g.add_argument(
        "--lr",
        type=positive_float,
        default=None,
        metavar="LR",
        help="Adam learning rate (default: from the hyperparameter file)",
    )
    g.add_argument(
        "--ent-coef",
        type=non_negative_float,
        default=None,
        metavar="C",
        help="entropy coefficient (default: from the hyperparameter file)",
    )
    add_quiet_argument(p)


def run(args) -> int:
    check_output_path(args.out)
    check_outputs([args.hyperparams] if args.hyperparams else [], [args.out])
    d = args.checkpoint_dir
    if d:
        if os.path.exists(d) and not os.path.isdir(d):
            raise CliError(f"checkpoint directory {d} exists and is not a directory")
        parent = os.path.dirname(os.path.abspath(d))
        if not os.path.isdir(parent):
            raise CliError(f"checkpoint directory parent {parent} does not exist")
    tb = args.tensorboard
    if tb:
        if os.path.exists(tb) and not os.path.isdir(tb):
            raise CliError(f"--tensorboard {tb} exists and is not a directory")
        if not os.path.isdir(os.path.dirname(os.path.abspath(tb))):
            raise CliError(f"--tensorboard {tb}: its parent directory does not exist")
        try:
            import tensorboard  # noqa: F401
        except ImportError:
            raise CliError("--tensorboard needs the tensorboard package: pip install "
                           "tensorboard (or the project's [tensorboard] extra)") from None
    try:
        check_env(args.env, args.env_kwargs)  # one-line error before torch is imported
        hp = load_hyperparameters(args.env, args.hyperparams)
    except ValueError as e:
        raise CliError(one_line(e)) from None
    overrides = {"n_steps": args.n_steps, "batch_size": args.batch_size,
                 "n_epochs": args.n_epochs, "learning_rate": args.lr,
                 "ent_coef": args.ent_coef, "n_envs": args.n_envs,
                 "n_timesteps": args.timesteps, "observation": args.observation}
    hp.update({k: v for k, v in overrides.items() if v is not None})
    n_envs, timesteps = hp.pop("n_envs"), hp.pop("n_timesteps")
    observation = hp.pop("observation")
    if d:
        os.makedirs(d, exist_ok=True)
    if args.tensorboard:
        os.makedirs(args.tensorboard, exist_ok=True)
    total = planned_timesteps(timesteps, n_envs, hp["n_steps"])
    with progress_for(args, total, f"train-ppo {args.env}", unit="step") as bar:
        log = None if args.quiet else bar.write
        model, meta = train(
            args.env,
            timesteps,
            seed=args.seed,
            n_envs=n_envs,
            vec=args.vec,
            env_kwargs=args.env_kwargs,
            eval_every=args.eval_every,
            eval_episodes=args.eval_episodes,
            eval_seed=args.eval_seed,
            checkpoint_dir=args.checkpoint_dir,
            hyperparameters=hp,
            observation=observation,
            progress=bar,
            log=log,
            tensorboard_dir=args.tensorboard,
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
