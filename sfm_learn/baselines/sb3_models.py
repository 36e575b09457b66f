"""The ``sb3:ALGO:PATH`` policy spec: any model zip saved by plain Stable-Baselines3 or rl-zoo3.

::

    mkv eval --env MKVJam-v0 --policy sb3:PPO:logs/ppo/MKVJam-v0_1/MKVJam-v0.zip --episodes 50

``ALGO`` names the class that saved the zip (case-insensitive): ``PPO``, ``A2C``, ``DQN``,
``SAC``, ``TD3``, ``DDPG`` from stable-baselines3, and ``RecurrentPPO``, ``TRPO``, ``QRDQN``,
``ARS`` from sb3-contrib when it is installed. The model must have been trained on the env's own
observation and action spaces (the loader checks them; DQN-style algorithms need a ``Discrete``
action space, which the MK-V envs do not have, so they are refused with that reason).

Observations are passed to the model as the env gives them, except:

* a zip written by ``mkv train-ppo`` (it carries ``mkv_meta.json``) gets the observation rescaling
  it was trained with (Gymnasium's ``RescaleObservation``), so ``sb3:PPO:ppo.zip`` and
  ``ppo:ppo.zip`` act the same;
* rl-zoo3's observation normalisation: a ``vecnormalize.pkl`` beside the zip, in a folder named
  after the zip (rl-zoo3's ``<run>/<env>.zip`` + ``<run>/<env>/vecnormalize.pkl``), or in the only
  subfolder of the zip's folder that has one, is applied with its saved statistics (frozen).

Other rl-zoo3 wrappers (frame stacking, custom env wrappers) are not reproduced.

The returned policy has SB3's ``predict`` and passes ``state`` and ``episode_start`` through, so a
recurrent model (RecurrentPPO) keeps its memory across the steps of an episode: the episode
runners hand back the ``state`` it returns. Loading a zip unpickles parts of it (as
``ALGO.load`` does): only load files you trust.
"""

from __future__ import annotations

import glob
import importlib
import json
import os
import pickle
import zipfile

import numpy as np

from mkv_env.policies import PolicySpecError

__all__ = ["ALGORITHMS", "SB3Model", "load_spec", "find_vecnormalize"]

#: Algorithm name (lower case) -> (module, class).
ALGORITHMS = {
    "ppo": ("stable_baselines3", "PPO"),
    "a2c": ("stable_baselines3", "A2C"),
    "dqn": ("stable_baselines3", "DQN"),
    "sac": ("stable_baselines3", "SAC"),
    "td3": ("stable_baselines3", "TD3"),
    "ddpg": ("stable_baselines3", "DDPG"),
    "recurrentppo": ("sb3_contrib", "RecurrentPPO"),
    "trpo": ("sb3_contrib", "TRPO"),
    "qrdqn": ("sb3_contrib", "QRDQN"),
    "ars": ("sb3_contrib", "ARS"),
}

# What rl-zoo3's enjoy.py passes so zips from other SB3 versions load without their schedules.
_CUSTOM_OBJECTS = {"learning_rate": 0.0, "lr_schedule": lambda _: 0.0,
                   "clip_range": lambda _: 0.0}


class SB3Model:
    """SB3's ``predict`` over a loaded model, with the observation transform it was trained with.

    ``predict`` takes one observation or a batch (n_envs, n_obs) and returns the model's own
    ``(actions, state)``; ``episode_start`` is passed as one bool per env.
    """

    def __init__(self, model, transform=None, spec: str = "sb3"):
        self.model = model
        self.transform = transform
        self.spec = spec

    def reset(self, seed: int | None = None) -> None:
        """Seed the model's sampling (used by ``deterministic=False``)."""
        if seed is not None:
            self.model.set_random_seed(int(seed) % 2**32)

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = True):
        obs = np.asarray(observation)
        if self.transform is not None:
            obs = self.transform(obs)
        n_envs = 1 if obs.ndim == 1 else obs.shape[0]
        if episode_start is not None:
            episode_start = np.broadcast_to(
                np.asarray(episode_start, dtype=bool).reshape(-1), (n_envs,)).copy()
        return self.model.predict(obs, state=state, episode_start=episode_start,
                                  deterministic=deterministic)


