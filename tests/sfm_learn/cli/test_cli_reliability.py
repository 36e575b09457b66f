"""Bad input through the ``mkv`` commands: one line, exit 2, no traceback, no file changed."""

import hashlib
import os

import numpy as np
import pytest

from sfm_learn.cli import main
from sfm_learn.eigenspace.policy import fit_policy


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def digest(path):
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


@pytest.fixture(scope="module")
def files(tmp_path_factory, small_train):
    from mkv_env.dataset import save

    d = tmp_path_factory.mktemp("reliability")
    data = d / "data.npz"
    save(small_train, data)
    policy = fit_policy(small_train).save(d / "policy.npz")
    return {"data": str(data), "policy": str(policy), "dir": d}


CASES = [
    ("fit {data} --out {data}", "also an input"),
    ("compare {data} {policy} --plot {dir}/f.png --spectrum {dir}/f.png", "two outputs"),
    ("train-bc {data} --out {data}", "also an input"),
    ("compare {data} {policy} --json {data}", "also an input"),
    ("compare {data} {policy} --json {dir}/same.png --plot {dir}/same.png", "two outputs"),
    ("eval --env MKVJam-v0 --policy sfm:{policy} --episodes 1 --json {policy}", "also an input"),
    ("eval --env MKVJam-v0 --policy teacher --episodes 1 --json {dir}/e.png --plot {dir}/e.png",
     "two outputs"),
    ("record --env MKV-v0 --policy sfm:{policy} --episodes 1 --out {policy}", "also an input"),
    ("record --env MKV-v0 --policy teacher --episodes 1 --out /dev/null", "not a regular file"),
    ("record --env MKV-v0 --policy teacher --episodes 99999999999999999999999 --out {dir}/x.npz",
     "at most"),
    ("train-ppo --env MKV-v0 --timesteps 100000000000000000000 --out {dir}/p.zip", "at most"),
    ("fit {data} --out {dir}/p.npz --history 100000", "history must be an int in [0, 1000]"),
    ("fit {data} --out {dir}/p.npz --history 1000 --traces 0.5,0.6", "feature columns"),
]


@pytest.mark.parametrize("line, message", CASES)
def test_bad_input_is_one_line_and_changes_nothing(files, capsys, line, message):
    before = {p: digest(files["dir"] / p) for p in os.listdir(files["dir"])}
    argv = line.format(**files).split()
    code, _, err = run(capsys, *argv)
    assert code == 2 and err.count("\n") == 1 and message in err, err
    assert "Traceback" not in err
    after = {p: digest(files["dir"] / p) for p in os.listdir(files["dir"])}
    assert after == before


def test_a_library_call_raises_value_error_not_cli_error(small_train):
    """bc.train called from a notebook raises ValueError (one line), never the CLI's error."""
    from sfm_learn.baselines import bc
    from sfm_learn.cli.common import CliError

    with pytest.raises(ValueError) as e:
        bc.train(small_train, epochs=1, held_out=0.0, features="fancy")
    assert not isinstance(e.value, CliError) and "\n" not in str(e.value)


def test_demo_interrupted_leaves_the_previous_output_untouched(tmp_path, capsys, monkeypatch):
    pytest.importorskip("stable_baselines3")
    out = tmp_path / "demo"
    out.mkdir()
    (out / "report.md").write_text("the previous report\n")
    from sfm_learn.cli import demo

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(demo, "_evaluate", interrupted)
    code, _, err = run(capsys, "demo", "--quick", "--quiet", "--skip-calib", "--out", out)
    assert code == 130 and "interrupted" in err
    assert os.listdir(out) == ["report.md"]
    assert (out / "report.md").read_text() == "the previous report\n"
    assert sorted(os.listdir(tmp_path)) == ["demo"]  # no temporary folder left


@pytest.mark.parametrize("value", [np.nan, np.inf, 3e38])
def test_datasets_with_impossible_readings_are_refused_by_every_command(
        tmp_path, capsys, small_train, files, value):
    import json
    import zipfile

    from mkv_env.dataset import _write_entry, content_sha256

    arrays = {k: v.copy() for k, v in small_train.arrays.items()}
    arrays["observations"][5, 2] = value
    meta = dict(small_train.metadata, content_sha256=content_sha256(arrays))
    bad = tmp_path / "bad.npz"
    with zipfile.ZipFile(bad, "w") as zf:
        _write_entry(zf, "metadata", np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8))
        for key, a in arrays.items():
            _write_entry(zf, key, a)
    for argv in (["fit", bad, "--out", tmp_path / "p.npz"],
                 ["train-bc", bad, "--out", tmp_path / "b.zip"],
                 ["compare", bad, files["policy"]]):
        code, _, err = run(capsys, *argv)
        assert code == 2 and err.count("\n") == 1 and "finite" in err, err
    assert sorted(os.listdir(tmp_path)) == ["bad.npz"]


def test_a_fifo_as_an_input_file_is_refused_without_waiting(tmp_path, capsys, files):
    fifo = tmp_path / "pipe.npz"
    os.mkfifo(fifo)
    for argv in (["fit", fifo, "--out", tmp_path / "p.npz"],
                 ["compare", files["data"], fifo],
                 ["eval", "--env", "MKVJam-v0", "--policy", f"bc:{fifo}", "--episodes", "1"]):
        code, _, err = run(capsys, *argv)
        assert code == 2 and "not a regular file" in err and err.count("\n") == 1, err
