"""Run a policy in a registered env and record every step into a :class:`~mkv_env.dataset.Dataset`.

::

    from mkv_env.recorder import record
    from mkv_env.dataset import save
    data = record("MKV-v0", "teacher", episodes=10, seed=0)   # episode i uses seed 0 + i
    save(data, "teacher.npz")

The policy may be a spec string (:func:`mkv_env.policies.make_policy`) or any object with the
SB3 ``predict``. Before each episode the recorder calls ``policy.reset(seed=...)`` if the policy
has it, with a seed derived from the episode's env seed (:func:`policy_seed`), so every episode
replays exactly on its own, whatever ran before it.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence

import gymnasium as gym
import numpy as np

import mkv_env
from mkv_env import dataset as ds
from mkv_env.jams import scenario_name
from mkv_env.policies import make_policy

_BOOL_INFO = ("stuck", "bumped", "collision", "in_jam")
_INT_INFO = ("jams", "escapes", "collisions")


def policy_seed(env_seed: int) -> int:
    """The policy's seed for an episode whose env is reset with ``env_seed``: a different stream
    from the env's own (gymnasium seeds ``np_random`` with the plain seed)."""
    return int(np.random.SeedSequence([int(env_seed), 0x7EAC4E12]).generate_state(1)[0])


def make_env(env_id: str, env_kwargs: dict | None = None, **extra) -> gym.Env:
    """``gymnasium.make`` with one-line errors: ValueError for an unknown id or bad kwargs.

    Gymnasium's "environment MKV-v0 is out of date" notice is silenced here: the v0 ids stay
    supported unchanged (their rewards define earlier results); v1 differs only in its reward.
    """
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*is out of date. You should consider",
                                    category=DeprecationWarning)
            return gym.make(env_id, **(env_kwargs or {}), **extra)
    except gym.error.Error as e:
        raise ValueError(f"cannot make env {env_id!r}: {str(e).splitlines()[0]}") from None
    except TypeError as e:
        raise ValueError(f"bad arguments for env {env_id!r}: {e}") from None


_CHUNK_ROWS = 8192
# Columns of the float64 scalar buffer, one row per step (ints and bools are exact in float64).
_SCALARS = ("rewards", "terminated", "truncated", "stuck", "bumped", "collision", "in_jam",
            "distance_m", "jams", "escapes", "collisions", "x", "y", "heading", "escaped")


