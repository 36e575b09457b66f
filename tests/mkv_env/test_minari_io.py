"""Minari export and import: a round trip equal to the npz (observations, actions, rewards,
terminations, every info column, seeds, metadata), readable by plain Minari, offline, and an
export that never leaves a partial dataset behind. (The commands: tests/sfm_learn/cli.)"""

import os
import sys
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

pytest.importorskip("minari", reason="the minari extra is not installed "
                                      "(pip install 'mkv-sfm[minari]')")

import minari  # noqa: E402
from minari.dataset.minari_dataset import gen_dataset_id, parse_dataset_id  # noqa: E402

from mkv_env import dataset as mds  # noqa: E402
from mkv_env.minari_io import (  # noqa: E402
    INFO_FIELDS,
    MinariError,
    check_dataset_id,
    export_minari,
    import_minari,
)
from mkv_env.recorder import make_env, record  # noqa: E402


@pytest.fixture
def store(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    return tmp_path / "minari"


def _listing(root):
    return sorted(os.path.relpath(os.path.join(d, f), root)
                  for d, _, files in os.walk(root) for f in files)


@pytest.mark.parametrize("env_id", ["MKVJam-v0", "MKV-v0"])
def test_round_trip_equals_the_dataset(store, env_id):
    data = record(env_id, "teacher", 3, seed=0, env_kwargs={"max_episode_steps": 60})
    dataset_id = f"mkv/{env_id.lower()}-v0"
    assert export_minari(data, dataset_id) == dataset_id
    back = import_minari(dataset_id)
    schema = {**mds.STEP_FIELDS, **mds.OPTIONAL_STEP_FIELDS, **mds.EPISODE_FIELDS}
    columns = ("observations", "final_observations", "actions", "rewards", "terminated",
               "truncated", "episode_seeds", "episode_lengths", *INFO_FIELDS)
    for key in columns:
        if key == "escaped" and env_id == "MKV-v0":
            assert key not in back and key not in data
            continue
        assert back[key].dtype == np.dtype(schema[key][0]) == data[key].dtype, key
        assert np.array_equal(back[key], data[key]), key
    assert back.metadata == data.metadata
    assert back.equals(data)  # every array (dtype, shape, bytes) and the metadata
    mds.validate(back)        # the checksum and schema of the dataset format


def test_plain_minari_reads_it_and_rebuilds_the_env(store):
    data = record("MKVJam-v0", "teacher", 2, seed=0, env_kwargs={"max_episode_steps": 30})
    export_minari(data, "mkv/plain-v1")
    assert "mkv/plain-v1" in minari.list_local_datasets()
    dset = minari.load_dataset("mkv/plain-v1", download=False)
    assert dset.total_episodes == 2 and dset.total_steps == data.n_steps
    assert dset.storage.metadata["algorithm_name"] == "teacher"
    episodes = list(dset.iterate_episodes())
    seeds = [m["seed"] for m in dset.storage.get_episode_metadata([ep.id for ep in episodes])]
    assert seeds == list(data["episode_seeds"])
    for ep, rows, final in zip(episodes, data.episode_slices(), data["final_observations"],
                               strict=True):
        n = rows.stop - rows.start
        assert ep.observations.shape == (n + 1, 10) and ep.actions.shape == (n, 2)
        np.testing.assert_array_equal(ep.observations[-1], final)
        np.testing.assert_array_equal(ep.rewards, data["rewards"][rows])
        np.testing.assert_array_equal(ep.infos["pose"], data["pose"][rows])
        np.testing.assert_array_equal(ep.infos["escaped"], data["escaped"][rows])
    env = dset.recover_environment()
    ref = make_env("MKVJam-v0", {"max_episode_steps": 30})
    try:
        assert env.observation_space == ref.observation_space
        assert env.action_space == ref.action_space
        assert env.spec.id == "MKVJam-v0" and env.spec.max_episode_steps == 30
    finally:
        env.close()
        ref.close()


@pytest.mark.parametrize("bad", ["no-version", "mkv/x", "../up-v0", "", "teacher-v0",
                                 "a/x-v0", "mkv/x-v00", "mkv/a.b-v0", "mkv//x-v0",
                                 "mkv/\u00fc-v0", "/abs/x-v0", "mkv/x-v0/", None, 3])
def test_bad_ids_are_refused_before_anything_is_written(store, bad):
    data = record("MKV-v0", "random", 1, seed=0, env_kwargs={"max_episode_steps": 5})
    with pytest.raises(MinariError, match="bad Minari dataset id") as e:
        export_minari(data, bad)
    assert "\n" not in str(e.value)
    with pytest.raises(MinariError, match="bad Minari dataset id"):
        import_minari(bad)
    assert not store.exists()


@pytest.mark.parametrize("good", ["mkv/teacher-v0", "ab/x-v12", "D4RL/door/human_1-v3",
                                  "mkv/x--v0", "mkv/x-v1-v2"])
def test_accepted_ids_are_minari_ids(good):
    assert check_dataset_id(good) == good
    assert gen_dataset_id(*parse_dataset_id(good)) == good


def test_existing_overwrite_and_missing(store, tmp_path):
    first = record("MKVJam-v0", "random", 1, seed=0, env_kwargs={"max_episode_steps": 10})
    second = record("MKVJam-v0", "teacher", 2, seed=5, env_kwargs={"max_episode_steps": 10})
    export_minari(first, "mkv/once-v0")
    with pytest.raises(MinariError, match="exists") as e:
        export_minari(second, "mkv/once-v0")
    assert "\n" not in str(e.value)
    assert import_minari("mkv/once-v0").equals(first)
    export_minari(second, "mkv/once-v0", overwrite=True)
    assert import_minari("mkv/once-v0").equals(second)
    assert not [p for p in os.listdir(store) if p.startswith(".")]  # no temporary folders
    with pytest.raises(MinariError, match="no local Minari dataset mkv/never-v0"):
        import_minari("mkv/never-v0")
    nowhere = tmp_path / "nowhere"
    with pytest.raises(MinariError, match="no local Minari dataset"):
        import_minari("mkv/once-v0", data_path=nowhere)
    assert not nowhere.exists()  # an import creates nothing
    with pytest.raises(MinariError, match="is not a Minari dataset"):
        export_minari(first, "mkv/x-v0", data_path=_namespace_store(tmp_path))


def _namespace_store(tmp_path):
    """A store where ``mkv/x-v0`` is a namespace folder (holding a dataset), not a dataset."""
    root = tmp_path / "ns_store"
    (root / "mkv" / "x-v0" / "y-v0").mkdir(parents=True)
    return root


def test_data_path_argument_wins_over_the_environment(store, tmp_path):
    data = record("MKV-v0", "random", 1, seed=0, env_kwargs={"max_episode_steps": 8})
    other = tmp_path / "other"
    export_minari(data, "mkv/here-v0", data_path=other)
    assert (other / "mkv" / "here-v0" / "data").is_dir()
    assert (other / "mkv" / "namespace_metadata.json").is_file()
    assert not store.exists()
    assert import_minari("mkv/here-v0", data_path=other).equals(data)
    with pytest.raises(MinariError, match="no local Minari dataset"):
        import_minari("mkv/here-v0")
    afile = tmp_path / "afile"
    afile.write_text("")
    with pytest.raises(MinariError, match="is not a directory"):
        export_minari(data, "mkv/here-v0", data_path=afile)


def test_a_failed_export_leaves_no_partial_dataset_and_keeps_the_old_one(store, monkeypatch):
    old = record("MKV-v0", "random", 1, seed=0, env_kwargs={"max_episode_steps": 8})
    new = record("MKV-v0", "random", 2, seed=1, env_kwargs={"max_episode_steps": 8})
    real = minari.create_dataset_from_buffers

    def interrupted(*args, **kwargs):
        real(*args, **kwargs)  # the files are written, then Ctrl-C
        raise KeyboardInterrupt

    monkeypatch.setattr(minari, "create_dataset_from_buffers", interrupted)
    with pytest.raises(KeyboardInterrupt):
        export_minari(new, "mkv/fresh-v0")
    assert _listing(store) == []
    monkeypatch.setattr(minari, "create_dataset_from_buffers", real)
    export_minari(old, "mkv/kept-v0")
    before = _listing(store)
    monkeypatch.setattr(minari, "create_dataset_from_buffers", interrupted)
    with pytest.raises(KeyboardInterrupt):
        export_minari(new, "mkv/kept-v0", overwrite=True)
    assert _listing(store) == before
    assert import_minari("mkv/kept-v0").equals(old)


def test_foreign_dataset_is_refused_in_one_line(store):
    from minari.data_collector import EpisodeBuffer

    env = make_env("MKV-v0")
    obs, _ = env.reset(seed=0)
    buf = EpisodeBuffer(id=0, seed=0, observations=np.stack([obs, obs]),
                        actions=np.zeros((1, 2), dtype=np.int64), rewards=[0.0],
                        terminations=[False], truncations=[True], infos={})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Minari's nudges for an author and a code link
        minari.create_dataset_from_buffers("other/foreign-v0", [buf], env=env.spec,
                                           algorithm_name="x", data_format="hdf5")
    env.close()
    with pytest.raises(MinariError, match="not written by mkv export"):
        import_minari("other/foreign-v0")


def test_without_the_extra_the_error_says_how_to_install(store, monkeypatch):
    data = record("MKV-v0", "random", 1, seed=0, env_kwargs={"max_episode_steps": 5})
    monkeypatch.setitem(sys.modules, "minari", None)  # import minari -> ImportError
    for call in (lambda: export_minari(data, "mkv/x-v0"), lambda: import_minari("mkv/x-v0")):
        with pytest.raises(MinariError, match=r"needs the minari extra \(pip install "
                                              r"'mkv-sfm\[minari\]'\)"):
            call()


# ------------------------------------------------------------------ nested ids, checksums
@pytest.mark.parametrize("bad", ["mkv/teacher-v0/inner-v0", "mkv/a-v12/b/x-v0", "mkv/v-v0/x-v1",
                                 "/".join(["ab"] * 2000) + "/x-v0",
                                 "/".join(["ab"] * 5) + "/x-v0", "mkv/" + "x" * 300 + "-v0"])
def test_nested_and_huge_ids_are_refused_in_one_line(store, bad):
    data = record("MKV-v0", "random", 1, seed=0, env_kwargs={"max_episode_steps": 5})
    for call in (lambda: export_minari(data, bad), lambda: import_minari(bad),
                 lambda: check_dataset_id(bad)):
        with pytest.raises(MinariError, match="bad Minari dataset id") as e:
            call()
        assert "\n" not in str(e.value) and len(str(e.value)) < 400
    assert not store.exists()


def test_a_dataset_is_never_written_inside_another(store):
    data = record("MKV-v0", "random", 1, seed=0, env_kwargs={"max_episode_steps": 5})
    export_minari(data, "mkv/teacher-v0")
    before = _listing(store)
    with pytest.raises(MinariError, match="has the form of a dataset"):
        export_minari(data, "mkv/teacher-v0/inner-v0")
    assert _listing(store) == before
    assert sorted(minari.list_local_datasets()) == ["mkv/teacher-v0"]


_SEG = st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_-]{0,6}", fullmatch=True)


