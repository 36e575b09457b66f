"""Minari (Farama's offline-RL dataset standard) export and import of mkv datasets.

::

    from mkv_env.minari_io import export_minari, import_minari
    export_minari(load("teacher.npz"), "mkv/teacher-v0")     # into Minari's local store
    data = import_minari("mkv/teacher-v0")                     # back: equal arrays and metadata

or ``mkv export DATA.npz --minari mkv/teacher-v0`` and ``mkv import-minari mkv/teacher-v0 --out
DATA.npz``. One Minari episode per mkv episode: observations (with the final one: length n + 1),
actions, rewards, terminations, truncations, and the ground-truth columns as step ``infos``
(``stuck``, ``bumped``, ``collision``, ``in_jam``, ``distance_m``, ``jams``, ``escapes``,
``collisions``, ``pose``, and ``escaped`` on ``MKVJam``); the episode seed as Minari's episode
seed; the env (id and kwargs) as the dataset's env spec, so ``dataset.recover_environment()``
rebuilds it (with ``mkv_env`` imported); the mkv metadata (JSON) under ``mkv_metadata``.

Everything stays local: datasets go to ``data_path`` or Minari's ``MINARI_DATASETS_PATH``
(default ``~/.minari/datasets``); nothing is downloaded. Needs the ``minari`` extra
(``pip install 'mkv-sfm[minari]'``: minari with its HDF5 backend, about 35 MB; jax, which
Minari's own step-by-step collector needs, is not needed here).
"""

from __future__ import annotations

import json
import os
import re
import warnings
from contextlib import contextmanager

import numpy as np

from mkv_env import dataset as ds

__all__ = ["MinariError", "export_minari", "import_minari", "INFO_FIELDS"]

#: Per-step arrays stored as Minari step infos.
INFO_FIELDS = ("stuck", "bumped", "collision", "in_jam", "distance_m", "jams", "escapes",
               "collisions", "pose", "escaped")
_ID = re.compile(r"^(?:[A-Za-z0-9][\w-]*/)*[A-Za-z0-9][\w-]*-v\d+$")


class MinariError(ValueError):
    """A bad dataset id, a missing or existing dataset, or no minari installed (one line)."""


def _minari():
    try:
        import minari
    except ImportError:
        raise MinariError("Minari export/import needs the minari extra (pip install "
                          "'mkv-sfm[minari]')") from None
    return minari


@contextmanager
def _datasets_path(data_path):
    """Point Minari at ``data_path`` for the duration (it reads MINARI_DATASETS_PATH)."""
    if data_path is None:
        yield
        return
    old = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = os.fspath(data_path)
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = old


def _check_id(dataset_id: str) -> None:
    if not isinstance(dataset_id, str) or not _ID.match(dataset_id):
        raise MinariError(f"bad Minari dataset id {dataset_id!r}: use NAMESPACE/NAME-vVERSION, "
                          "e.g. mkv/teacher-v0")


