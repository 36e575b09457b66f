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
(default ``~/.minari/datasets``); nothing is downloaded, and an import creates nothing. An
export is built in a hidden folder of the store and moved into place when complete, so a
failed or interrupted export leaves no partial dataset, and ``overwrite`` replaces the old
dataset only once the new one is written. Needs the ``minari`` extra (``pip install
'mkv-sfm[minari]'``: minari with its HDF5 backend, about 43 MB; jax, which only Minari's
step-by-step ``DataCollector`` needs, is not needed here).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
import warnings
from contextlib import contextmanager

import numpy as np

from mkv_env import dataset as ds

__all__ = ["MinariError", "export_minari", "import_minari", "INFO_FIELDS", "check_dataset_id"]

#: Per-step arrays stored as Minari step infos (``escaped`` only where the dataset has it).
INFO_FIELDS = (*ds.INFO_FIELDS, *ds.OPTIONAL_STEP_FIELDS)

_SEGMENT = r"[A-Za-z0-9][A-Za-z0-9_-]*"
# Minari's own form is (namespace/)name-vN with a namespace of two characters or more; mkv
# asks for a namespace, ASCII letters/digits/_/- (so an id is a safe relative path) and a
# version without leading zeros (Minari parses v00 as the same version 0 as v0).
_ID = re.compile(rf"(?P<ns>{_SEGMENT}(?:/{_SEGMENT})*)/{_SEGMENT}-v(?:0|[1-9][0-9]*)")
_TMP_PREFIX = ".mkv-export-"
#: Folders a namespace may nest (Minari's own ``D4RL/door/human-v2`` uses two) and the longest id:
#: an id is a relative path in the store, and a deep one only makes paths no file system takes.
MAX_NAMESPACE_DEPTH = 4
MAX_ID_LENGTH = 200
# a NAME-vVERSION segment: a dataset's own folder, never a namespace folder
_DATASET_SEGMENT = re.compile(r".*-v[0-9]+")


class MinariError(ValueError):
    """A bad dataset id, a missing or existing dataset, or no minari installed (one line)."""


def _minari():
    try:
        import minari
    except ImportError:
        raise MinariError("Minari export/import needs the minari extra (pip install "
                          "'mkv-sfm[minari]')") from None
    return minari


def check_dataset_id(dataset_id) -> str:
    """``dataset_id`` if it has the form NAMESPACE/NAME-vVERSION, else :class:`MinariError`."""
    ok = isinstance(dataset_id, str) and len(dataset_id) <= MAX_ID_LENGTH
    m = _ID.fullmatch(dataset_id) if ok else None
    if m is None or len(m["ns"]) < 2:
        raise MinariError(f"bad Minari dataset id {_shown(dataset_id)}: use "
                          "NAMESPACE/NAME-vVERSION (ASCII letters, digits, _ and -; a namespace "
                          f"of 2 characters or more; at most {MAX_ID_LENGTH} characters), e.g. "
                          "mkv/teacher-v0")
    folders = m["ns"].split("/")
    if len(folders) > MAX_NAMESPACE_DEPTH:
        raise MinariError(f"bad Minari dataset id {_shown(dataset_id)}: a namespace of "
                          f"{len(folders)} folders; at most {MAX_NAMESPACE_DEPTH}")
    nested = next((f for f in folders if _DATASET_SEGMENT.fullmatch(f)), None)
    if nested is not None:
        raise MinariError(f"bad Minari dataset id {_shown(dataset_id)}: its namespace folder "
                          f"{nested!r} has the form of a dataset (NAME-vVERSION); a dataset "
                          "inside another's folder is invisible to Minari")
    return dataset_id


def _shown(dataset_id) -> str:
    """repr of an id for a message, cut to 80 characters."""
    text = repr(dataset_id)
    return text if len(text) <= 80 else text[:77] + "..."


def _store_root(data_path) -> str:
    """The Minari store: ``data_path``, else MINARI_DATASETS_PATH, else ~/.minari/datasets."""
    if data_path is None:
        data_path = os.environ.get("MINARI_DATASETS_PATH") or os.path.join(
            os.path.expanduser("~"), ".minari", "datasets")
    root = os.path.abspath(os.fspath(data_path))
    if os.path.exists(root) and not os.path.isdir(root):
        raise MinariError(f"Minari dataset folder {root} is not a directory")
    return root


