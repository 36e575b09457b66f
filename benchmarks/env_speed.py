"""Environment speed: MK-V envs against LunarLander-v3 (the named peer), measured in the same run.

Single envs through ``gymnasium.make`` (same wrapper stack), random actions from a fixed seed,
resets included; vector envs through ``gymnasium.make_vec`` with N robots (native
``vector_entry_point``, and Gymnasium's ``sync`` of single envs as its peer). Every figure is the
median of ``--rounds`` alternating rounds (so background load hits all alike). Prints every ratio,
then where one MKV-v0 step's time goes, where a native vector env robot-step's time goes, what
Chipmunk alone costs with one space per robot and with all arenas in one space, and the ceiling
these put on the vector env's ratio to the single env.

    python benchmarks/env_speed.py [--steps 50000] [--rounds 5] [--num-envs 16]
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings

import gymnasium as gym
import numpy as np
import pymunk

import mkv_env  # noqa: F401  (registers the ids)
import mkv_env.robot as robot_mod
from mkv_env import world as world_mod

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
    seconds, robot_steps = _run_vector(envs, steps)
    return robot_steps / seconds


def _run_vector(envs, steps: int) -> tuple[float, int]:
    """Step ``envs`` with random actions for about ``steps`` robot-steps, then close it:
    (seconds, robot-steps)."""
    n = envs.num_envs
    calls = max(steps // n, 1)
    actions = np.random.default_rng(0).integers(0, 3, size=(calls, n, 2))
    t0 = time.perf_counter()
    for a in actions:
        envs.step(a)
    seconds = time.perf_counter() - t0
    envs.close()
    return seconds, calls * n


def _timed(parts: dict[str, float], key: str, f):
    """``f`` wrapped to add its wall time to ``parts[key]``."""
    def g(*a, **k):
        t = time.perf_counter()
        r = f(*a, **k)
        parts[key] += time.perf_counter() - t
        return r
    return g


def where_the_time_goes(steps: int) -> list[tuple[str, float]]:
    """Mean microseconds per MKV-v0 step in each part (timed around the calls, random actions,
    resets included), from an unwrapped env (the wrappers' share is the difference to the
    wrapped step)."""
    env = gym.make("MKV-v0")
    u = env.unwrapped
    parts = {"physics (Robot.advance)": 0.0, "sensors": 0.0, "reset (amortised)": 0.0}
    adv, read, reset = robot_mod.Robot.advance, u.sensors.read, u.reset

    robot_mod.Robot.advance = _timed(parts, "physics (Robot.advance)", adv)
    u.sensors.read = _timed(parts, "sensors", read)
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


def vector_split(num_envs: int, steps: int) -> dict[str, float]:
    """Microseconds per robot-step of the native vector env in its parts (random actions, resets
    included): physics (``_move``: one compiled call for all robots), resets, and the rest
    (per-robot sensing, scoring and infos in Python, plus the vector bookkeeping)."""
    envs = gym.make_vec("MKV-v0", num_envs=num_envs, vectorization_mode="vector_entry_point")
    v = envs.unwrapped
    envs.reset(seed=0)
    parts = {"physics": 0.0, "reset": 0.0}
    v._move = _timed(parts, "physics", v._move)
    for e in v.envs:
        e.reset = _timed(parts, "reset", e.reset)
    total, robot_steps = _run_vector(envs, steps)
    out = {k: t / robot_steps * 1e6 for k, t in parts.items()}
    out["total"] = total / robot_steps * 1e6
    out["rest"] = out["total"] - out["physics"] - out["reset"]
    return out


def chipmunk_shared_vs_separate(num_envs: int, steps: int) -> tuple[float, float]:
    """Chipmunk's own ``space.step`` cost, microseconds per robot-step (4 substeps), for N robots
    each in its own space (as the envs are built) and for one space holding the N arenas side
    by side (the issue's alternative). Both get the same arenas (MKV-v0 resets, seeds 0..N-1),
    the env's own obstacle shapes and contact callbacks, and the same motion: every 50 steps each
    robot body is given a random velocity (0.3 m/s scale, the robot's speed), so it drives into
    clutter and jams."""
    substeps, dt = 4, 0.1 / 4
    separate, bodies_sep, bodies_shared = [], [], []

    def new_space():  # as mkv_env.world.World builds it
        space = pymunk.Space()
        space.iterations, space.damping = 10, world_mod.SPACE_DAMPING
        world_mod.count_contacts(space)
        return space

    shared = new_space()
    env = gym.make("MKV-v0").unwrapped
    for i in range(num_envs):
        env.reset(seed=i)
        w = env.world
        x, y, th = w.robot.pose()
        sp = new_space()
        world_mod.add_obstacles(sp, w.layout)
        bodies_sep.append(robot_mod.Robot(sp, w.robot_params, (x, y), th).body)
        separate.append(sp)
        dx = 10.0 * i  # arenas are 4 m wide: 10 m apart never touch
        world_mod.add_obstacles(shared, w.layout, dx)
        bodies_shared.append(robot_mod.Robot(shared, w.robot_params, (x + dx, y), th).body)

    def run(spaces, bodies) -> float:
        rng = np.random.default_rng(1)
        elapsed = 0.0
        for k in range(steps):
            if k % 50 == 0:
                vel = rng.normal(0.0, 0.3, size=(num_envs, 2)).tolist()
                spin = rng.normal(0.0, 1.0, size=num_envs).tolist()
                for b, v, w in zip(bodies, vel, spin, strict=True):
                    b.velocity, b.angular_velocity = v, w
            t = time.perf_counter()
            for sp in spaces:
                for _ in range(substeps):
                    sp.step(dt)
            elapsed += time.perf_counter() - t
        return elapsed / (steps * num_envs) * 1e6

    return run(separate, bodies_sep), run([shared], bodies_shared)


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
    splits = [vector_split(n, args.steps) for _ in range(args.rounds)]
    vs = {k: statistics.median(s[k] for s in splits) for k in splits[0]}
    chip = [chipmunk_shared_vs_separate(n, 1500) for _ in range(args.rounds)]
    sep = statistics.median(c[0] for c in chip)
    shared = statistics.median(c[1] for c in chip)
    t_single = 1e6 / single
    print(f"\nnative vector x{n}, us per robot-step (medians, timed around the calls):")
    print(f"  physics (all robots in one compiled call)   {vs['physics']:6.2f}")
    print(f"  resets (amortised)                          {vs['reset']:6.2f}")
    print(f"  per-robot sensing, scoring, infos; vector   {vs['rest']:6.2f}")
    print(f"  total                                       {vs['total']:6.2f}"
          f"   (MKV-v0 single env: {t_single:.2f} per step)")
    print(f"\nChipmunk's space.step alone, us per robot-step ({n} robots, same arenas and motion):")
    print(f"  one space per robot (as built)              {sep:6.2f}")
    print(f"  one space holding all {n} arenas             {shared:6.2f}"
          f"   ({sep / shared:.2f}x faster)")
    floor = vs["physics"] + vs["reset"]
    print(f"\nceiling of native vector x{n} / MKV-v0 single (target 4) if all per-robot sensing, "
          "scoring,\ninfos and vector bookkeeping cost nothing (resets kept, as the single env "
          "pays them too):")
    print(f"  physics as now:                      {t_single:.2f} / {floor:.2f} = "
          f"{t_single / floor:.2f}")
    # generous: as if all of physics were Chipmunk's and all of it got the shared-space speed-up
    shared_floor = vs["physics"] * shared / sep + vs["reset"]
    print(f"  physics {sep / shared:.2f}x faster (one shared space): {t_single:.2f} / "
          f"{shared_floor:.2f} = {t_single / shared_floor:.2f}")

if __name__ == "__main__":
    main()
