"""``mkv import-minari``: a Minari dataset written by ``mkv export`` back into a dataset file.

::

    mkv import-minari NAMESPACE/NAME-vN --out DATA.npz [--data-path DIR]
"""

from __future__ import annotations

import argparse

from sfm_learn.cli.common import CliError, check_output_path, check_outputs, one_line


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset_id", metavar="ID", help="local Minari dataset id")
    p.add_argument("--out", required=True, metavar="DATA.npz",
                   help="dataset file to write (as mkv record writes)")
    p.add_argument("--data-path", metavar="DIR",
                   help="Minari's dataset folder (default: MINARI_DATASETS_PATH or "
                        "~/.minari/datasets)")


def run(args) -> int:
    from mkv_env.dataset import save
    from mkv_env.minari_io import MinariError, import_minari

    check_output_path(args.out)
    check_outputs([], [args.out])
    try:
        data = import_minari(args.dataset_id, data_path=args.data_path)
    except MinariError as e:
        raise CliError(one_line(e)) from None
    save(data, args.out)
    print(f"wrote {args.out}: {data.n_episodes} episodes, {data.n_steps} steps")
    return 0
