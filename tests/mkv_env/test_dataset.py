"""Dataset format: exact round trip, deterministic bytes, atomic writes, clear load errors."""

import json
import os
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mkv_env import dataset as ds
from mkv_env.recorder import record


@pytest.fixture(scope="module")
def jam_data():
    return record("MKVJam-v0", "teacher", episodes=6, seed=0)


def _one_line_error(path):
    with pytest.raises(ds.DatasetError) as e:
        ds.load(path)
    msg = str(e.value)
    assert "\n" not in msg and str(path) in msg
    return msg


def test_round_trip_is_exact(jam_data, tmp_path):
    path = ds.save(jam_data, tmp_path / "d.npz")
    back = ds.load(path)
    assert back.equals(jam_data)
    for k, a in jam_data.arrays.items():
        assert back[k].dtype == a.dtype and np.array_equal(back[k], a)
    assert back.metadata == jam_data.metadata
    assert back.sensor_names == jam_data.sensor_names


def test_schema_contents(jam_data):
    m = jam_data.metadata
    assert m["format"] == "mkv-dataset" and m["schema_version"] == ds.SCHEMA_VERSION
    assert m["env_id"] == "MKVJam-v0" and m["policy"] == "teacher" and m["seed"] == 0
    assert m["package_version"] and len(m["sensor_names"]) == 10
    assert m["has_escaped"] and len(m["episode_scenarios"]) == 6
    assert list(jam_data["episode_seeds"]) == [0, 1, 2, 3, 4, 5]
    assert set(ds.STEP_FIELDS) | {"escaped"} | set(ds.EPISODE_FIELDS) == set(jam_data.arrays)


def test_same_seeds_give_identical_bytes(jam_data, tmp_path):
    again = record("MKVJam-v0", "teacher", episodes=6, seed=0)
    for k in jam_data.arrays:
        assert again[k].tobytes() == jam_data[k].tobytes(), k
    a = ds.save(jam_data, tmp_path / "a.npz")
    b = ds.save(again, tmp_path / "b.npz")
    assert open(a, "rb").read() == open(b, "rb").read()


def test_truncated_file(jam_data, tmp_path):
    path = ds.save(jam_data, tmp_path / "d.npz")
    raw = open(path, "rb").read()
    for cut in (len(raw) // 2, len(raw) - 10, 30):
        bad = tmp_path / f"cut{cut}.npz"
        bad.write_bytes(raw[:cut])
        assert "truncated or corrupt" in _one_line_error(bad)


def test_flipped_bytes_anywhere(jam_data, tmp_path):
    path = ds.save(jam_data, tmp_path / "d.npz")
    raw = open(path, "rb").read()
    for pos in np.linspace(0, len(raw) - 1, 40).astype(int):
        flipped = bytearray(raw)
        flipped[pos] ^= 0xFF
        bad = tmp_path / "flip.npz"
        bad.write_bytes(bytes(flipped))
        try:
            back = ds.load(bad)
        except ds.DatasetError as e:
            assert "\n" not in str(e)
        else:  # a flip in a zip field nobody reads (e.g. a timestamp) is harmless
            assert back.equals(jam_data)


def _rewrite(src, dst, change):
    """Re-save a dataset file with consistent zip checksums after ``change(arrays, meta)``."""
    with np.load(src) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays.pop("metadata").tobytes())
    change(arrays, meta)
    with zipfile.ZipFile(dst, "w") as zf:
        zf.writestr("metadata.npy", _npy(np.frombuffer(json.dumps(meta).encode(), np.uint8)))
        for k, a in arrays.items():
            zf.writestr(k + ".npy", _npy(a))


def _npy(a):
    import io

    buf = io.BytesIO()
    np.lib.format.write_array(buf, a)
    return buf.getvalue()


@pytest.mark.parametrize("change,match", [
    (lambda a, m: a["actions"].__setitem__((0, 0), 2 - a["actions"][0, 0]), "checksum"),
    (lambda a, m: a.__setitem__("rewards", a["rewards"][:-1]), "rewards"),
    (lambda a, m: a.__setitem__("pose", a["pose"].astype(np.float32)), "pose"),
    (lambda a, m: a.pop("stuck"), "missing arrays: stuck"),
    (lambda a, m: a.__setitem__("extra", np.zeros(3)), "unexpected arrays: extra"),
    (lambda a, m: m.__setitem__("schema_version", 99), "schema version 99"),
    (lambda a, m: m.__setitem__("format", "other"), "not an MKV dataset"),
    (lambda a, m: m.pop("sensor_names"), "lacks sensor_names"),
    (lambda a, m: a["episode"].__setitem__(0, 3), "episode column"),
])
def test_tampered_file(jam_data, tmp_path, change, match):
    src = ds.save(jam_data, tmp_path / "d.npz")
    bad = tmp_path / "bad.npz"
    _rewrite(src, bad, change)
    assert match in _one_line_error(bad)


