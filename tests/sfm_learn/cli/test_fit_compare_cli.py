"""``mkv fit`` and ``mkv compare``: outputs, plots, and one-line errors."""

import json

import numpy as np
import pytest

from sfm_learn.cli import main
from sfm_learn.eigenspace.policy import SfMPolicy


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def fitted(tmp_path_factory, data_files):
    train, _ = data_files
    out = tmp_path_factory.mktemp("fit") / "policy.npz"
    assert main(["fit", str(train), "--out", str(out)]) == 0
    return out


def test_fit_reports_rank_and_spectrum_and_writes_a_loadable_policy(capsys, tmp_path,
                                                                    data_files):
    train, _ = data_files
    out, spec = tmp_path / "p.npz", tmp_path / "spectrum.png"
    code, text, err = run(capsys, "fit", train, "--out", out, "--spectrum", spec)
    assert code == 0, err
    p = SfMPolicy.load(out)
    assert f"chosen rank n = {p.n_components} of {p.projector.n_features_in_}" in text
    assert "<- n (largest ratio above the floor)" in text
    for s in p.projector.singular_values_[:3]:
        assert f"{s:11.4g}" in text
    assert spec.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_fit_options_change_the_model(capsys, tmp_path, data_files):
    train, _ = data_files
    out = tmp_path / "p.npz"
    code, text, err = run(capsys, "fit", train, "--out", out, "--features", "raw",
                          "--history", "2", "--rank", "4", "--solver", "lstsq",
                          "--thresholds", "fixed")
    assert code == 0, err
    p = SfMPolicy.load(out)
    assert p.n_components == 4 and p.feature_spec.history == 2
    assert p.feature_spec.trace_decays == () and p.feature_spec.prev_action == "none"
    assert p.projector.solver == "lstsq"
    np.testing.assert_array_equal(p.thresholds, [[-0.5, 0.5], [-0.5, 0.5]])
    assert "(given)" in text


def test_compare_prints_metrics_and_writes_figure3_spectrum_and_json(capsys, tmp_path, fitted,
                                                                     data_files):
    _, held = data_files
    fig, js = tmp_path / "fig3.png", tmp_path / "cmp.json"
    code, text, err = run(capsys, "compare", held, fitted, "--plot", fig, "--json", js)
    assert code == 0, err
    doc = json.loads(js.read_text())
    assert set(doc["modes"]) == {"teacher_forced", "free_running"}
    assert set(doc["baselines"]) == {"copy_previous", "constant"}
    keys = set(doc["modes"]["free_running"])
    assert all(set(m) == keys for m in [*doc["modes"].values(), *doc["baselines"].values()])
    m = doc["modes"]["free_running"]
    assert f"{m['drive']:.3f}" in text and f"{m['steer_timing']:.3f}" in text
    assert "free-running" in text and "copy previous" in text
    assert 0.0 <= m["drive"] <= 1.0 and doc["baselines"]["constant"]["drive"] > 0
    assert m["onsets"] >= 1 and len(m["ci"]["onset_hit_w2"]) == 2
    assert len(doc["episodes"]) == 3 and not doc["in_sample"]
    assert "WARNING" not in text
    for png in (fig, tmp_path / "fig3_spectrum.png"):
        assert png.read_bytes()[:4] == b"\x89PNG"


def test_compare_on_the_training_data_warns_in_sample(capsys, fitted, data_files):
    train, _ = data_files
    code, text, err = run(capsys, "compare", train, fitted)
    assert code == 0 and "in-sample" in text