class EpisodeRecorder:
    """Accumulates steps of consecutive episodes; :meth:`to_dataset` stacks them.

    Steps go into preallocated numpy chunks (three row writes per step, no per-step Python
    objects kept alive, so the garbage collector has nothing to walk as recordings grow).

    Args:
        sensor_names: channel names of the observation.
    """

    def __init__(self, sensor_names: Sequence[str]):
        self.sensor_names = list(sensor_names)
        self._c = len(self.sensor_names)
        self._chunks: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._j = _CHUNK_ROWS  # row in the current chunk; full -> allocate on next add
        self._seeds: list[int] = []
        self._lengths: list[int] = []
        self._final: list[np.ndarray] = []
        self._scenarios: list = []
        self.has_escaped: bool | None = None

    def begin(self, seed: int, info: dict) -> None:
        self._seeds.append(int(seed))
        self._lengths.append(0)
        scen = info.get("scenario")  # the jam envs' code; datasets keep the readable name
        self._scenarios.append(scen if scen is None or isinstance(scen, str)
                               else scenario_name(scen))
        if self.has_escaped is None:
            self.has_escaped = "escaped" in info

    def _new_chunk(self) -> None:
        self._chunks.append((np.empty((_CHUNK_ROWS, self._c), dtype=np.float32),
                             np.empty((_CHUNK_ROWS, 2), dtype=np.int64),
                             np.empty((_CHUNK_ROWS, len(_SCALARS)), dtype=np.float64)))
        self._j = 0
        self._obs_buf, self._act_buf, self._scal_buf = self._chunks[-1]

    def add(self, obs, action, reward, terminated, truncated, info: dict) -> None:
        if self._j == _CHUNK_ROWS:
            self._new_chunk()
        j = self._j
        self._obs_buf[j] = obs
        self._act_buf[j] = action
        x, y, heading = info["pose"]
        self._scal_buf[j] = (
            reward, terminated, truncated, info["stuck"], info["bumped"], info["collision"],
            info["in_jam"], info["distance_m"], info["jams"], info["escapes"],
            info["collisions"], x, y, heading, info.get("escaped", False),
        )
        self._j = j + 1
        self._lengths[-1] += 1

    @property
    def n_steps(self) -> int:
        """Steps recorded so far."""
        return int(sum(self._lengths))

    def end(self, final_obs) -> None:
        self._final.append(np.asarray(final_obs, dtype=np.float32))

    def to_dataset(self, metadata: dict) -> ds.Dataset:
        c = self._c
        lengths = np.asarray(self._lengths, dtype=np.int64)
        n = int(lengths.sum())
        if self._chunks:
            obs = np.concatenate([ch[0] for ch in self._chunks])[:n]
            act = np.concatenate([ch[1] for ch in self._chunks])[:n]
            scal = np.concatenate([ch[2] for ch in self._chunks])[:n]
        else:
            obs = np.zeros((0, c), np.float32)
            act = np.zeros((0, 2), np.int64)
            scal = np.zeros((0, len(_SCALARS)))
        col = {name: scal[:, i] for i, name in enumerate(_SCALARS)}
        arrays = {
            "observations": np.ascontiguousarray(obs),
            "actions": np.ascontiguousarray(act),
            "rewards": col["rewards"].copy(),
            "distance_m": col["distance_m"].copy(),
            "pose": np.ascontiguousarray(scal[:, 11:14]),
            "episode": np.repeat(np.arange(len(lengths), dtype=np.int32), lengths),
            "step": (np.concatenate([np.arange(k, dtype=np.int32) for k in lengths])
                     if len(lengths) else np.zeros(0, dtype=np.int32)),
            "episode_seeds": np.asarray(self._seeds, dtype=np.int64),
            "episode_lengths": lengths,
            "final_observations": np.asarray(self._final, dtype=np.float32).reshape(-1, c),
        }
        for k in ("terminated", "truncated") + _BOOL_INFO:
            arrays[k] = col[k] != 0
        for k in _INT_INFO:
            arrays[k] = col[k].astype(np.int32)
        if self.has_escaped:
            arrays["escaped"] = col["escaped"] != 0
        scen = self._scenarios if any(s is not None for s in self._scenarios) else None
        meta = dict(metadata, sensor_names=self.sensor_names, has_escaped=bool(self.has_escaped),
                    episode_scenarios=scen)
        return ds.build(arrays, meta)


def run_episodes(env: gym.Env, policy, seeds: Sequence[int], recorder: EpisodeRecorder,
                 on_episode: Callable[[int, int], None] | None = None,
                 max_steps: int | None = None) -> None:
    """Run one episode per seed, feeding every step to ``recorder``.

    The policy is called as SB3 calls it: ``predict(obs, state=state, episode_start=start)``,
    with the ``state`` it returned at the previous step (``None`` at an episode's first step), so
    recurrent policies keep their memory within an episode.

    ``on_episode(i, n_steps)`` is called after episode ``i``. ``max_steps`` caps an episode
    (needed only for envs without a time limit); capped episodes end with ``truncated`` True.
    """
    predict = policy.predict
    reset_policy = getattr(policy, "reset", None)
    add = recorder.add
    for i, seed in enumerate(seeds):
        obs, info = env.reset(seed=int(seed))
        if reset_policy is not None:
            reset_policy(seed=policy_seed(seed))
        recorder.begin(seed, info)
        start = True
        state = None  # a recurrent policy's memory: handed back every step, reset per episode
        k = 0
        while True:
            action, state = predict(obs, state=state, episode_start=start)
            start = False
            next_obs, reward, terminated, truncated, info = env.step(action)
            k += 1
            if max_steps is not None and k >= max_steps:
                truncated = True
            add(obs, action, float(reward), bool(terminated), bool(truncated), info)
            obs = next_obs
            if terminated or truncated:
                break
        recorder.end(obs)
        if on_episode is not None:
            on_episode(i, k)