def find_vecnormalize(path: str) -> str | None:
    """rl-zoo3's ``vecnormalize.pkl`` for a model zip at ``path``, or None (see module doc)."""
    folder = os.path.dirname(os.path.abspath(path))
    stem = os.path.splitext(os.path.basename(path))[0]
    for candidate in (os.path.join(folder, stem, "vecnormalize.pkl"),
                      os.path.join(folder, "vecnormalize.pkl")):
        if os.path.isfile(candidate):
            return candidate
    found = sorted(glob.glob(os.path.join(folder, "*", "vecnormalize.pkl")))
    return found[0] if len(found) == 1 else None


def _vecnormalize_transform(pkl: str):
    with open(pkl, "rb") as f:
        stats = pickle.load(f)
    if not getattr(stats, "norm_obs", False):
        return None
    return lambda obs: stats.normalize_obs(np.asarray(obs, dtype=np.float32))


def _mkv_transform(path: str):
    """The observation map of a zip written by ``mkv train-ppo`` (None for other zips)."""
    try:
        with zipfile.ZipFile(path) as zf:
            if "mkv_meta.json" not in zf.namelist():
                return None
            meta = json.loads(zf.read("mkv_meta.json"))
    except (zipfile.BadZipFile, OSError, ValueError):
        return None
    from sfm_learn.baselines.ppo import observation_transform

    return observation_transform(meta, len(meta.get("sensor_names", [])))


def _algorithm(name: str):
    key = name.strip().lower().replace("-", "").replace("_", "")
    if key not in ALGORITHMS:
        raise PolicySpecError(f"unknown SB3 algorithm {name!r}; known: "
                              + ", ".join(cls for _, cls in ALGORITHMS.values()))
    module, cls = ALGORITHMS[key]
    try:
        return getattr(importlib.import_module(module), cls)
    except ImportError:
        extra = "sb3-contrib" if module == "sb3_contrib" else "stable-baselines3"
        raise PolicySpecError(f"sb3:{cls} needs {extra} (pip install {extra})") from None


def load_spec(arg: str, env, seed):
    """``sb3:ALGO:PATH`` -> :class:`SB3Model`."""
    algo, sep, path = arg.partition(":")
    path = path.strip()
    if not sep or not algo.strip() or not path:
        raise PolicySpecError("sb3 needs an algorithm and a file: sb3:ALGO:PATH, e.g. "
                              "sb3:PPO:model.zip")
    cls = _algorithm(algo)
    if not os.path.exists(path):
        raise PolicySpecError(f"{path}: no such file")
    if os.path.isdir(path):
        raise PolicySpecError(f"{path} is a directory, not a model zip")
    from sfm_learn.baselines.sb3 import import_torch

    import_torch()
    try:
        model = cls.load(path, device="cpu", custom_objects=_CUSTOM_OBJECTS)
    except Exception as e:  # a corrupt or foreign file: one line
        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise PolicySpecError(f"{path}: cannot load it as a {cls.__name__} zip ({reason})") \
            from None
    if env is not None:
        _check_spaces(model, env, path, cls.__name__)
    transform = _mkv_transform(path)
    pkl = find_vecnormalize(path)
    if transform is None and pkl is not None:
        try:
            transform = _vecnormalize_transform(pkl)
        except Exception as e:
            raise PolicySpecError(f"{pkl}: cannot read the normalisation statistics "
                                  f"({type(e).__name__})") from None
    policy = SB3Model(model, transform, spec=f"sb3:{cls.__name__}:{path}")
    if seed is not None:
        policy.reset(seed)
    return policy


def _check_spaces(model, env, path: str, algo: str) -> None:
    name = os.path.basename(path)
    m_act, e_act = model.action_space, env.action_space
    if type(m_act) is not type(e_act) or getattr(m_act, "shape", None) != e_act.shape or (
            hasattr(e_act, "nvec") and not np.array_equal(m_act.nvec, e_act.nvec)):
        raise PolicySpecError(f"{name} ({algo}) acts in {m_act} but the env's action space is "
                              f"{e_act}")
    m_obs, e_obs = model.observation_space, env.observation_space
    if getattr(m_obs, "shape", None) != getattr(e_obs, "shape", None):
        raise PolicySpecError(f"{name} ({algo}) expects observations of shape {m_obs.shape} but "
                              f"the env gives {e_obs.shape}")
