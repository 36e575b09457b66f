"""What the mkv_env policies share to follow stable-baselines3's ``predict`` contract.

SB3 calls ``predict(observation, state=None, episode_start=None, deterministic=...)`` with one
observation of shape (obs_dim,) or a batch of shape (n_envs, obs_dim) from a vector env, and
``episode_start`` of shape (n_envs,) marking the envs whose episode begins with this observation.
The policies here keep one internal state per env index, grown on demand, and one random stream
per env index:

* env 0 draws from the policy's own stream, ``numpy.random.default_rng(seed)``, so a policy used
  one observation at a time behaves exactly as it always did;
* env ``i >= 1`` draws from ``default_rng(SeedSequence(seed).spawn(i + 1)[i])``, an independent
  stream (:func:`env_seed_sequence`), so what env ``i`` does depends on neither the other envs nor
  the batch size.
"""

from __future__ import annotations

import numpy as np

__all__ = ["as_batch", "env_rng", "env_seed_sequence", "episode_starts"]


def as_batch(observation, obs_dim: int | None = None,
             dtype=None) -> tuple[np.ndarray, bool]:
    """One observation (obs_dim,) or a batch (n_envs, obs_dim) as a 2-D array.

    Returns:
        obs: array of shape (n_envs, obs_dim) (n_envs = 1 for a single observation).
        single: True when the input was one observation (return actions of shape (2,) then).

    Raises:
        ValueError: for any other shape (or a width other than ``obs_dim`` when given).
    """
    obs = np.asarray(observation, dtype=dtype)
    single = obs.ndim == 1
    if single:
        obs = obs[None, :]
    if obs.ndim != 2 or (obs_dim is not None and obs.shape[1] != obs_dim):
        dim = "obs_dim" if obs_dim is None else str(obs_dim)
        raise ValueError(f"observation must have shape ({dim},) or (n_envs, {dim}), "
                         f"got {np.shape(observation)}")
    return obs, single


def episode_starts(episode_start, n_envs: int) -> np.ndarray:
    """``episode_start`` (None, a bool, or an array of shape (n_envs,)) as a bool array (n_envs,).

    ``None`` means no env starts; a single bool applies to every env.
    """
    if episode_start is None:
        return np.zeros(n_envs, dtype=bool)
    starts = np.asarray(episode_start, dtype=bool).reshape(-1)
    if starts.size == 1:
        return np.full(n_envs, bool(starts[0]))
    if starts.size != n_envs:
        raise ValueError(f"episode_start must be a bool or have shape ({n_envs},) for "
                         f"{n_envs} envs, got shape {np.shape(episode_start)}")
    return starts


def env_seed_sequence(root: np.random.SeedSequence, i: int) -> np.random.SeedSequence:
    """The seed sequence of env ``i``: ``root`` itself for env 0, else ``root.spawn(i + 1)[i]``
    (computed without advancing ``root``'s spawn counter)."""
    if i == 0:
        return root
    return np.random.SeedSequence(root.entropy, spawn_key=(*root.spawn_key, i),
                                  pool_size=root.pool_size)


def env_rng(root: np.random.SeedSequence, i: int) -> np.random.Generator:
    """The random stream of env ``i`` (see :func:`env_seed_sequence`)."""
    return np.random.default_rng(env_seed_sequence(root, i))