def recording_metadata(env, env_id: str, env_kwargs: dict | None, policy: str,
                       seed: int) -> dict:
    """The metadata of a recording (besides what :meth:`EpisodeRecorder.to_dataset` adds)."""
    return {
        "format": ds.FORMAT,
        "schema_version": ds.SCHEMA_VERSION,
        "env_id": env_id,
        "env_kwargs": dict(env_kwargs or {}),
        "policy": policy,
        "seed": int(seed),
        "control_period_s": float(getattr(env.unwrapped, "control_period_s", 0.1)),
        "package_version": mkv_env.__version__,
    }


def record(env_id: str, policy, episodes: int, seed: int = 0, env_kwargs: dict | None = None,
           on_episode: Callable[[int, int], None] | None = None,
           max_steps: int | None = None, first_seed: int | None = None,
           min_steps: int | None = None, max_extra_episodes: int = 10_000) -> ds.Dataset:
    """Record ``episodes`` episodes of ``policy`` (spec string or object) in ``env_id``.

    Episode ``i`` resets the env with seed ``seed + i``. Returns the dataset (in memory; write it
    with :func:`mkv_env.dataset.save`). A policy given as a spec is built with the policy seed of
    ``first_seed`` (default ``seed``): a run that records part of a larger seed range (a worker's
    share of an evaluation) passes the range's first seed, so its episodes do not depend on how
    the range was split.

    ``min_steps``: when the episodes ended early (a jam env's escape) and gave fewer steps, record
    further episodes (seeds ``seed + episodes``, ``+ 1``, ...; each capped at what is still
    missing and at ``max_steps``) until there are exactly ``min_steps``, at most
    ``max_extra_episodes`` more; a recording that reaches it anyway is unchanged.
    """
    if not (isinstance(episodes, (int, np.integer)) and episodes >= 1):
        raise ValueError(f"episodes must be a positive integer, got {episodes!r}")
    if min_steps is not None and not (isinstance(min_steps, (int, np.integer))
                                      and not isinstance(min_steps, bool) and min_steps >= 1):
        raise ValueError(f"min_steps must be a positive integer or None, got {min_steps!r}")
    if not (isinstance(seed, (int, np.integer)) and 0 <= seed < 2**63 - episodes):
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    env = make_env(env_id, env_kwargs)
    try:
        if isinstance(policy, str):
            spec = policy
            policy = make_policy(policy, env,
                                 seed=policy_seed(seed if first_seed is None else first_seed))
        else:
            spec = getattr(policy, "spec", type(policy).__name__)
        recorder = EpisodeRecorder(env.unwrapped.sensor_names)
        seeds = [int(seed) + i for i in range(int(episodes))]
        run_episodes(env, policy, seeds, recorder, on_episode, max_steps)
        extra = 0
        while min_steps is not None and extra < max_extra_episodes:
            missing = int(min_steps) - recorder.n_steps
            if missing <= 0:
                break
            cap = missing if max_steps is None else min(missing, int(max_steps))
            run_episodes(env, policy, [int(seed) + int(episodes) + extra], recorder, None, cap)
            extra += 1
        return recorder.to_dataset(recording_metadata(env, env_id, env_kwargs, spec, seed))
    finally:
        env.close()


def summarize(data: ds.Dataset) -> dict:
    """Steps, episodes, jams, escapes and stuck fraction of a dataset (ground truth)."""
    last = np.cumsum(data["episode_lengths"]) - 1
    out = {
        "steps": data.n_steps,
        "episodes": data.n_episodes,
        "jams": int(data["jams"][last].sum()),
        "escapes": int(data["escapes"][last].sum()),
        "stuck_fraction": float(data["stuck"].mean()) if data.n_steps else 0.0,
        "distance_m": float(data["distance_m"][last].sum()),
    }
    if "escaped" in data:
        out["escaped_episodes"] = int(data["escaped"][last].sum())
    return out
