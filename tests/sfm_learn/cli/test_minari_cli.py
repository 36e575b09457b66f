"""``mkv export DATA.npz --minari ID`` and ``mkv import-minari ID --out DATA.npz``: the round trip
through the commands, and one line with exit status 2 for every user mistake."""

import os
import sys

import pytest

pytest.importorskip("minari", reason="the minari extra is not installed "
                                      "(pip install 'mkv-sfm[minari]')")

from mkv_env.dataset import load, save  # noqa: E402
from mkv_env.recorder import record  # noqa: E402
from sfm_learn.cli import main  # noqa: E402

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")


@pytest.fixture
def store(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    return tmp_path / "minari"


@pytest.fixture
def npz(tmp_path):
    data = record("MKVJam-v0", "teacher", 2, seed=3, env_kwargs={"max_episode_steps": 20})
    save(data, tmp_path / "d.npz")
    return tmp_path / "d.npz", data


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_export_and_import_round_trip(store, npz, tmp_path, capsys):
    path, data = npz
    code, out, err = run(capsys, "export", path, "--minari", "mkv/cli-v0")
    assert code == 0, err
    assert out == f"wrote Minari dataset mkv/cli-v0: 2 episodes, {data.n_steps} steps\n"
    assert (store / "mkv" / "cli-v0" / "data").is_dir()
    back = tmp_path / "back.npz"
    code, out, err = run(capsys, "import-minari", "mkv/cli-v0", "--out", back)
    assert code == 0, err
    assert out == f"wrote {back}: 2 episodes, {data.n_steps} steps\n"
    assert load(back).equals(data)
    assert back.read_bytes() == path.read_bytes()  # the same deterministic file
    assert oct(back.stat().st_mode & 0o777) == oct(path.stat().st_mode & 0o777)


def test_data_path_option_and_overwrite(store, npz, tmp_path, capsys):
    path, data = npz
    other = tmp_path / "other"
    assert run(capsys, "export", path, "--minari", "mkv/dp-v0", "--data-path", other)[0] == 0
    assert (other / "mkv" / "dp-v0" / "data").is_dir() and not store.exists()
    code, _, err = run(capsys, "export", path, "--minari", "mkv/dp-v0", "--data-path", other)
    assert code == 2 and "exists" in err and "--overwrite" in err
    assert run(capsys, "export", path, "--minari", "mkv/dp-v0", "--data-path", other,
               "--overwrite")[0] == 0
    out = tmp_path / "back.npz"
    out.write_bytes(b"old")  # replaced as a whole
    assert run(capsys, "import-minari", "mkv/dp-v0", "--out", out, "--data-path", other)[0] == 0
    assert load(out).equals(data)


@pytest.mark.parametrize("argv, says", [
    (["export", "{npz}", "--minari", "bad"], "bad Minari dataset id 'bad'"),
    (["export", "{npz}", "--minari", "a/x-v0"], "bad Minari dataset id"),
    (["export", "{npz}", "--minari", "mkv/exists-v0"], "exists"),
    (["export", "{npz}", "--minari", "mkv/exists-v0/inner-v0"], "has the form of a dataset"),
    (["export", "{npz}", "--minari", "/".join(["ab"] * 2000) + "/x-v0"],
     "bad Minari dataset id"),
    (["import-minari", "mkv/exists-v0/inner-v0", "--out", "{tmp}/x.npz"],
     "has the form of a dataset"),
    (["export", "{tmp}/none.npz", "--minari", "mkv/x-v0"], "does not exist"),
    (["export", "{npz}"], "--minari"),
    (["import-minari", "mkv/none-v0", "--out", "{tmp}/x.npz"], "no local Minari dataset"),
    (["import-minari", "bad-id", "--out", "{tmp}/x.npz"], "bad Minari dataset id"),
    (["import-minari", "mkv/exists-v0", "--out", "{tmp}/nodir/x.npz"], "does not exist"),
    (["import-minari", "mkv/exists-v0", "--out", "{tmp}"], "is a directory"),
    (["import-minari", "mkv/exists-v0", "--out", "{tmp}/x.npz", "--data-path", "{npz}"],
     "not a directory"),
])
def test_mistakes_are_one_line_with_exit_2(store, npz, tmp_path, capsys, argv, says):
    path, _ = npz
    assert run(capsys, "export", path, "--minari", "mkv/exists-v0")[0] == 0
    argv = [a.format(npz=path, tmp=tmp_path) for a in argv]
    code, out, err = run(capsys, *argv)
    assert code == 2 and err.count("\n") == 1 and says in err, err
    assert err.startswith(f"mkv {argv[0]}: error: ")
    assert not (tmp_path / "x.npz").exists()
    assert sorted(os.listdir(store)) == ["mkv"]
    assert sorted(os.listdir(store / "mkv")) == ["exists-v0", "namespace_metadata.json"]


def test_without_the_extra_the_commands_say_how_to_install(store, npz, tmp_path, capsys,
                                                           monkeypatch):
    path, _ = npz
    monkeypatch.setitem(sys.modules, "minari", None)  # import minari -> ImportError
    for argv in (["export", path, "--minari", "mkv/x-v0"],
                 ["import-minari", "mkv/x-v0", "--out", tmp_path / "x.npz"]):
        code, _, err = run(capsys, *argv)
        assert code == 2 and err.count("\n") == 1, err
        assert "needs the minari extra (pip install 'mkv-sfm[minari]')" in err
    assert not (tmp_path / "x.npz").exists() and not store.exists()


def test_import_refuses_a_tampered_checksum(store, npz, tmp_path, capsys):
    import json

    import minari

    path, data = npz
    assert run(capsys, "export", path, "--minari", "mkv/sum-v0")[0] == 0
    dataset = minari.load_dataset("mkv/sum-v0", download=False)
    meta = json.loads(dataset.storage.metadata["mkv_metadata"])
    meta["content_sha256"] = "f" * 64
    dataset.storage.update_metadata({"mkv_metadata": json.dumps(meta, sort_keys=True)})
    out = tmp_path / "back.npz"
    code, _, err = run(capsys, "import-minari", "mkv/sum-v0", "--out", out)
    assert code == 2 and err.count("\n") == 1 and "content_sha256" in err, err
    assert err.startswith("mkv import-minari: error: ") and not out.exists()