def test_wrong_files(tmp_path):
    assert "no such file" in _one_line_error(tmp_path / "missing.npz")
    text = tmp_path / "text.npz"
    text.write_text("time drive steer\n")
    _one_line_error(text)
    plain = tmp_path / "plain.npz"
    np.savez(plain, x=np.arange(3))
    assert "no metadata" in _one_line_error(plain)


def test_atomic_save_leaves_old_file_and_no_temp(jam_data, tmp_path, monkeypatch):
    path = tmp_path / "d.npz"
    ds.save(jam_data, path)
    before = path.read_bytes()

    def boom(src, dst):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", boom)
    small = jam_data.select_episodes([0])
    with pytest.raises(KeyboardInterrupt):
        ds.save(small, path)
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["d.npz"]


def test_split_by_episode(jam_data):
    train, held = jam_data.split(held_out_fraction=0.34, seed=1)
    assert train.n_episodes + held.n_episodes == 6 and held.n_episodes == 2
    src = train.metadata["source_episodes"] + held.metadata["source_episodes"]
    assert sorted(src) == list(range(6))
    assert train.n_steps + held.n_steps == jam_data.n_steps
    # each held-out episode is a verbatim copy of its source episode
    slices = jam_data.episode_slices()
    for j, e in enumerate(held.metadata["source_episodes"]):
        rows = held.episode_slices()[j]
        assert np.array_equal(held["observations"][rows], jam_data["observations"][slices[e]])
        assert held["episode_seeds"][j] == jam_data["episode_seeds"][e]
        assert held.metadata["episode_scenarios"][j] == jam_data.metadata["episode_scenarios"][e]
    assert list(held["episode"]) == sorted(held["episode"]) and held["episode"][0] == 0
    again = jam_data.split(0.34, seed=1)[1]
    assert again.metadata["source_episodes"] == held.metadata["source_episodes"]
    with pytest.raises(ValueError):
        jam_data.split(1.0)


def test_split_subset_saves_and_loads(jam_data, tmp_path):
    _, held = jam_data.split(0.5, seed=0)
    assert ds.load(ds.save(held, tmp_path / "h.npz")).equals(held)


def _write_unchecked(data, path):
    """Write a dataset the way save() does, but without validating it, checksum recomputed (as
    anyone editing a file could): the loader must catch bad content on its own."""
    import json
    import zipfile

    from mkv_env.dataset import _write_entry, content_sha256

    meta = dict(data.metadata, content_sha256=content_sha256(data.arrays))
    with zipfile.ZipFile(path, "w") as zf:
        _write_entry(zf, "metadata", np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8))
        for key, a in data.arrays.items():
            _write_entry(zf, key, a)


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(key=st.sampled_from(["observations", "final_observations", "rewards", "pose",
                            "actions"]),
       value=st.sampled_from([np.nan, np.inf, -np.inf, 3e38, -1e7, 7, -1]),
       where=st.floats(0, 1))
def test_damaged_values_with_a_recomputed_checksum_are_refused(tmp_path, key, value, where):
    from mkv_env.dataset import Dataset, DatasetError, load

    data = record("MKVJam-v0", "random", 2, 0, {"max_episode_steps": 20})
    arrays = {k: v.copy() for k, v in data.arrays.items()}
    a = arrays[key]
    if a.dtype.kind == "i" and not (np.isfinite(value) and abs(value) < 1e9):
        value = 99
    i = min(int(where * a.size), a.size - 1)
    flat = a.reshape(-1)
    ok_value = key != "actions" and np.isfinite(value) and abs(value) <= 1e6
    if key == "actions":
        ok_value = 0 <= value <= 2
    if key in ("rewards", "pose"):
        ok_value = np.isfinite(value)
    flat[i] = value
    path = tmp_path / "d.npz"
    _write_unchecked(Dataset(arrays, data.metadata), path)
    if ok_value:
        load(path)
    else:
        with pytest.raises(DatasetError) as e:
            load(path)
        assert "\n" not in str(e.value)