def _is_dataset(root: str, dataset_id: str) -> bool:
    return os.path.isdir(os.path.join(root, dataset_id, "data"))  # Minari's own test


@contextmanager
def _minari_store(path: str):
    """Point Minari at ``path`` for the duration (it reads MINARI_DATASETS_PATH on each call)."""
    old = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = path
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = old


def _episode_buffers(data: ds.Dataset):
    from minari.data_collector import EpisodeBuffer

    for e, rows in enumerate(data.episode_slices()):
        yield EpisodeBuffer(
            id=e, seed=int(data["episode_seeds"][e]),
            observations=np.concatenate([data["observations"][rows],
                                         data["final_observations"][e:e + 1]]),
            actions=np.asarray(data["actions"][rows]),
            rewards=list(np.asarray(data["rewards"][rows], dtype=np.float64)),
            terminations=list(np.asarray(data["terminated"][rows], dtype=bool)),
            truncations=list(np.asarray(data["truncated"][rows], dtype=bool)),
            infos={k: np.asarray(data[k][rows]) for k in INFO_FIELDS if k in data})


def export_minari(data: ds.Dataset, dataset_id: str, *, overwrite: bool = False,
                  data_path=None) -> str:
    """Write ``data`` as the local Minari dataset ``dataset_id``; returns the id.

    Raises :class:`MinariError` for a bad id, an existing dataset (unless ``overwrite``), an
    empty dataset or a missing minari; ``ValueError`` if the dataset's env cannot be made."""
    from mkv_env.recorder import make_env

    check_dataset_id(dataset_id)
    minari = _minari()
    if data.n_episodes == 0:
        raise MinariError("the dataset has no episodes; Minari needs at least one")
    root = _store_root(data_path)
    target = os.path.join(root, dataset_id)
    if _is_dataset(root, dataset_id):
        if not overwrite:
            raise MinariError(f"Minari dataset {dataset_id} exists in {root}; pass --overwrite "
                              "to replace it")
    elif os.path.lexists(target):
        raise MinariError(f"{target} exists and is not a Minari dataset; choose another id")
    meta = data.metadata
    env = make_env(meta["env_id"], meta.get("env_kwargs"))  # its spec carries kwargs and limit
    os.makedirs(root, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=_TMP_PREFIX, dir=root)  # hidden: Minari's listing skips it
    try:
        with _minari_store(tmp), warnings.catch_warnings():
            # Minari nudges for an author, e-mail, code link and eval env: not ours to invent
            warnings.filterwarnings("ignore", message=".*is set to None", category=UserWarning)
            dataset = minari.create_dataset_from_buffers(
                dataset_id, list(_episode_buffers(data)), env=env.spec,
                algorithm_name=str(meta.get("policy")),
                observation_space=env.observation_space, action_space=env.action_space,
                description=(f"MK-V robot ({meta['env_id']}) recorded by mkv-sfm "
                             f"{meta.get('package_version')}: {data.n_episodes} episodes of "
                             f"policy {meta.get('policy')!r}; sensor channels "
                             f"{', '.join(meta['sensor_names'])}"),
                data_format="hdf5")
            dataset.storage.update_metadata({"mkv_metadata": json.dumps(meta, sort_keys=True)})
            del dataset
        _move_into_store(tmp, root, dataset_id)
    finally:
        env.close()
        shutil.rmtree(tmp, ignore_errors=True)
    return dataset_id


def _move_into_store(tmp: str, root: str, dataset_id: str) -> None:
    """Move the finished dataset from ``tmp`` to ``root`` (replacing an old one) and copy the
    namespace files Minari wrote that the store lacks."""
    target = os.path.join(root, dataset_id)
    os.makedirs(os.path.dirname(target), exist_ok=True)
    if os.path.isdir(target):
        old = tempfile.mkdtemp(prefix=_TMP_PREFIX, dir=root)
        os.replace(target, os.path.join(old, "old"))
        os.replace(os.path.join(tmp, dataset_id), target)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(os.path.join(tmp, dataset_id), target)
    for here, _dirs, files in os.walk(tmp):
        for name in files:
            dest = os.path.join(root, os.path.relpath(os.path.join(here, name), tmp))
            if name == "namespace_metadata.json" and not os.path.exists(dest):
                shutil.copyfile(os.path.join(here, name), dest)


