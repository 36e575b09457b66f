"""Environment speed: MK-V envs against LunarLander-v3 (the named peer), measured in the same run.

Single envs through ``gymnasium.make`` (same wrapper stack), random actions from a fixed seed,
resets included; vector envs through ``gymnasium.make_vec`` with N robots (native
``vector_entry_point`` with one and two threads, and Gymnasium's ``sync`` of single envs as its
peer); the physics alone of the same N robots (the step kernel's ``physics``: the compiled
wheel/motor substeps and Chipmunk, nothing else) as the floor. Every figure is the median of
``--rounds`` alternating rounds (so background load hits all alike). Prints every ratio against
its target, then where a native vector env robot-step's time goes and where a single MKV-v0
step's time goes. Exits 0; a missed target is printed as ``MISSED``, not an exit status.

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
from mkv_env import kernel as kernel_mod

warnings.filterwarnings("ignore", category=DeprecationWarning)  # MKV-v0 "out of date" notice


def single_steps_per_second(env_id: str, steps: int, seed: int = 0, **kwargs) -> float:
    env = gym.make(env_id, **kwargs)
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


def _actions(steps: int, n: int) -> np.ndarray:
    return np.random.default_rng(0).integers(0, 3, size=(max(steps // n, 1), n, 2))


def vector_steps_per_second(env_id: str, steps: int, num_envs: int, mode: str,
                            **kwargs) -> float:
    envs = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode=mode, **kwargs)
    envs.reset(seed=0)
    acts = _actions(steps, num_envs)
    t0 = time.perf_counter()
    for a in acts:
        envs.step(a)
    seconds = time.perf_counter() - t0
    envs.close()
    return acts.shape[0] * num_envs / seconds


def physics_steps_per_second(env_id: str, steps: int, num_envs: int) -> float:
    """Robot-steps/s of the physics alone (compiled substeps + Chipmunk) of the robots of a
    native vector env reset like the others: the floor of a robot-step."""
    envs = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point")
    envs.reset(seed=0)
    physics = envs.unwrapped._batch.physics
    acts = _actions(steps, num_envs)
    t0 = time.perf_counter()
    for a in acts:
        physics(a)
    seconds = time.perf_counter() - t0
    envs.close()
    return acts.shape[0] * num_envs / seconds


def kernel_steps_per_second(env_id: str, steps: int, num_envs: int, threads: int) -> float:
    """Robot-steps/s of the step kernel's call alone (no autoreset, no Python bookkeeping) with
    ``threads`` threads: how the compiled part scales, whatever the Python around it costs."""
    envs = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point",
                        num_threads=threads)
    envs.reset(seed=0)
    v = envs.unwrapped
    batch, sub = v._batch, v.envs
    acts = _actions(steps, num_envs)
    t0 = time.perf_counter()
    for a in acts:
        need = batch.step(a, None)
        while need is not None:
            for i in need:
                batch.set_noise(i, sub[i]._sensors.draw_block())
            need = batch.step(a, None)
    seconds = time.perf_counter() - t0
    envs.close()
    return acts.shape[0] * num_envs / seconds


def vector_split(num_envs: int, steps: int, env_id: str = "MKV-v0") -> dict[str, float]:
    """Microseconds per robot-step of the native vector env (one thread, random actions, resets
    included) in its parts: the one kernel call of a step (``Batch.vstep``: stepping every robot,
    the autoresets in C, the result arrays and Gymnasium's info dict), resets done by Python
    (none for MKV-v0: they run inside the call) and the Python around the call."""
    envs = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point")
    v = envs.unwrapped
    envs.reset(seed=0)
    parts = {"call": 0.0, "reset": 0.0}
    if v._fast is not None:
        v._fast = _timed(parts, "call", v._fast)
    for e in v.envs:
        e.reset = _timed(parts, "reset", e.reset)
    acts = _actions(steps, num_envs)
    t0 = time.perf_counter()
    for a in acts:
        envs.step(a)
    total = time.perf_counter() - t0
    robot_steps = acts.shape[0] * num_envs
    out = {k: t / robot_steps * 1e6 for k, t in parts.items()}
    out["total"] = total / robot_steps * 1e6
    out["rest"] = out["total"] - out["call"] - out["reset"]
    envs.close()
    return out


def _timed(parts: dict[str, float], key: str, f):
    """``f`` wrapped to add its wall time to ``parts[key]``."""
    def g(*a, **k):
        t = time.perf_counter()
        r = f(*a, **k)
        parts[key] += time.perf_counter() - t
        return r
    return g


def where_the_single_step_goes(steps: int) -> list[tuple[str, float]]:
    """Mean microseconds per MKV-v0 step (wrapped as gym.make makes it; random actions, resets
    included): the step kernel call, the resets, the env's Python around the kernel (decode,
    info dict) and Gymnasium's wrappers."""
    env = gym.make("MKV-v0")
    u = env.unwrapped
    env.reset(seed=0)
    parts = {"kernel": 0.0, "reset": 0.0, "unwrapped": 0.0}
    batch = u._batch

    class Timed:
        def __getattr__(self, name):
            return getattr(batch, name)

        def step1(self, *a):
            t = time.perf_counter()
            r = batch.step1(*a)
            parts["kernel"] += time.perf_counter() - t
            return r

    u._batch = Timed()
    ustep, ureset = u.step, u.reset
    u.step = _timed(parts, "unwrapped", ustep)
    u.reset = _timed(parts, "reset", ureset)
    acts = list(np.random.default_rng(0).integers(0, 3, size=(steps, 2)))
    t0 = time.perf_counter()
    for a in acts:
        _, _, te, tr, _ = env.step(a)
        if te or tr:
            env.reset()
    total = time.perf_counter() - t0
    us = {k: v / steps * 1e6 for k, v in parts.items()}
    return [("step kernel (physics, sensors, tracker, reward, info numbers)", us["kernel"]),
            ("the env's Python around it (decode, info dict)", us["unwrapped"] - us["kernel"]),
            ("reset (amortised)", us["reset"]),
            ("Gymnasium's wrappers", total / steps * 1e6 - us["unwrapped"] - us["reset"]),
            ("wrapped step, total", total / steps * 1e6)]