@pytest.mark.parametrize("argv, message", [
    (["fit", "{missing}", "--out", "{tmp}/p.npz"], "does not exist"),
    (["fit", "{train}", "--out", "{tmp}/p.txt"], "must end in .npz"),
    (["fit", "{train}", "--out", "{tmp}/nodir/p.npz"], "does not exist"),
    (["fit", "{train}", "--out", "{tmp}/p.npz", "--rank", "0"], "--rank must be in"),
    (["fit", "{train}", "--out", "{tmp}/p.npz", "--traces", "0.5,1.5"], "decays must be in"),
    (["fit", "{train}", "--out", "{tmp}/p.npz", "--spectrum", "{tmp}/s.pdf"], "must end in .png"),
    (["compare", "{held}", "{train}"], "not an SfM policy file"),
    (["compare", "{held}", "{missing}"], "does not exist"),
    (["compare", "{held}", "{policy}", "--episode", "7", "--plot", "{tmp}/f.png"],
     "out of range"),
    (["eval", "--env", "MKVJam-v0", "--policy", "sfm:{missing}", "--episodes", "1"],
     "does not exist"),
    (["eval", "--env", "MKVJam-v0", "--policy", "sfm:", "--episodes", "1"], "needs a path"),
])
def test_bad_input_is_one_line_exit_2_and_no_output(capsys, tmp_path, data_files, fitted,
                                                    argv, message):
    train, held = data_files
    fill = dict(missing=tmp_path / "missing.npz", tmp=tmp_path, train=train, held=held,
                policy=fitted)
    code, out, err = run(capsys, *[a.format(**fill) for a in argv])
    assert code == 2
    assert message in err and err.count("\n") == 1, err
    assert not (tmp_path / "p.npz").exists() and not (tmp_path / "f.png").exists()


def test_sfm_spec_evaluates_through_mkv_eval(capsys, fitted):
    code, text, err = run(capsys, "eval", "--env", "MKVJam-v0", "--policy", f"sfm:{fitted}",
                          "--episodes", "2", "--seed", "3", "--quiet")
    assert code == 0, err
    assert "escape rate" in text


@pytest.mark.parametrize("steps, episodes, options, columns, need", [
    (2, 1, [], "32 features + 2 command columns", 35),         # the 2-step dataset
    (34, 1, [], "32 features + 2 command columns", 35),        # one row short
    (2, 2, ["--preset", "paper"], "10 features + 2 command columns", 13),
    (12, 1, ["--features", "raw"], "10 features + 2 command columns", 13),
    (38, 1, ["--encoding", "onehot"], "32 features + 6 command columns", 39),
    (5, 1, ["--history", "1"], "42 features + 2 command columns", 45),
])
def test_fit_refuses_fewer_rows_than_a_stacked_row_has_columns_plus_one(
        capsys, tmp_path, tiny_data, steps, episodes, options, columns, need):
    data = tiny_data(steps, episodes)
    out, png = tmp_path / "p.npz", tmp_path / "s.png"
    code, text, err = run(capsys, "fit", data, "--out", out, "--spectrum", png, *options)
    assert code == 2 and text == ""
    assert err.count("\n") == 1 and err.startswith("mkv fit: error: ")
    assert (f"dataset {data} has {steps * episodes} rows; an SfM fit of {columns} needs at "
            f"least {need}") in err
    assert not out.exists() and not png.exists() and list(tmp_path.iterdir()) == []


def test_fit_counts_the_rows_of_every_dataset_together(capsys, tmp_path, tiny_data):
    a, b = tiny_data(2), tiny_data(2, 2)
    code, _, err = run(capsys, "fit", a, b, "--out", tmp_path / "p.npz")
    assert code == 2 and f"datasets {a}, {b} (together) have 6 rows" in err
    assert not (tmp_path / "p.npz").exists()
    # 20 + 15 = 35 rows: enough together, though neither is alone
    code, text, err = run(capsys, "fit", tiny_data(20), tiny_data(15), "--out",
                          tmp_path / "p.npz")
    assert code == 0, err
    assert SfMPolicy.load(tmp_path / "p.npz").training["rows"] == 35


@pytest.mark.parametrize("options, need", [([], 35), (["--preset", "paper"], 13)])
def test_fit_accepts_the_smallest_identifiable_dataset(capsys, tmp_path, tiny_data, options,
                                                       need):
    out = tmp_path / "p.npz"
    code, text, err = run(capsys, "fit", tiny_data(need), "--out", out, *options)
    assert code == 0, err
    p = SfMPolicy.load(out)
    assert p.training["rows"] == need and f"fitted on {need} steps" in text
    # every one of the stacked row's columns gets a singular value: the full spectrum
    assert p.projector.singular_values_.size == p.projector.n_features_in_ == need - 1
