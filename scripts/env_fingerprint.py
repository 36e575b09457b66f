"""Fingerprint of MK-V trajectories: a hash of every observation, reward, flag and true pose.

Speed work on the simulator must not change a single bit of what it produces. Run this before
and after a change and compare the printed digests (one per env id, plus one over all)::

    python scripts/env_fingerprint.py [--episodes 20] [--steps 600]

Each id runs ``--episodes`` seeded episodes of seeded random actions and, for the wander ids,
the scripted teacher too (its obstacle avoidance exercises contacts, jams and sliding).
"""

from __future__ import annotations

import argparse
import hashlib
import warnings

import gymnasium as gym
import numpy as np

import mkv_env  # noqa: F401  (registers the ids)
from mkv_env.teacher import ScriptedTeacher

IDS = ("MKV-v0", "MKVJam-v0", "MKV-v1", "MKVJam-v1")


def fingerprint(env_id: str, episodes: int, steps: int, kernel: str | None = None) -> str:
    """The digest of ``episodes`` episodes of ``env_id`` (``kernel``: "c", "python" or None for
    the default)."""
    h = hashlib.sha256()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        env = gym.make(env_id, kernel=kernel)
    for ep in range(episodes):
        obs, _ = env.reset(seed=1000 + ep)
        teacher = ScriptedTeacher(seed=ep) if ep % 2 else None
        rng = np.random.default_rng(ep)
        h.update(obs.tobytes())
        for _ in range(steps):
            action = teacher.predict(obs)[0] if teacher else rng.integers(0, 3, size=2)
            obs, reward, terminated, truncated, info = env.step(action)
            h.update(obs.tobytes())
            h.update(np.array([reward, *info["pose"]], dtype=np.float64).tobytes())
            h.update(bytes([terminated, truncated]))
            if terminated or truncated:
                break
    env.close()
    return h.hexdigest()[:16]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--kernel", choices=("c", "python"), default=None,
                    help="the step kernel (default: the compiled one where built)")
    args = ap.parse_args(argv)
    total = hashlib.sha256()
    for env_id in IDS:
        d = fingerprint(env_id, args.episodes, args.steps, args.kernel)
        total.update(d.encode())
        print(f"{env_id:<12}{d}")
    print(f"{'all':<12}{total.hexdigest()[:16]}")


if __name__ == "__main__":
    main()