def _verdict(ok: bool) -> str:
    return "met" if ok else "MISSED"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=50_000)
    ap.add_argument("--rounds", type=int, default=5,
                    help="alternating rounds; the median of each is reported")
    ap.add_argument("--num-envs", type=int, default=16)
    args = ap.parse_args(argv)
    if not kernel_mod.AVAILABLE:
        raise SystemExit("the compiled step kernel is not built: nothing to compare")
    n, s = args.num_envs, args.steps
    ref = "MKV-v0 kernel='python'"
    vec1, vec2 = f"MKV-v0 native vector x{n}", f"MKV-v0 native vector x{n}, 2 threads"
    phys, sync = f"MKV-v0 physics alone x{n}", f"MKV-v0 sync vector x{n}"
    k1, k2 = f"MKV-v0 stepping alone x{n}", f"MKV-v0 stepping alone x{n}, 2 threads"
    rows: dict[str, list[float]] = {k: [] for k in (
        "LunarLander-v3", "MKV-v0", "MKVJam-v0", "MKV-v1", "MKVJam-v1",
        ref, vec1, vec2, phys, k1, k2, sync)}
    for _ in range(args.rounds):  # alternate so background load hits all alike
        rows["LunarLander-v3"].append(single_steps_per_second("LunarLander-v3", s))
        rows["MKV-v0"].append(single_steps_per_second("MKV-v0", s))
        rows["MKVJam-v0"].append(single_steps_per_second("MKVJam-v0", s))
        rows["MKV-v1"].append(single_steps_per_second("MKV-v1", s // 2))
        rows["MKVJam-v1"].append(single_steps_per_second("MKVJam-v1", s // 2))
        rows[ref].append(
            single_steps_per_second("MKV-v0", s // 5, kernel="python"))
        rows[vec1].append(vector_steps_per_second("MKV-v0", s, n, "vector_entry_point"))
        rows[vec2].append(vector_steps_per_second("MKV-v0", s, n, "vector_entry_point",
                                                  num_threads=2))
        rows[phys].append(physics_steps_per_second("MKV-v0", s, n))
        rows[k1].append(kernel_steps_per_second("MKV-v0", s, n, 1))
        rows[k2].append(kernel_steps_per_second("MKV-v0", s, n, 2))
        rows[sync].append(vector_steps_per_second("MKV-v0", s // 2, n, "sync"))
    med = {k: statistics.median(v) for k, v in rows.items()}
    print(f"{'env':<44}{'steps/s (median)':>18}   all rounds")
    for k, v in rows.items():
        print(f"{k:<44}{med[k]:>18,.0f}   {'  '.join(f'{x:,.0f}' for x in v)}")
    ll, single = med["LunarLander-v3"], med["MKV-v0"]
    per_robot, floor = 1e6 / med[vec1], 1e6 / med[phys]
    r_single, r_vec = single / ll, med[vec1] / ll
    r_floor, r_threads = per_robot / floor, med[vec2] / med[vec1]
    r_jam = single / med["MKVJam-v0"]
    print("\nratios (medians):")
    print(f"  MKV-v0 / LunarLander-v3                     = {r_single:5.2f}   "
          f"(target >= 3.5: {_verdict(r_single >= 3.5)})")
    print(f"  native vector x{n} / LunarLander-v3          = {r_vec:5.2f}   "
          f"(target >= 6: {_verdict(r_vec >= 6)})")
    print(f"  native vector x{n} time per robot-step / physics alone = {per_robot:.2f} / "
          f"{floor:.2f} us = {r_floor:.2f}   (target <= 1.5: {_verdict(r_floor <= 1.5)})")
    print(f"  2 threads / 1 thread, native vector x{n}     = {r_threads:5.2f}   "
          f"(target >= 1.7: {_verdict(r_threads >= 1.7)})")
    print(f"    (stepping alone, 2 threads / 1             = {med[k2] / med[k1]:5.2f}: resets in C "
          "run on the threads too; the result arrays and Python are serial)")
    print(f"  MKVJam-v0 time per step / MKV-v0's          = {r_jam:5.2f}   "
          f"(target <= 1.3: {_verdict(r_jam <= 1.3)})")
    print(f"  MKV-v1 / LunarLander-v3                     = {med['MKV-v1'] / ll:5.2f}")
    print(f"  MKVJam-v1 / LunarLander-v3                  = {med['MKVJam-v1'] / ll:5.2f}")
    print(f"  MKV-v0 compiled kernel / Python reference   = "
          f"{single / med[ref]:5.2f}")
    print(f"  native vector x{n} / sync vector x{n}         = {med[vec1] / med[sync]:5.2f}")

    splits = [vector_split(n, s) for _ in range(args.rounds)]
    vs = {k: statistics.median(x[k] for x in splits) for k in splits[0]}
    print(f"\nnative vector x{n}, one thread, us per robot-step (medians, timed around the "
          "calls):")
    print(f"  physics alone (the floor, measured above)                  {floor:6.2f}")
    print(f"  stepping alone (physics + sensing, tracking, scoring; above) {1e6 / med[k1]:6.2f}")
    print("  the step's kernel call (Batch.vstep: stepping, resets in C,")
    print(f"    result arrays, info dict)                                  {vs['call']:6.2f}")
    print(f"  resets done by Python (amortised)                            {vs['reset']:6.2f}")
    print(f"  Python around the call                                       {vs['rest']:6.2f}")
    print(f"  total                                                        {vs['total']:6.2f}")
    print("\nwhere an MKV-v0 step's time goes (us per step, timed around the calls):")
    for name, us in where_the_single_step_goes(min(s, 30_000)):
        print(f"  {name:<64}{us:6.2f}")


if __name__ == "__main__":
    main()
