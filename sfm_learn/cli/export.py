"""``mkv export``: a dataset file into Minari, the offline-RL dataset standard.

::

    mkv export DATA.npz --minari NAMESPACE/NAME-vN [--overwrite] [--data-path DIR]

The dataset goes to Minari's local store (``MINARI_DATASETS_PATH`` or ``--data-path``); see
:mod:`mkv_env.minari_io` and docs/minari.md. ``mkv import-minari`` reads it back.
"""

from __future__ import annotations

import argparse

from sfm_learn.cli.common import CliError, load_dataset, one_line


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", metavar="DATA.npz", help="a dataset file (mkv record, mkv teleop)")
    p.add_argument("--minari", required=True, metavar="ID",
                   help="Minari dataset id, NAMESPACE/NAME-vVERSION, e.g. mkv/teacher-v0")
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset")
    p.add_argument("--data-path", metavar="DIR",
                   help="Minari's dataset folder (default: MINARI_DATASETS_PATH or "
                        "~/.minari/datasets)")


def run(args) -> int:
    from mkv_env.minari_io import MinariError, export_minari

    data = load_dataset(args.data)
    try:
        export_minari(data, args.minari, overwrite=args.overwrite, data_path=args.data_path)
    except MinariError as e:
        raise CliError(one_line(e)) from None
    print(f"wrote Minari dataset {args.minari}: {data.n_episodes} episodes, {data.n_steps} steps")
    return 0
