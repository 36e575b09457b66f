"""Minari export and import: a round trip equal to the npz (observations, actions, rewards,
terminations, every info column, seeds, metadata), readable by plain Minari, offline."""

import numpy as np
import pytest

pytest.importorskip("minari", reason="the minari extra is not installed")

import minari  # noqa: E402

from mkv_env.minari_io import MinariError, export_minari, import_minari  # noqa: E402
from mkv_env.recorder import make_env, record  # noqa: E402


@pytest.fixture
def store(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    return tmp_path / "minari"


@pytest.mark.parametrize("env_id", ["MKVJam-v0", "MKV-v0"])
def test_round_trip_equals_the_dataset(store, env_id):
    data = record(env_id, "teacher", 3, 7, {"max_episode_steps": 40})
    export_minari(data, f"mkv/{env_id.lower()}-v0")
    back = import_minari(f"mkv/{env_id.lower()}-v0")
    assert back.equals(data)  # every array (dtype, shape, bytes) and the metadata
    assert ("escaped" in back) == (env_id == "MKVJam-v0")


def test_plain_minari_reads_it_and_rebuilds_the_env(store):
    data = record("MKVJam-v0", "teacher", 2, 0, {"max_episode_steps": 30})
    export_minari(data, "mkv/plain-v1")
    ds = minari.load_dataset("mkv/plain-v1", download=False)
    assert ds.total_episodes == 2 and ds.total_steps == data.n_steps
    ep = next(ds.iterate_episodes())
    n = int(data["episode_lengths"][0])
    assert ep.observations.shape == (n + 1, 10) and ep.actions.shape == (n, 2)
    np.testing.assert_array_equal(ep.infos["stuck"], data["stuck"][:n])
    env = ds.recover_environment()
    ref = make_env("MKVJam-v0")
    assert env.observation_space == ref.observation_space
    assert env.action_space == ref.action_space and env.spec.max_episode_steps == 30
    env.close()
    ref.close()


def test_bad_ids_existing_and_missing_datasets(store):
    data = record("MKVJam-v0", "random", 1, 0, {"max_episode_steps": 10})
    for bad in ("no-version", "mkv/x", "../up-v0", ""):
        with pytest.raises(MinariError, match="bad Minari dataset id"):
            export_minari(data, bad)
    export_minari(data, "mkv/once-v0")
    with pytest.raises(MinariError, match="exists"):
        export_minari(data, "mkv/once-v0")
    export_minari(data, "mkv/once-v0", overwrite=True)
    with pytest.raises(MinariError, match="no local Minari dataset"):
        import_minari("mkv/never-v0")


def test_the_commands(store, tmp_path, capsys):
    from mkv_env.dataset import load, save
    from sfm_learn.cli import main

    data = record("MKVJam-v0", "teacher", 2, 3, {"max_episode_steps": 20})
    save(data, tmp_path / "d.npz")
    assert main(["export", str(tmp_path / "d.npz"), "--minari", "mkv/cli-v0"]) == 0
    assert main(["import-minari", "mkv/cli-v0", "--out", str(tmp_path / "back.npz")]) == 0
    assert load(tmp_path / "back.npz").equals(data)
    capsys.readouterr()
    for argv in (["export", str(tmp_path / "d.npz"), "--minari", "bad"],
                 ["export", str(tmp_path / "d.npz"), "--minari", "mkv/cli-v0"],
                 ["import-minari", "mkv/none-v0", "--out", str(tmp_path / "x.npz")]):
        code = main(argv)
        err = capsys.readouterr().err
        assert code == 2 and err.count("\n") == 1, err
    assert not (tmp_path / "x.npz").exists()
