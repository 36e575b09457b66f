"""Environment speed: MKV-v0 against LunarLander-v3, measured in the same run.

Both through ``gymnasium.make`` (same wrapper stack), random actions from a fixed seed, resets
included. Reports the single-process ratio (target >= 1.0), the async vector-env throughput with
2 workers, and a profile of where MKV-v0's time goes.

    python benchmarks/env_speed.py [--steps 100000] [--rounds 3]
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import statistics
import time

import gymnasium as gym
import numpy as np

import mkv_env  # noqa: F401  (registers the ids)


def steps_per_second(env_id: str, steps: int, seed: int = 0) -> float:
    env = gym.make(env_id)
    env.action_space.seed(seed)
    env.reset(seed=seed)
    if isinstance(env.action_space, gym.spaces.MultiDiscrete):
        actions = list(np.random.default_rng(seed).integers(0, 3, size=(steps, 2)))
    else:
        actions = [int(a) for a in np.random.default_rng(seed).integers(0, 4, size=steps)]
    step, reset = env.step, env.reset
    t0 = time.perf_counter()
    for a in actions:
        _, _, terminated, truncated, _ = step(a)
        if terminated or truncated:
            reset()
    dt = time.perf_counter() - t0
    env.close()
    return steps / dt


def vector_steps_per_second(env_id: str, steps: int, workers: int = 2) -> float:
    envs = gym.make_vec(env_id, num_envs=workers, vectorization_mode="async")
    envs.reset(seed=0)
    rng = np.random.default_rng(0)
    n_calls = steps // workers
    actions = rng.integers(0, 3, size=(n_calls, workers, 2))
    t0 = time.perf_counter()
    for a in actions:
        envs.step(a)
    dt = time.perf_counter() - t0
    envs.close()
    return n_calls * workers / dt


def profile(env_id: str, steps: int) -> str:
    env = gym.make(env_id)
    env.reset(seed=0)
    actions = np.random.default_rng(0).integers(0, 3, size=(steps, 2))
    prof = cProfile.Profile()
    prof.enable()
    for a in actions:
        _, _, te, tr, _ = env.step(a)
        if te or tr:
            env.reset()
    prof.disable()
    out = io.StringIO()
    pstats.Stats(prof, stream=out).sort_stats("tottime").print_stats(8)
    return out.getvalue()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=100_000)
    ap.add_argument("--rounds", type=int, default=5,
                    help="alternating rounds; the median of each is reported")
    ap.add_argument("--no-profile", action="store_true")
    args = ap.parse_args(argv)
    mkv, ll, jam = [], [], []
    for _ in range(args.rounds):  # alternate so background load hits both alike
        ll.append(steps_per_second("LunarLander-v3", args.steps))
        mkv.append(steps_per_second("MKV-v0", args.steps))
        jam.append(steps_per_second("MKVJam-v0", args.steps // 4))
    print(f"{'env':<16}{'steps/s (median)':>16}{'all rounds':>40}")
    for name, xs in (("LunarLander-v3", ll), ("MKV-v0", mkv), ("MKVJam-v0", jam)):
        print(f"{name:<16}{statistics.median(xs):>16,.0f}"
              f"{'  '.join(f'{x:,.0f}' for x in xs):>40}")
    print(f"ratio MKV-v0 / LunarLander-v3 = {statistics.median(mkv) / statistics.median(ll):.2f}"
          "  (medians; target >= 1.0)")
    vec = vector_steps_per_second("MKV-v0", args.steps // 2)
    print(f"async vector env, 2 workers: {vec:,.0f} steps/s "
          f"({vec / statistics.median(mkv):.2f}x single process)")
    if not args.no_profile:
        print("\nwhere MKV-v0's time goes (cProfile, tottime):")
        print(profile("MKV-v0", 20_000))


if __name__ == "__main__":
    main()
