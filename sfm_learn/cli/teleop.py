"""``mkv teleop``: drive the robot with the arrow keys and record the run as a dataset.

::

    mkv teleop [--env MKV-v0] [--episodes 1] [--seed 0] [--fps 10] [--zoom 1] --out RUN.npz

Up drives forward, down reverses, left/right steer, Escape ends. Needs a display; without one,
or when DISPLAY/WAYLAND_DISPLAY names one that no server answers for, it refuses in one line
(headless teleop: ``mkv record --policy script:COMMANDS.txt``).
"""

from __future__ import annotations

import argparse

from sfm_learn.cli.common import (
    CliError,
    add_env_arguments,
    check_output_path,
    check_outputs,
    int_in_range,
    one_line,
    positive_float,
    seed,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_env_arguments(p)
    p.add_argument("--episodes", type=int_in_range(1, 1000), default=1, metavar="N",
                   help="episodes to drive (default 1); episode i uses env seed S+i")
    p.add_argument("--seed", type=seed, default=0, metavar="S",
                   help="episode i uses env seed S+i (default 0)")
    p.add_argument("--fps", type=int_in_range(1, 60), default=10,
                   help="control steps per second of wall time (default 10: real time)")
    p.add_argument("--zoom", type=positive_float, default=1.0, help="window scale (default 1)")
    p.add_argument("--out", required=True, metavar="RUN.npz",
                   help="dataset file to write with the driven episodes (as mkv record "
                        "writes)")


def run(args) -> int:
    from mkv_env.dataset import save
    from mkv_env.recorder import summarize
    from mkv_env.teleop import TeleopError, record_keyboard

    check_output_path(args.out)
    check_outputs([], [args.out])
    try:
        data = record_keyboard(args.env, args.episodes, args.seed, args.env_kwargs, args.fps,
                               args.zoom)
    except TeleopError as e:
        raise CliError(one_line(e)) from None
    save(data, args.out)
    s = summarize(data)
    print(f"{s['episodes']} episodes, {s['steps']} steps driven by hand; wrote {args.out}")
    return 0
