"""Recorder overhead: recording teacher episodes vs stepping the same env with the same policy.

Both sides run ``MKV-v0`` with the scripted teacher on the same seeds (episode i uses seed i) for
at least ``--steps`` steps. "plain" is the bare loop (reset, predict, step); "recorded" is
:func:`mkv_env.recorder.record` (the same loop feeding an :class:`EpisodeRecorder`, then stacking
the arrays, checksumming and validating) followed by :func:`mkv_env.dataset.save` to a
temporary file. The two are interleaved for ``--rounds`` rounds and the best time of each is
kept. Target: recorded / plain <= 1.20.

    python benchmarks/recorder_overhead.py [--steps 100000] [--rounds 2]
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
import time

import gymnasium as gym

import mkv_env  # noqa: F401  (registers the ids)
from mkv_env.dataset import save
from mkv_env.policies import make_policy
from mkv_env.recorder import policy_seed, record

ENV_ID = "MKV-v0"


def plain(episodes: int) -> tuple[float, int]:
    """Seconds and steps of the bare loop: no recording."""
    env = gym.make(ENV_ID)
    policy = make_policy("teacher", env, seed=policy_seed(0))
    steps = 0
    t0 = time.perf_counter()
    for seed in range(episodes):
        obs, info = env.reset(seed=seed)
        policy.reset(seed=policy_seed(seed))
        start = True
        while True:
            action, _ = policy.predict(obs, episode_start=start)
            start = False
            obs, reward, terminated, truncated, info = env.step(action)
            steps += 1
            if terminated or truncated:
                break
    dt = time.perf_counter() - t0
    env.close()
    return dt, steps


def recorded(episodes: int, directory: str) -> tuple[float, int]:
    """Seconds and steps of recording the same episodes and saving the dataset."""
    t0 = time.perf_counter()
    data = record(ENV_ID, "teacher", episodes, seed=0)
    save(data, os.path.join(directory, "bench.npz"))
    return time.perf_counter() - t0, data.n_steps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=100_000)
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    episode_steps = gym.spec(ENV_ID).max_episode_steps
    episodes = math.ceil(args.steps / episode_steps)
    best_plain = best_rec = math.inf
    with tempfile.TemporaryDirectory() as d:
        for r in range(args.rounds):
            tp, n_plain = plain(episodes)
            tr, n_rec = recorded(episodes, d)
            assert n_plain == n_rec, (n_plain, n_rec)
            best_plain, best_rec = min(best_plain, tp), min(best_rec, tr)
            print(f"round {r + 1}: plain {tp:.2f} s, recorded {tr:.2f} s, "
                  f"ratio {tr / tp:.3f} ({n_rec} steps)")
        size = os.path.getsize(os.path.join(d, "bench.npz"))
    ratio = best_rec / best_plain
    print(f"{ENV_ID}, teacher, {n_rec} steps in {episodes} episodes")
    print(f"plain    {best_plain:.2f} s  ({n_plain / best_plain:,.0f} steps/s)")
    print(f"recorded {best_rec:.2f} s  ({n_rec / best_rec:,.0f} steps/s), file {size / 1e6:.1f} MB")
    verdict = "met" if ratio <= 1.2 else "MISSED"
    print(f"ratio recorded/plain = {ratio:.3f}  (target <= 1.20: {verdict})")


if __name__ == "__main__":
    main()
