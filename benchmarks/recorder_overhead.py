"""Recorder overhead: recording teacher episodes vs stepping the same env with the same policy.

Both sides run ``MKV-v0`` with the scripted teacher on the same seeds (episode i uses seed i) for
at least ``--steps`` steps. "plain" is the bare loop (reset, predict, step); "recorded" is the
recorder's loop (:func:`mkv_env.recorder.run_episodes` feeding an
:class:`~mkv_env.recorder.EpisodeRecorder`), plus stacking the arrays, checksumming, validating
(:meth:`EpisodeRecorder.to_dataset`) and writing the file (:func:`mkv_env.dataset.save`).

The two sides alternate in blocks of ``--block`` episodes, so that a load change on a shared
machine hits both alike; the whole comparison runs ``--rounds`` times and the round with the
lowest total is reported. Target: recorded / plain <= 1.20.

    python benchmarks/recorder_overhead.py [--steps 100000] [--rounds 2] [--block 5]
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
from mkv_env.recorder import EpisodeRecorder, policy_seed, run_episodes

ENV_ID = "MKV-v0"
META = {"env_id": ENV_ID, "env_kwargs": {}, "policy": "teacher", "seed": 0,
        "control_period_s": 0.1, "package_version": mkv_env.__version__}


def plain(env, policy, seeds) -> int:
    """The bare loop, no recording; returns the number of steps."""
    steps = 0
    for seed in seeds:
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
    return steps


def one_round(episodes: int, block: int, directory: str) -> tuple[float, float, int, int]:
    env_p, env_r = gym.make(ENV_ID), gym.make(ENV_ID)
    pol_p = make_policy("teacher", env_p, seed=0)
    pol_r = make_policy("teacher", env_r, seed=0)
    recorder = EpisodeRecorder(env_r.unwrapped.sensor_names)
    t_plain = t_rec = 0.0
    n_plain = 0
    for first in range(0, episodes, block):
        seeds = range(first, min(first + block, episodes))
        t0 = time.perf_counter()
        n_plain += plain(env_p, pol_p, seeds)
        t1 = time.perf_counter()
        run_episodes(env_r, pol_r, seeds, recorder)
        t2 = time.perf_counter()
        t_plain += t1 - t0
        t_rec += t2 - t1
    t0 = time.perf_counter()
    data = recorder.to_dataset(META)
    save(data, os.path.join(directory, "bench.npz"))
    t_rec += time.perf_counter() - t0
    return t_plain, t_rec, n_plain, data.n_steps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=100_000)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--block", type=int, default=5, help="episodes per alternation block")
    args = ap.parse_args()
    episodes = math.ceil(args.steps / gym.spec(ENV_ID).max_episode_steps)
    best = None
    with tempfile.TemporaryDirectory() as d:
        for r in range(args.rounds):
            tp, tr, n_plain, n_rec = one_round(episodes, args.block, d)
            assert n_plain == n_rec, (n_plain, n_rec)
            print(f"round {r + 1}: plain {tp:.2f} s, recorded {tr:.2f} s, ratio {tr / tp:.3f}")
            if best is None or tp + tr < best[0] + best[1]:
                best = (tp, tr)
        size = os.path.getsize(os.path.join(d, "bench.npz"))
    tp, tr = best
    ratio = tr / tp
    print(f"{ENV_ID}, teacher, {n_rec} steps in {episodes} episodes")
    print(f"plain    {tp:.2f} s  ({n_plain / tp:,.0f} steps/s)")
    print(f"recorded {tr:.2f} s  ({n_rec / tr:,.0f} steps/s), file {size / 1e6:.1f} MB")
    verdict = "met" if ratio <= 1.2 else "MISSED"
    print(f"ratio recorded/plain = {ratio:.3f}  (target <= 1.20: {verdict})")


if __name__ == "__main__":
    main()
