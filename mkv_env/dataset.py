"""The recorded-dataset format: numpy arrays plus JSON metadata in one ``.npz`` file.

One row per control step, in episode order. Row ``t`` of an episode holds the observation the
policy saw, the action it sent, and what the env returned for that action (reward,
terminated/truncated, ground-truth ``info`` after the step).

Per-step arrays (``N`` = total steps):

| key            | shape   | dtype   | meaning                                                 |
|----------------|---------|---------|---------------------------------------------------------|
| observations   | (N, C)  | float32 | sensor channels seen before acting (names in metadata)  |
| actions        | (N, 2)  | int64   | [drive, steer] sent, 0/1/2                              |
| rewards        | (N,)    | float64 | reward for that step                                    |
| terminated     | (N,)    | bool    | env terminated after that step                          |
| truncated      | (N,)    | bool    | env truncated after that step (time limit)              |
| episode        | (N,)    | int32   | episode index 0..E-1                                    |
| step           | (N,)    | int32   | step index within the episode                           |
| stuck          | (N,)    | bool    | info: commanded to drive but not moving                 |
| bumped         | (N,)    | bool    | info: any bump switch pressed                           |
| collision      | (N,)    | bool    | info: new contact this step                             |
| in_jam         | (N,)    | bool    | info                                                    |
| distance_m     | (N,)    | float64 | info: cumulative distance in the episode [m]            |
| jams, escapes, collisions | (N,) | int32 | info: cumulative counts                          |
| pose           | (N, 3)  | float64 | info: x [m], y [m], heading [rad] after the step        |
| escaped        | (N,)    | bool    | info (only envs that report it, e.g. ``MKVJam-v0``)     |

Per-episode arrays (``E`` episodes): ``episode_seeds`` (int64), ``episode_lengths`` (int64),
``final_observations`` (E, C) float32 (the observation after the last step).

``metadata`` (a JSON document stored as a uint8 array, so loading never needs pickle): ``format``
(``"mkv-dataset"``), ``schema_version``, ``env_id``, ``env_kwargs``, ``policy``, ``seed``,
``sensor_names``, ``control_period_s``, ``package_version``, ``n_steps``, ``n_episodes``,
``episode_scenarios`` (list or null), ``has_escaped``, ``content_sha256`` (of every array, so a
tampered file is caught even when the zip checksums were redone).

Writes are atomic (temporary file in the same directory, then ``os.replace``) and deterministic:
the zip entries carry a fixed timestamp, so recording the same seeds twice gives byte-identical
files.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import tokenize
import zipfile
import zlib
from dataclasses import dataclass, field

import numpy as np

from mkv_env.actions import ACTION_NVEC
from mkv_env.params import MAX_READING
from sfm_common.files import atomic_path

FORMAT = "mkv-dataset"
SCHEMA_VERSION = 1

STEP_FIELDS: dict[str, tuple[str, tuple]] = {
    # key: (dtype, trailing shape); "C" = number of sensor channels
    "observations": ("float32", ("C",)),
    "actions": ("int64", (len(ACTION_NVEC),)),
    "rewards": ("float64", ()),
    "terminated": ("bool", ()),
    "truncated": ("bool", ()),
    "episode": ("int32", ()),
    "step": ("int32", ()),
    "stuck": ("bool", ()),
    "bumped": ("bool", ()),
    "collision": ("bool", ()),
    "in_jam": ("bool", ()),
    "distance_m": ("float64", ()),
    "jams": ("int32", ()),
    "escapes": ("int32", ()),
    "collisions": ("int32", ()),
    "pose": ("float64", (3,)),
}
OPTIONAL_STEP_FIELDS: dict[str, tuple[str, tuple]] = {"escaped": ("bool", ())}
EPISODE_FIELDS: dict[str, tuple[str, tuple]] = {
    "episode_seeds": ("int64", ()),
    "episode_lengths": ("int64", ()),
    "final_observations": ("float32", ("C",)),
}
INFO_FIELDS = ("stuck", "bumped", "collision", "in_jam", "distance_m", "jams", "escapes",
               "collisions", "pose")
"""The env ``info`` keys stored per step (plus ``escaped`` where the env reports it)."""

METADATA_KEYS = ("format", "schema_version", "env_id", "env_kwargs", "policy", "seed",
                 "sensor_names", "control_period_s", "package_version", "n_steps", "n_episodes",
                 "episode_scenarios", "has_escaped", "content_sha256")

_ZIP_DATE = (1980, 1, 1, 0, 0, 0)


class DatasetError(ValueError):
    """A dataset file that is missing, truncated, tampered with or not a dataset (one line)."""


@dataclass
class Dataset:
    """Arrays (see the module docstring for keys, shapes and dtypes) and metadata."""

    arrays: dict[str, np.ndarray]
    metadata: dict = field(default_factory=dict)

    def __getitem__(self, key: str) -> np.ndarray:
        return self.arrays[key]

    def __contains__(self, key: str) -> bool:
        return key in self.arrays

    @property
    def n_steps(self) -> int:
        return int(len(self.arrays["actions"]))

    @property
    def n_episodes(self) -> int:
        return int(len(self.arrays["episode_seeds"]))

    @property
    def sensor_names(self) -> list[str]:
        return list(self.metadata["sensor_names"])

    def episode_slices(self) -> list[slice]:
        """Row range of each episode, in order."""
        ends = np.cumsum(self.arrays["episode_lengths"])
        starts = ends - self.arrays["episode_lengths"]
        return [slice(int(a), int(b)) for a, b in zip(starts, ends, strict=True)]

    def select_episodes(self, indices) -> Dataset:
        """A new dataset holding the given episodes (in the given order), renumbered 0..k-1."""
        indices = [int(i) for i in np.asarray(indices, dtype=np.int64).reshape(-1)]
        for i in indices:
            if not 0 <= i < self.n_episodes:
                raise IndexError(f"episode {i} out of range [0, {self.n_episodes})")
        slices = self.episode_slices()
        rows = (np.concatenate([np.arange(slices[i].start, slices[i].stop) for i in indices])
                if indices else np.zeros(0, dtype=np.int64))
        arrays = {}
        for key, arr in self.arrays.items():
            if key in EPISODE_FIELDS:
                arrays[key] = arr[indices]
            else:
                arrays[key] = arr[rows]
        lengths = arrays["episode_lengths"]
        arrays["episode"] = np.repeat(np.arange(len(indices), dtype=np.int32), lengths)
        meta = dict(self.metadata)
        scen = meta.get("episode_scenarios")
        meta["episode_scenarios"] = None if scen is None else [scen[i] for i in indices]
        meta["n_steps"], meta["n_episodes"] = int(len(rows)), len(indices)
        meta["source_episodes"] = [
            self.metadata.get("source_episodes", list(range(self.n_episodes)))[i] for i in indices
        ]
        return build(arrays, meta)

    def split(self, held_out_fraction: float = 0.2, seed: int = 0) -> tuple[Dataset, Dataset]:
        """Split by whole episodes into (train, held_out); see :func:`split_by_episode`."""
        return split_by_episode(self, held_out_fraction, seed)

    def equals(self, other: Dataset) -> bool:
        """Exact equality of every array (dtype, shape, bytes) and of the metadata."""
        if set(self.arrays) != set(other.arrays) or self.metadata != other.metadata:
            return False
        return all(
            a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
            for a, b in ((self.arrays[k], other.arrays[k]) for k in self.arrays)
        )


def build(arrays: dict[str, np.ndarray], metadata: dict) -> Dataset:
    """A validated :class:`Dataset` from arrays and metadata: the metadata is normalised through
    JSON (tuples become lists, as after a save/load round trip) and its counts and checksum set."""
    meta = json.loads(json.dumps(metadata, sort_keys=True))
    meta.setdefault("format", FORMAT)
    meta.setdefault("schema_version", SCHEMA_VERSION)
    meta["n_steps"] = int(len(arrays["actions"]))
    meta["n_episodes"] = int(len(arrays["episode_seeds"]))
    meta["content_sha256"] = content_sha256(arrays)
    data = Dataset(dict(arrays), meta)
    validate(data)
    return data


def split_by_episode(data: Dataset, held_out_fraction: float = 0.2,
                     seed: int = 0) -> tuple[Dataset, Dataset]:
    """Split whole episodes into (train, held_out), a seeded random choice of episodes.

    At least one episode goes to each side when there are two or more; both keep episode order.
    """
    if not (0.0 <= held_out_fraction < 1.0):
        raise ValueError(f"held_out_fraction must be in [0, 1), got {held_out_fraction!r}")
    n = data.n_episodes
    k = int(round(held_out_fraction * n))
    if held_out_fraction > 0 and n >= 2:
        k = min(max(k, 1), n - 1)
    held = np.sort(np.random.default_rng(seed).permutation(n)[:k])
    train = np.setdiff1d(np.arange(n), held)
    return data.select_episodes(train), data.select_episodes(held)


# ---------------------------------------------------------------------- hashing / validation
def content_sha256(arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 over every array's key, dtype, shape and bytes, in sorted key order."""
    h = hashlib.sha256()
    for key in sorted(arrays):
        a = np.ascontiguousarray(arrays[key])
        h.update(f"{key}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def validate(data: Dataset) -> None:
    """Raise :class:`DatasetError` unless arrays and metadata follow the schema."""
    meta, arrays = data.metadata, data.arrays
    if not isinstance(meta, dict):
        raise DatasetError("metadata is not a JSON object")
    if meta.get("format") != FORMAT:
        raise DatasetError(f"not an MKV dataset (format {meta.get('format')!r})")
    if meta.get("schema_version") != SCHEMA_VERSION:
        raise DatasetError(
            f"schema version {meta.get('schema_version')!r} is not supported "
            f"(this package reads version {SCHEMA_VERSION})"
        )
    missing = [k for k in METADATA_KEYS if k not in meta]
    if missing:
        raise DatasetError(f"metadata lacks {', '.join(missing)}")
    names = meta["sensor_names"]
    if not (isinstance(names, list) and names and all(isinstance(n, str) for n in names)):
        raise DatasetError("metadata sensor_names must be a non-empty list of strings")
    expected = dict(STEP_FIELDS)
    if meta["has_escaped"]:
        expected.update(OPTIONAL_STEP_FIELDS)
    expected.update(EPISODE_FIELDS)
    missing = sorted(set(expected) - set(arrays))
    extra = sorted(set(arrays) - set(expected))
    if missing:
        raise DatasetError(f"missing arrays: {', '.join(missing)}")
    if extra:
        raise DatasetError(f"unexpected arrays: {', '.join(extra)}")
    n, e, c = meta["n_steps"], meta["n_episodes"], len(names)
    for key, (dtype, tail) in expected.items():
        a = arrays[key]
        rows = e if key in EPISODE_FIELDS else n
        shape = (rows, *(c if d == "C" else d for d in tail))
        if a.dtype != np.dtype(dtype) or a.shape != shape:
            raise DatasetError(
                f"array {key!r} is {a.dtype}{list(a.shape)}, expected {dtype}{list(shape)}"
            )
    lengths = arrays["episode_lengths"]
    if np.any(lengths < 1) or int(lengths.sum()) != n:
        raise DatasetError("episode_lengths do not add up to n_steps")
    expect_ep = np.repeat(np.arange(e, dtype=np.int32), lengths)
    if not np.array_equal(arrays["episode"], expect_ep):
        raise DatasetError("episode column is not 0..E-1 in runs of episode_lengths")
    expect_step = np.concatenate([np.arange(k, dtype=np.int32) for k in lengths]) if e else \
        np.zeros(0, dtype=np.int32)
    if not np.array_equal(arrays["step"], expect_step):
        raise DatasetError("step column does not count 0.. within each episode")
    scen = meta["episode_scenarios"]
    if scen is not None and (not isinstance(scen, list) or len(scen) != e):
        raise DatasetError("episode_scenarios must be null or one entry per episode")
    _validate_values(meta, arrays)
    if meta["content_sha256"] != content_sha256(arrays):
        raise DatasetError("array contents do not match the recorded checksum (file altered?)")


#: Largest magnitude accepted for a sensor reading: the MK-V's channels stay within +-60 (encoder
#: ticks per step); anything near float32's range is a damaged or fabricated file, not a reading.
MAX_ABS_READING = MAX_READING


def _validate_values(meta: dict, arrays: dict) -> None:
    """The content, not only the layout: finite readings of plausible size, actions in range,
    finite rewards and poses, a usable control period. (The checksum only proves the file is
    unchanged since its checksum was computed; anyone can recompute it.)"""
    for key in ("observations", "final_observations"):
        a = arrays[key]
        bad = ~np.isfinite(a) | (np.abs(a) > MAX_ABS_READING)
        if bad.any():
            row, col = (int(v[0]) for v in np.nonzero(bad))
            raise DatasetError(f"{key} row {row}, channel {meta['sensor_names'][col]!r} is "
                               f"{a[row, col]!r}: readings must be finite and within "
                               f"+-{MAX_ABS_READING:g}")
    act = arrays["actions"]
    if act.size and (act.min() < 0 or np.any(act >= np.asarray(ACTION_NVEC))):
        raise DatasetError(f"actions must be command indices 0..{max(ACTION_NVEC) - 1}, found "
                           f"{int(act.min())}..{int(act.max())}")
    for key in ("rewards", "distance_m", "pose"):
        if not np.all(np.isfinite(arrays[key])):
            raise DatasetError(f"{key} contains NaN or infinite values")
    if np.any(arrays["episode_seeds"] < 0):
        raise DatasetError("episode_seeds must be non-negative")
    dt = meta.get("control_period_s")
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not (0 < dt < 1e3):
        raise DatasetError(f"control_period_s must be a positive number of seconds, got {dt!r}")
    if not isinstance(meta.get("env_kwargs", {}), dict):
        raise DatasetError("env_kwargs must be a JSON object")


# ---------------------------------------------------------------------- save / load
def save(data: Dataset, path) -> str:
    """Write ``data`` to ``path`` atomically and deterministically; returns the path.

    The content checksum and counts in the metadata are (re)computed here.
    """
    path = os.fspath(path)
    arrays = {k: np.ascontiguousarray(v) for k, v in data.arrays.items()}
    meta = dict(data.metadata)
    meta["n_steps"] = int(len(arrays["actions"]))
    meta["n_episodes"] = int(len(arrays["episode_seeds"]))
    meta["content_sha256"] = content_sha256(arrays)
    validate(Dataset(arrays, meta))
    meta_bytes = json.dumps(meta, sort_keys=True, separators=(",", ":")).encode("utf-8")
    with atomic_path(path, ".npz") as tmp, open(tmp, "wb") as f:
        with zipfile.ZipFile(f, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
            _write_entry(zf, "metadata", np.frombuffer(meta_bytes, dtype=np.uint8))
            for key in sorted(arrays):
                _write_entry(zf, key, arrays[key])
        f.flush()
        os.fsync(f.fileno())
    return path


def _write_entry(zf: zipfile.ZipFile, key: str, array: np.ndarray) -> None:
    info = zipfile.ZipInfo(key + ".npy", date_time=_ZIP_DATE)
    info.compress_type = zipfile.ZIP_DEFLATED
    info.external_attr = 0o644 << 16
    buf = io.BytesIO()
    np.lib.format.write_array(buf, array, allow_pickle=False)
    zf.writestr(info, buf.getvalue(), compresslevel=1)


def load(path, check: bool = True) -> Dataset:
    """Read and validate a dataset file. Raises :class:`DatasetError` with a one-line reason."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise DatasetError(f"{path}: no such file")
    if not os.path.isfile(path):
        raise DatasetError(f"{path} is not a regular file (a directory, FIFO or device)")
    try:
        with np.load(path, allow_pickle=False) as npz:
            raw = {k: npz[k] for k in npz.files}
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, KeyError,
            NotImplementedError, RuntimeError, SyntaxError, tokenize.TokenError) as e:
        # RuntimeError: an "encrypted" member; SyntaxError, TokenError: a damaged .npy header
        # (numpy parses it as a Python literal)
        reason = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise DatasetError(f"{path}: not a readable dataset (truncated or corrupt: {reason})") \
            from None
    if "metadata" not in raw:
        raise DatasetError(f"{path}: not an MKV dataset (no metadata entry)")
    try:
        meta = json.loads(raw.pop("metadata").tobytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, ValueError) as e:
        raise DatasetError(f"{path}: metadata is not valid JSON ({e})") from None
    data = Dataset(raw, meta)
    if check:
        try:
            validate(data)
        except DatasetError as e:
            raise DatasetError(f"{path}: {e}") from None
    return data