@settings(max_examples=200, deadline=None)
@given(ns=st.lists(_SEG, min_size=1, max_size=7), name=_SEG,
       version=st.integers(0, 10**6))
def test_generated_ids_accepted_only_as_flat_minari_ids(ns, name, version):
    """Every accepted id is a Minari id (parse and generate give it back), no namespace folder
    of it has a dataset's NAME-vN form, and its namespace is at most 4 folders deep; every
    refusal is one line."""
    import re

    dataset_id = "/".join(ns) + f"/{name}-v{version}"
    try:
        assert check_dataset_id(dataset_id) == dataset_id
    except MinariError as e:
        assert "\n" not in str(e)
        nested = any(re.fullmatch(r".*-v[0-9]+", f) for f in ns)
        assert nested or len(ns) > 4 or len("/".join(ns)) < 2 or len(dataset_id) > 200, e
        return
    assert gen_dataset_id(*parse_dataset_id(dataset_id)) == dataset_id
    assert len(ns) <= 4 and not any(re.fullmatch(r".*-v[0-9]+", f) for f in ns)


def _rewrite_mkv_metadata(store, dataset_id, edit):
    import json

    with _store_env(store):
        ds_ = minari.load_dataset(dataset_id, download=False)
        meta = json.loads(ds_.storage.metadata["mkv_metadata"])
        edit(meta)
        ds_.storage.update_metadata({"mkv_metadata": json.dumps(meta, sort_keys=True)})