def _check_regular_files(root: str, dataset_id: str) -> None:
    """:class:`MinariError` (one line) if the dataset's folder, or a namespace file on the way to
    it, holds anything but regular files and folders: Minari and h5py would block forever on a
    FIFO put in place of ``metadata.json`` or ``main_data.hdf5``, or read a device."""
    import stat

    def check(path: str) -> None:
        try:
            mode = os.stat(path).st_mode
        except OSError as e:
            raise MinariError(f"cannot read Minari dataset {dataset_id}: {path}: "
                              f"{e.strerror}") from None
        if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
            raise MinariError(f"Minari dataset {dataset_id}: {path} is not a regular file (a "
                              "FIFO, socket or device)")

    parts = dataset_id.split("/")
    for depth in range(1, len(parts)):
        meta = os.path.join(root, *parts[:depth], "namespace_metadata.json")
        if os.path.lexists(meta):
            check(meta)
    for here, dirs, files in os.walk(os.path.join(root, dataset_id)):
        for name in (*files, *dirs):
            check(os.path.join(here, name))


def import_minari(dataset_id: str, *, data_path=None) -> ds.Dataset:
    """The mkv :class:`~mkv_env.dataset.Dataset` of a local Minari dataset written by
    :func:`export_minari` (validated like any dataset file). Reads only; never downloads."""
    check_dataset_id(dataset_id)
    minari = _minari()
    root = _store_root(data_path)
    if not _is_dataset(root, dataset_id):
        raise MinariError(f"no local Minari dataset {dataset_id} in {root} (nothing is "
                          "downloaded)")
    _check_regular_files(root, dataset_id)
    try:
        with _minari_store(root):
            dataset = minari.load_dataset(dataset_id, download=False)
            raw = dataset.storage.metadata.get("mkv_metadata")
            if raw is None:
                raise MinariError(f"Minari dataset {dataset_id} was not written by mkv export "
                                  "(no mkv_metadata)")
            meta = json.loads(raw)
            episodes = list(dataset.iterate_episodes())
            seeds = [m.get("seed") for m in dataset.storage.get_episode_metadata(
                [ep.id for ep in episodes])]
    except MinariError:
        raise
    except (OSError, KeyError, ValueError) as e:  # a damaged store: h5py, JSON, Minari
        text = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise MinariError(f"cannot read Minari dataset {dataset_id}: {text}") from None
    if not episodes or not isinstance(meta, dict):
        raise MinariError(f"Minari dataset {dataset_id} does not hold an mkv dataset")
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
        "episode_lengths": lengths,
        "episode": np.repeat(np.arange(len(episodes), dtype=np.int32), lengths),
        "step": np.concatenate([np.arange(k, dtype=np.int32) for k in lengths]),
    }
    schema = {**ds.STEP_FIELDS, **ds.OPTIONAL_STEP_FIELDS}
    try:
        arrays["episode_seeds"] = np.asarray(seeds, dtype=np.int64)
        for key in INFO_FIELDS:
            if key in episodes[0].infos:
                arrays[key] = np.concatenate(
                    [np.asarray(ep.infos[key]) for ep in episodes]).astype(schema[key][0])
        # verified, not recomputed: the arrays must be those the export recorded
        if meta.get("content_sha256") != ds.content_sha256(arrays):
            raise MinariError(f"Minari dataset {dataset_id}: its contents do not match the "
                              "content_sha256 recorded by mkv export (altered since?)")
        return ds.build(arrays, meta)
    except MinariError:
        raise
    except (TypeError, ValueError, KeyError) as e:  # DatasetError is a ValueError
        text = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise MinariError(f"Minari dataset {dataset_id} does not hold a valid mkv dataset: "
                          f"{text}") from None
