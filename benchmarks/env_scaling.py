"""Robots per core: one thread's robot-steps per second, and memory per robot, from 16 to 4,096
robots, beside Gymnasium's LunarLander-v3 (the named peer) through its sync vector env at the
same sizes, measured in the same run.

Each size of MKV-v1 and MKVJam-v1 runs the native vector env (``vectorization_mode=
"vector_entry_point"``, one thread) on random actions from a fixed seed, autoresets included,
after two warm-up steps; LunarLander-v3 runs ``gymnasium.make_vec(..., vectorization_mode="sync")``.
Every rate is the median of ``--rounds`` rounds that alternate over the sizes and envs, so
background load hits all alike. Memory per robot is the growth of the resident set (RSS, from
/proc/self/statm) of a fresh Python process from just before ``make_vec`` to after ``reset`` and
five steps, divided by the number of robots; it is measured once per size in its own process.

Prints the table, the 4,096-robot rate over the 16-robot rate (issue target >= 0.85) and the
memory per robot at 4,096 robots (target <= 64 KiB), and, with matplotlib installed, draws the
curve to ``--png``. Exits 0; a missed target is printed as ``MISSED``.

    python benchmarks/env_scaling.py [--robot-steps 200000] [--rounds 3] [--png env_scaling.png]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
import warnings

import gymnasium as gym

import mkv_env  # noqa: F401  (registers the ids)

warnings.filterwarnings("ignore", category=DeprecationWarning)

SIZES = (16, 64, 256, 1024, 4096)
ENVS = ("MKV-v1", "MKVJam-v1", "LunarLander-v3")


def _make(env_id: str, n: int):
    if env_id.startswith("MKV"):
        return gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point",
                            num_threads=1)
    return gym.make_vec(env_id, num_envs=n, vectorization_mode="sync")


def robot_steps_per_second(env_id: str, n: int, robot_steps: int) -> float:
    """One thread's robot-steps per second of ``n`` robots: random actions, autoresets included."""
    envs = _make(env_id, n)
    envs.action_space.seed(0)
    envs.reset(seed=0)
    steps = max(robot_steps // n, 4)
    acts = [envs.action_space.sample() for _ in range(steps + 2)]
    for a in acts[:2]:  # warm-up: the first steps allocate the physics engine's buffers
        envs.step(a)
    t0 = time.perf_counter()
    for a in acts[2:]:
        envs.step(a)
    seconds = time.perf_counter() - t0
    envs.close()
    return steps * n / seconds


def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _memory_child(env_id: str, n: int) -> None:
    before = _rss_bytes()
    envs = _make(env_id, n)
    envs.action_space.seed(0)
    envs.reset(seed=0)
    for _ in range(5):
        envs.step(envs.action_space.sample())
    print(json.dumps({"per_robot": (_rss_bytes() - before) / n}))


def memory_per_robot(env_id: str, n: int) -> float:
    """RSS growth per robot in a fresh process (bytes), from before ``make_vec`` to after five
    steps."""
    out = subprocess.run([sys.executable, __file__, "--memory-child", env_id, str(n)],
                         check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])["per_robot"]


def _verdict(ok: bool) -> str:
    return "met" if ok else "MISSED"


def _plot(path: str, rates: dict, mem: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    for env_id in ENVS:
        a.plot(SIZES, [rates[env_id, n] for n in SIZES], marker="o", label=env_id)
        b.plot(SIZES, [mem[env_id, n] / 1024 for n in SIZES], marker="o", label=env_id)
    for ax in (a, b):
        ax.set_xscale("log", base=2)
        ax.set_xlabel("robots (envs) on one thread")
        ax.grid(alpha=0.3)
    a.set_yscale("log")
    a.set_ylabel("robot-steps per second (median)")
    a.set_title("one thread's rate")
    b.set_yscale("log")
    b.axhline(64, color="grey", ls="--", lw=1, label="target: 64 KiB")
    b.set_ylabel("RSS growth per env (KiB)")
    b.set_title("memory per env (fresh process)")
    a.legend(fontsize=8)
    b.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    if argv is None and len(sys.argv) == 4 and sys.argv[1] == "--memory-child":
        _memory_child(sys.argv[2], int(sys.argv[3]))
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot-steps", type=int, default=200_000,
                    help="robot-steps timed per size and round (default 200,000)")
    ap.add_argument("--rounds", type=int, default=3,
                    help="alternating rounds; the median of each is reported")
    ap.add_argument("--png", default="env_scaling.png", help="where to draw the curve")
    ap.add_argument("--target-size", type=int, default=SIZES[-1],
                    help="the size the targets are read at (default the largest, 4,096)")
    args = ap.parse_args(argv)
    if args.robot_steps < 1 or args.rounds < 1:
        ap.error("--robot-steps and --rounds must be at least 1")
    if args.target_size not in SIZES:
        ap.error(f"--target-size must be one of {', '.join(map(str, SIZES))}")
    runs: dict[tuple[str, int], list[float]] = {(e, n): [] for e in ENVS for n in SIZES}
    for _ in range(args.rounds):
        for n in SIZES:
            for env_id in ENVS:
                runs[env_id, n].append(robot_steps_per_second(env_id, n, args.robot_steps))
    rates = {k: statistics.median(v) for k, v in runs.items()}
    mem = {(e, n): memory_per_robot(e, n) for e in ENVS for n in SIZES}
    print(f"{'env':<16}{'robots':>8}{'robot-steps/s':>15}{'x smallest':>12}{'KiB/robot':>11}"
          "   all rounds")
    for env_id in ENVS:
        for n in SIZES:
            r = rates[env_id, n]
            print(f"{env_id:<16}{n:>8}{r:>15,.0f}{r / rates[env_id, SIZES[0]]:>12.2f}"
                  f"{mem[env_id, n] / 1024:>11.1f}   "
                  + "  ".join(f"{x:,.0f}" for x in runs[env_id, n]))
    print("\ntargets (medians):")
    big, small = args.target_size, SIZES[0]
    for env_id in ("MKV-v1", "MKVJam-v1"):
        flat = rates[env_id, big] / rates[env_id, small]
        kib = mem[env_id, big] / 1024
        print(f"  {env_id}: {big:,}-robot rate / {small:,}-robot rate = {flat:4.2f}   "
              f"(target >= 0.85: {_verdict(flat >= 0.85)})")
        print(f"  {env_id}: memory per robot at {big:,} = {kib:6.1f} KiB   "
              f"(target <= 64: {_verdict(kib <= 64)})")
        print(f"  {env_id} / LunarLander-v3 at {big:,} robots = "
              f"{rates[env_id, big] / rates['LunarLander-v3', big]:5.2f}")
    try:
        _plot(args.png, rates, mem)
    except ImportError:
        print("\nmatplotlib is not installed: no plot")
    else:
        print(f"\nthe curve: {args.png}")


if __name__ == "__main__":
    main()
