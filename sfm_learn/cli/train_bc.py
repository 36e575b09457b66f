"""``mkv train-bc``: behaviour-clone an SB3 policy from teacher demonstrations
(:mod:`sfm_learn.baselines.bc`).

::

    mkv train-bc DATA.npz --out bc.zip [--epochs 30] [--min-updates 1000] [--batch-size 256]
                 [--lr 1e-3] [--seed 0] [--held-out 0.2] [--features default|raw] [--quiet]
"""

from __future__ import annotations

import argparse
import os

from sfm_learn.baselines.bc import (
    ACTION_NAMES,
    DEFAULTS,
    VALUE_NAMES,
    check_rows,
    save,
    train,
)
from sfm_learn.cli.common import (
    CliError,
    add_quiet_argument,
    check_output_path,
    check_outputs,
    fraction,
    int_in_range,
    load_dataset,
    one_line,
    positive_float,
    positive_int,
    progress_for,
    seed,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", metavar="DATA.npz",
                   help="demonstrations (mkv record); at least features + 1 steps (33 by default, "
                        "11 for --features raw)")
    p.add_argument("--out", required=True, metavar="BC.zip",
                   help="model zip to write: an SB3 PPO zip holding the cloned policy, plus "
                        "mkv_meta.json (PPO.load reads it; run it as --policy bc:BC.zip)")
    p.add_argument(
        "--epochs",
        type=positive_int,
        default=DEFAULTS["epochs"],
        metavar="N",
        help=f"passes over the training rows (default {DEFAULTS['epochs']})",
    )
    p.add_argument(
        "--min-updates",
        type=int_in_range(0, 10_000_000),
        default=DEFAULTS["min_updates"],
        metavar="N",
        help="at least N minibatch updates: more epochs on small data (default "
        f"{DEFAULTS['min_updates']}; 0: exactly --epochs)",
    )
    p.add_argument(
        "--batch-size",
        type=positive_int,
        default=DEFAULTS["batch_size"],
        metavar="B",
        help=f"minibatch rows (default {DEFAULTS['batch_size']})",
    )
    p.add_argument(
        "--lr",
        type=positive_float,
        default=DEFAULTS["lr"],
        metavar="LR",
        help=f"Adam learning rate (default {DEFAULTS['lr']})",
    )
    p.add_argument(
        "--seed",
        type=seed,
        default=0,
        metavar="S",
        help="seeds the split, initialisation and shuffling (default 0)",
    )
    p.add_argument(
        "--held-out",
        type=fraction,
        default=DEFAULTS["held_out"],
        metavar="FRACTION",
        help="fraction of episodes held out to measure accuracy on (default "
        f"{DEFAULTS['held_out']}); the saved policy is then refitted on every episode",
    )
    p.add_argument(
        "--features",
        choices=("default", "raw"),
        default="default",
        help="default: the SfM policy's features (traces, previous command); "
        "raw: the observation only",
    )
    add_quiet_argument(p)


def _fmt_acc(acc: dict | None) -> str:
    if not acc:
        return "-"
    return ", ".join(f"{k} {v:.3f}" for k, v in acc.items() if v is not None)


def _refit_line(args, rows: int, epochs: int, held_epochs: int | None) -> str:
    """The line that starts the refit: on every row, for the saved policy, and where its epoch
    count comes from (planned from all rows as the held-out fit's was from its rows)."""
    batches = -(-rows // args.batch_size)
    if epochs > args.epochs:
        why = (f"--epochs {args.epochs} raised to reach --min-updates {args.min_updates} at "
               f"{batches} minibatches per epoch")
        if held_epochs is not None and held_epochs != epochs:
            why += f"; the held-out fit above ran {held_epochs} on its fewer rows"
    else:
        why = f"--epochs {args.epochs}, {batches} minibatches per epoch"
    return f"refit of the saved policy on all {rows} rows: {epochs} epochs ({why})"


def run(args) -> int:
    check_output_path(args.out)
    check_outputs([args.data], [args.out])
    data = load_dataset(args.data)
    try:  # before any training or writing (bc.min_rows says why this minimum)
        check_rows(data, held_out=args.held_out, seed=args.seed, features=args.features,
                   what=f"dataset {args.data}")
    except ValueError as e:
        raise CliError(one_line(e)) from None
    if data.n_episodes < 2 and args.held_out > 0:
        print(f"note: {args.data} has one episode; nothing held out")
    with progress_for(args, args.epochs, f"train-bc {os.path.basename(args.data)}",
                      unit="epoch") as bar:

        held_fit = {}

        def on_epoch(epoch, rec):
            held_fit["epochs"] = bar.total = rec["of"]
            bar.update(1)
            if not args.quiet:
                line = f"epoch {epoch}/{rec['of']}: train NLL {rec['train_nll']:.4f}"
                if "held_out_nll" in rec:
                    line += (
                        f", held-out NLL {rec['held_out_nll']:.4f}, accuracy "
                        f"{_fmt_acc(rec['held_out_accuracy'])}"
                    )
                bar.write(line)

        def on_refit(epoch, rec):
            if epoch == 1:  # the first epoch of the refit: say what it is
                bar.total = bar.n + rec["of"]
                if not args.quiet:
                    bar.write(_refit_line(args, data.n_steps, rec["of"], held_fit.get("epochs")))
            bar.update(1)

        policy, meta = train(
            data,
            epochs=args.epochs,
            batch_size=args.batch_size,
            lr=args.lr,
            seed=args.seed,
            held_out=args.held_out,
            features=args.features,
            on_epoch=on_epoch,
            min_updates=args.min_updates,
            on_refit=on_refit,
        )
    meta["dataset"]["file"] = os.path.basename(args.data)
    save(policy, meta, args.out)
    print(
        f"saved policy: {meta['teacher_steps']} training rows ({meta['teacher_episodes']} "
        "episodes), "
        f"{meta['epochs']} epochs ({meta['updates']} updates) in {meta['train_wall_s']:.1f} s, "
        f"{len(meta['feature_spec']['obs_names'])} channels -> "
        f"{len(meta['input_mean'])} {args.features} features"
    )
    held = meta["held_out"]
    if held is None:
        print(f"train accuracy {_fmt_acc(meta['train_accuracy'])} (nothing held out)")
    else:
        print(
            f"held-out ({meta['held_out_episodes']} episodes, {meta['held_out_steps']} rows, "
            f"measured on a network trained on the other {meta['validation_trained_steps']}; "
            "the saved policy was then refitted on every row): "
            f"accuracy {_fmt_acc(held['accuracy'])}; majority-class baseline "
            f"{_fmt_acc(held['majority_accuracy'])}; both right {held['joint_accuracy']:.3f}"
        )
        for name in ACTION_NAMES:
            parts = [
                f"{v} {r:.2f} (n={s})" if r is not None else f"{v} - (n=0)"
                for v, r, s in zip(
                    VALUE_NAMES[name], held["recall"][name], held["support"][name], strict=True
                )
            ]
            print(f"  {name} recall: " + ", ".join(parts))
    print(f"wrote {args.out}")
    return 0
