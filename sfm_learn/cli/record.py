"""``mkv record``: run a policy in an env and write its episodes to a dataset file.

::

    mkv record --env MKV-v0 --policy teacher --episodes N [--seed S] --out DATA.npz
"""

from __future__ import annotations

import argparse

from sfm_learn.cli.common import (
    POLICY_HELP,
    add_env_arguments,
    add_quiet_argument,
    add_trust_argument,
    apply_trust,
    check_env_and_policies,
    check_output_path,
    check_outputs,
    episodes_type,
    progress_for,
    seed,
    spec_path,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_env_arguments(p, required=True)
    p.add_argument("--policy", required=True, metavar="SPEC",
                   help=POLICY_HELP)
    p.add_argument("--episodes", type=episodes_type, required=True, metavar="N",
                   help="episodes to record (at most 10,000,000)")
    p.add_argument("--seed", type=seed, default=0, metavar="S",
                   help="episode i uses env seed S+i (default 0)")
    p.add_argument("--out", required=True, metavar="DATA.npz",
                   help="dataset file to write (observations, commands, rewards per step; "
                        "mkv_env.dataset)")
    add_quiet_argument(p)
    add_trust_argument(p)


def run(args) -> int:
    apply_trust(args)
    from mkv_env.dataset import save
    from mkv_env.recorder import record, summarize

    check_output_path(args.out)
    check_outputs([spec_path(args.policy)], [args.out])
    check_env_and_policies(args.env, args.env_kwargs, [args.policy])
    with progress_for(args, args.episodes, f"record {args.env}") as bar:
        data = record(args.env, args.policy, args.episodes, args.seed, args.env_kwargs,
                      on_episode=lambda i, n: bar.update(1))
    save(data, args.out)
    s = summarize(data)
    line = (f"{s['episodes']} episodes, {s['steps']} steps, {s['jams']} jams, "
            f"{s['escapes']} escapes, stuck fraction {s['stuck_fraction']:.3f}")
    if "escaped_episodes" in s:
        line += f", {s['escaped_episodes']}/{s['episodes']} episodes escaped"
    print(line)
    print(f"wrote {args.out}")
    return 0