class _store_env:
    def __init__(self, store):
        self.store = str(store)

    def __enter__(self):
        self.old = os.environ.get("MINARI_DATASETS_PATH")
        os.environ["MINARI_DATASETS_PATH"] = self.store

    def __exit__(self, *exc):
        if self.old is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = self.old


def test_a_tampered_checksum_is_refused_not_recomputed(store):
    data = record("MKVJam-v0", "teacher", 2, seed=0, env_kwargs={"max_episode_steps": 12})
    export_minari(data, "mkv/sum-v0")
    assert import_minari("mkv/sum-v0").equals(data)  # the honest one still imports

    def tamper(meta):
        meta["content_sha256"] = "0" * 64
    _rewrite_mkv_metadata(store, "mkv/sum-v0", tamper)
    with pytest.raises(MinariError, match="do not match the content_sha256") as e:
        import_minari("mkv/sum-v0")
    assert "\n" not in str(e.value)

    def drop(meta):
        del meta["content_sha256"]
    _rewrite_mkv_metadata(store, "mkv/sum-v0", drop)
    with pytest.raises(MinariError, match="do not match the content_sha256"):
        import_minari("mkv/sum-v0")


def test_tampered_arrays_under_the_old_checksum_are_refused(store):
    import h5py

    data = record("MKVJam-v0", "teacher", 2, seed=0, env_kwargs={"max_episode_steps": 12})
    export_minari(data, "mkv/edit-v0")
    [path] = [os.path.join(d, f) for d, _, files in os.walk(store / "mkv" / "edit-v0")
              for f in files if f.endswith(".hdf5")]
    with h5py.File(path, "r+") as f:
        rewards = f["episode_0"]["rewards"]
        rewards[0] = rewards[0] + 1.0  # a plausible, finite, schema-valid edit
    with pytest.raises(MinariError, match="do not match the content_sha256") as e:
        import_minari("mkv/edit-v0")
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("member", ["data/main_data.hdf5", "data/metadata.json",
                                    "../namespace_metadata.json"])
def test_a_fifo_in_the_store_is_refused_at_once(store, member):
    import signal

    data = record("MKV-v0", "random", 1, seed=0, env_kwargs={"max_episode_steps": 5})
    export_minari(data, "mkv/pipe-v0")
    path = os.path.normpath(store / "mkv" / "pipe-v0" / member)
    os.remove(path)
    os.mkfifo(path)

    def blocked(*_):
        raise TimeoutError("import_minari waited on a FIFO")
    old = signal.signal(signal.SIGALRM, blocked)
    signal.alarm(20)
    try:
        with pytest.raises(MinariError, match="is not a regular file") as e:
            import_minari("mkv/pipe-v0")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    assert "\n" not in str(e.value) and path in str(e.value)
