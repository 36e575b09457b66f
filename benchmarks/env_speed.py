"""Environment speed: MK-V envs against LunarLander-v3 (the named peer), measured in the same run.

Single envs through ``gymnasium.make`` (same wrapper stack), random actions from a fixed seed,
resets included; vector envs through ``gymnasium.make_vec`` with N robots (native
``vector_entry_point``, and Gymnasium's ``sync`` of single envs as its peer). Every figure is the
median of ``--rounds`` alternating rounds (so background load hits all alike). Prints every ratio,
then where one MKV-v0 step's time goes.

    python benchmarks/env_speed.py [--steps 50000] [--rounds 5] [--num-envs 16]
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings

import gymnasium as gym
import numpy as np

import mkv_env  # noqa: F401  (registers the ids)
import mkv_env.robot as robot_mod

warnings.filterwarnings("ignore", category=DeprecationWarning)  # MKV-v0 "out of date" notice


def single_steps_per_second(env_id: str, steps: int, seed: int = 0) -> float:
    env = gym.make(env_id)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    if isinstance(env.action_space, gym.spaces.MultiDiscrete):
        actions = list(rng.integers(0, 3, size=(steps, 2)))
    else:
        actions = [int(a) for a in rng.integers(0, 4, size=steps)]
    step, reset = env.step, env.reset
    t0 = time.perf_counter()
    for a in actions:
        _, _, terminated, truncated, _ = step(a)
        if terminated or truncated:
            reset()
    dt = time.perf_counter() - t0
    env.close()
    return steps / dt


def vector_steps_per_second(env_id: str, steps: int, num_envs: int, mode: str) -> float:
    envs = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode=mode)
    envs.reset(seed=0)
    calls = max(steps // num_envs, 1)
    actions = np.random.default_rng(0).integers(0, 3, size=(calls, num_envs, 2))
    t0 = time.perf_counter()
    for a in actions:
        envs.step(a)
    dt = time.perf_counter() - t0
    envs.close()
    return calls * num_envs / dt


def where_the_time_goes(steps: int) -> list[tuple[str, float]]:
    """Mean microseconds per MKV-v0 step in each part (timed around the calls, random actions,
    resets included), from an unwrapped env (the wrappers' share is the difference to the
    wrapped step)."""
    env = gym.make("MKV-v0")
    u = env.unwrapped
    parts = {"physics (Robot.advance)": 0.0, "sensors": 0.0, "reset (amortised)": 0.0}
    adv, read, reset = robot_mod.Robot.advance, u.sensors.read, u.reset

    def timed(key, f):
        def g(*a, **k):
            t = time.perf_counter()
            r = f(*a, **k)
            parts[key] += time.perf_counter() - t
            return r
        return g

    robot_mod.Robot.advance = timed("physics (Robot.advance)", adv)
    u.sensors.read = timed("sensors", read)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    acts = rng.integers(0, 3, size=(steps, 2))
    try:
        t0 = time.perf_counter()
        limit = env.spec.max_episode_steps
        for i, a in enumerate(acts, 1):
            _, _, te, tr, _ = u.step(a)
            if te or tr or i % limit == 0:
                t = time.perf_counter()
                reset()
                parts["reset (amortised)"] += time.perf_counter() - t
        total = time.perf_counter() - t0
    finally:
        robot_mod.Robot.advance = adv
        del u.sensors.read
    out = [(k, v / steps * 1e6) for k, v in parts.items()]
    rest = total / steps * 1e6 - sum(v for _, v in out)
    out.append(("bookkeeping, reward, info (rest of step)", rest))
    out.append(("unwrapped step, total", total / steps * 1e6))
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=50_000)
    ap.add_argument("--rounds", type=int, default=5,
                    help="alternating rounds; the median of each is reported")
    ap.add_argument("--num-envs", type=int, default=16)
    args = ap.parse_args(argv)
    n = args.num_envs
    rows: dict[str, list[float]] = {k: [] for k in (
        "LunarLander-v3", "MKV-v0", "MKVJam-v0", "MKV-v1",
        f"MKV-v0 native vector x{n}", f"MKV-v0 sync vector x{n}")}
    for _ in range(args.rounds):  # alternate so background load hits all alike
        rows["LunarLander-v3"].append(single_steps_per_second("LunarLander-v3", args.steps))
        rows["MKV-v0"].append(single_steps_per_second("MKV-v0", args.steps))
        rows["MKVJam-v0"].append(single_steps_per_second("MKVJam-v0", args.steps // 2))
        rows["MKV-v1"].append(single_steps_per_second("MKV-v1", args.steps // 2))
        rows[f"MKV-v0 native vector x{n}"].append(
            vector_steps_per_second("MKV-v0", args.steps, n, "vector_entry_point"))
        rows[f"MKV-v0 sync vector x{n}"].append(
            vector_steps_per_second("MKV-v0", args.steps // 2, n, "sync"))
    med = {k: statistics.median(v) for k, v in rows.items()}
    print(f"kernel: {robot_mod.DEFAULT_KERNEL}  (c = compiled loop; cffi/api = pure Python)")
    print(f"{'env':<28}{'steps/s (median)':>18}   all rounds")
    for k, v in rows.items():
        print(f"{k:<28}{med[k]:>18,.0f}   {'  '.join(f'{x:,.0f}' for x in v)}")
    ll, single = med["LunarLander-v3"], med["MKV-v0"]
    print("\nratios (medians):")
    print(f"  MKV-v0 / LunarLander-v3            = {single / ll:.2f}   (target >= 1.2)")
    print(f"  MKVJam-v0 / LunarLander-v3         = {med['MKVJam-v0'] / ll:.2f}")
    print(f"  MKV-v1 / LunarLander-v3            = {med['MKV-v1'] / ll:.2f}")
    print(f"  native vector x{n} / MKV-v0 single  = "
          f"{med[f'MKV-v0 native vector x{n}'] / single:.2f}   (target >= 4)")
    print(f"  sync vector x{n} / MKV-v0 single    = "
          f"{med[f'MKV-v0 sync vector x{n}'] / single:.2f}")
    print(f"  native / sync vector x{n}           = "
          f"{med[f'MKV-v0 native vector x{n}'] / med[f'MKV-v0 sync vector x{n}']:.2f}")
    print("\nwhere an MKV-v0 step's time goes (us per step, unwrapped, timed around the calls):")
    for name, us in where_the_time_goes(min(args.steps, 30_000)):
        print(f"  {name:<44}{us:6.2f}")


if __name__ == "__main__":
    main()