def export_minari(data: ds.Dataset, dataset_id: str, *, overwrite: bool = False,
                  data_path=None) -> str:
    """Write ``data`` as the local Minari dataset ``dataset_id``; returns the id.

    Raises :class:`MinariError` for a bad id or an existing dataset (unless ``overwrite``)."""
    _check_id(dataset_id)
    minari = _minari()
    import gymnasium as gym
    from minari.data_collector import EpisodeBuffer

    import mkv_env  # noqa: F401  (registers the ids)

    with _datasets_path(data_path):
        if dataset_id in minari.list_local_datasets():
            if not overwrite:
                raise MinariError(f"Minari dataset {dataset_id} exists; pass --overwrite to "
                                  "replace it")
            minari.delete_dataset(dataset_id)
        meta = data.metadata
        env_id, env_kwargs = meta["env_id"], dict(meta.get("env_kwargs") or {})
        env = gym.make(env_id, **env_kwargs)  # its spec carries the kwargs and step limit
        spec = env.spec
        buffers = []
        for e, rows in enumerate(data.episode_slices()):
            obs = np.concatenate([data["observations"][rows],
                                  data["final_observations"][e:e + 1]])
            infos = {k: np.asarray(data[k][rows]) for k in INFO_FIELDS if k in data}
            buffers.append(EpisodeBuffer(
                id=e, seed=int(data["episode_seeds"][e]), observations=obs,
                actions=np.asarray(data["actions"][rows]),
                rewards=list(np.asarray(data["rewards"][rows], dtype=np.float64)),
                terminations=list(np.asarray(data["terminated"][rows], dtype=bool)),
                truncations=list(np.asarray(data["truncated"][rows], dtype=bool)),
                infos=infos))
        try:
            with warnings.catch_warnings():
                # Minari nudges for an author, e-mail, code link and eval env: not ours to invent
                warnings.filterwarnings("ignore", message=".*is set to None",
                                        category=UserWarning)
                dataset = minari.create_dataset_from_buffers(
                    dataset_id, buffers, env=spec, algorithm_name=str(meta.get("policy")),
                    observation_space=env.observation_space, action_space=env.action_space,
                    description=(f"MK-V robot ({env_id}) recorded by mkv-sfm "
                                 f"{meta.get('package_version')}: {data.n_episodes} episodes "
                                 f"of policy {meta.get('policy')!r}; sensor channels "
                                 f"{', '.join(meta['sensor_names'])}"),
                    data_format="hdf5")
        finally:
            env.close()
        dataset.storage.update_metadata({"mkv_metadata": json.dumps(meta, sort_keys=True)})
    return dataset_id


def import_minari(dataset_id: str, *, data_path=None) -> ds.Dataset:
    """The mkv :class:`~mkv_env.dataset.Dataset` of a local Minari dataset written by
    :func:`export_minari` (validated like any dataset file)."""
    _check_id(dataset_id)
    minari = _minari()
    with _datasets_path(data_path):
        if dataset_id not in minari.list_local_datasets():
            raise MinariError(f"no local Minari dataset {dataset_id} (nothing is downloaded; "
                              "see minari list local)")
        dataset = minari.load_dataset(dataset_id, download=False)
        raw = dataset.storage.metadata.get("mkv_metadata")
        if raw is None:
            raise MinariError(f"Minari dataset {dataset_id} was not written by mkv export (no "
                              "mkv_metadata)")
        meta = json.loads(raw)
        episodes = list(dataset.iterate_episodes())
        seeds = [m.get("seed") for m in dataset.storage.get_episode_metadata(
            [ep.id for ep in episodes])]
    lengths = np.array([len(ep.rewards) for ep in episodes], dtype=np.int64)
    arrays = {
        "observations": np.concatenate([ep.observations[:-1] for ep in episodes]).astype(
            np.float32),
        "final_observations": np.stack([ep.observations[-1] for ep in episodes]).astype(
            np.float32),
        "actions": np.concatenate([ep.actions for ep in episodes]).astype(np.int64),
        "rewards": np.concatenate([ep.rewards for ep in episodes]).astype(np.float64),
        "terminated": np.concatenate([ep.terminations for ep in episodes]).astype(bool),
        "truncated": np.concatenate([ep.truncations for ep in episodes]).astype(bool),
        "episode_seeds": np.asarray(seeds, dtype=np.int64),
        "episode_lengths": lengths,
        "episode": np.repeat(np.arange(len(episodes), dtype=np.int32), lengths),
        "step": np.concatenate([np.arange(k, dtype=np.int32) for k in lengths]),
    }
    schema = {**ds.STEP_FIELDS, **ds.OPTIONAL_STEP_FIELDS}
    for key in INFO_FIELDS:
        if key in episodes[0].infos:
            dtype = np.dtype(schema[key][0])
            arrays[key] = np.concatenate([np.asarray(ep.infos[key]) for ep in episodes]).astype(
                dtype)
    try:
        return ds.build(arrays, meta)
    except ds.DatasetError as e:
        raise MinariError(f"Minari dataset {dataset_id} does not hold a valid mkv dataset: "
                          f"{e}") from None
