"""Stable-Baselines3 ``VecEnv`` over the native MK-V vector env (needs stable-baselines3).

SB3 trains on its own ``VecEnv`` API (reset returns observations only; ``step`` resets finished
envs at once and puts the last observation in ``info["terminal_observation"]``).
:class:`SB3VecEnv` gives that API to :class:`mkv_env.vector.MKVVectorEnv` run in
``SameStep`` autoreset mode, so a run is the same as SB3's ``DummyVecEnv`` over
``gymnasium.make(env_id)`` envs with the same seeds, only faster::

    from stable_baselines3 import PPO
    from mkv_env.sb3_vec import SB3VecEnv

    venv = SB3VecEnv("MKV-v1", n_envs=16, seed=0)
    PPO("MlpPolicy", venv).learn(100_000)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices

import mkv_env  # noqa: F401  (registers the ids)
from mkv_env.vector import MKVVectorEnv


class SB3VecEnv(VecEnv):
    """``n_envs`` robots of ``env_id`` (any MK-V id, ``**kwargs`` as for ``gym.make``) as an SB3
    VecEnv. ``seed`` seeds env i with ``seed + i`` at the first reset (as ``make_vec_env``)."""

    def __init__(self, env_id: str, n_envs: int = 8, seed: int | None = None, **kwargs):
        venv = gym.make_vec(env_id, num_envs=n_envs, vectorization_mode="vector_entry_point",
                            autoreset_mode="SameStep", **kwargs)
        if not isinstance(venv, MKVVectorEnv):
            raise ValueError(f"{env_id!r} is not an MK-V id with a native vector env")
        self.venv = venv
        venv.vector_infos = False  # SB3 wants per-env dicts: take the envs' own
        super().__init__(n_envs, venv.single_observation_space, venv.single_action_space)
        self.metadata = {"render_modes": ["rgb_array"], "autoreset_mode": "SameStep"}
        self.render_mode = kwargs.get("render_mode")
        self._actions: np.ndarray | None = None
        if seed is not None:
            self.seed(seed)

    # ------------------------------------------------------------------ VecEnv API
    def reset(self):
        """Reset every env with its own seed and its own options (as DummyVecEnv does)."""
        seeds = list(self._seeds)
        seed = seeds if any(s is not None for s in seeds) else None
        groups: dict[str, tuple[dict, list[int]]] = {}  # envs sharing the same options
        for i, o in enumerate(self._options):
            groups.setdefault(repr(sorted((o or {}).items())), (o or {}, []))[1].append(i)
        if len(groups) == 1:
            options = next(iter(groups.values()))[0]
            obs, _ = self.venv.reset(seed=seed, options=dict(options) or None)
            infos = list(self.venv.env_infos)
        else:
            infos = [None] * self.num_envs
            for options, idx in groups.values():
                mask = np.zeros(self.num_envs, dtype=bool)
                mask[idx] = True
                obs, _ = self.venv.reset(seed=seed, options={**options, "reset_mask": mask})
                for i in idx:
                    infos[i] = self.venv.env_infos[i]
        self.reset_infos = [dict(d) for d in infos]
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions).reshape(self.num_envs, -1)

    def step_wait(self):
        obs, rewards, terminated, truncated, info = self.venv.step(self._actions)
        dones = terminated | truncated
        infos = [dict(d) for d in self.venv.env_infos]
        for i in np.flatnonzero(dones):
            self.reset_infos[i] = infos[i]
            infos[i] = dict(self.venv.final_env_infos[i])
            infos[i]["terminal_observation"] = info["final_obs"][i]
        for i, d in enumerate(infos):
            d["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
        return obs, rewards.astype(np.float32), dones, infos

    def close(self) -> None:
        self.venv.close()

    def get_images(self) -> Sequence[np.ndarray | None]:
        return list(self.venv.render() or [None] * self.num_envs)

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return [getattr(self.venv.envs[i], attr_name) for i in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        for i in self._get_indices(indices):
            setattr(self.venv.envs[i], attr_name, value)

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None,
                   **method_kwargs) -> list[Any]:
        return [getattr(self.venv.envs[i], method_name)(*method_args, **method_kwargs)
                for i in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class, indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]  # the envs are unwrapped
