"""Sweep specs and sweep folders handed over by others (issue: trust, round two): one schema
validated before anything runs, damaged rows reported one line each, no hangs on FIFOs, outputs
never onto inputs."""

import json
import os
import shutil

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sfm_learn.cli import main
from sfm_learn.experiments import sweep

BASE = {
    "name": "tiny",
    "teacher_env": "MKV-v1",
    "env": ["MKVJam-v1"],
    "eval": {"episodes": 2, "seed": 4_100_000},
    "seeds": [0],
    "learners": {"sfm": {}},
    "budgets": {"sfm": [200]},
}


def _spec(**changes):
    spec = json.loads(json.dumps(BASE))
    spec.update(changes)
    return spec


@pytest.mark.parametrize("spec, match", [
    (_spec(seeds=[float("inf")]), "seeds must hold integers"),
    (_spec(seeds=[float("nan")]), "seeds must hold integers"),
    (_spec(budgets={"sfm": [float("inf")]}), "budgets.sfm must hold integers"),
    (_spec(eval={"episodes": float("inf"), "seed": 1}), "eval.episodes"),
    (_spec(learners={"..": {}}, budgets={"..": [200]}), "names are letters"),
    (_spec(learners={".hidden": {}}, budgets={".hidden": [200]}), "names are letters"),
    (_spec(learners={"a/b": {}}, budgets={"a/b": [200]}), "names are letters"),
    (_spec(learners={"sfm__x": {}}, budgets={"sfm__x": [200]}), "no '__'"),
    (_spec(learners={"bc": {"epochs": -1}}, budgets={"bc": [200]}), "epochs must be"),
    (_spec(learners={"bc": {"epochs": 2.5}}, budgets={"bc": [200]}), "epochs must be"),
    (_spec(learners={"dagger": {"rounds": 0}}, budgets={"dagger": [200]}), "rounds must be"),
    (_spec(learners={"sfm": {"preset": "nope"}}), "preset must be"),
    (_spec(env=["CartPole-v1"]), "not an MK-V env id"),
    (_spec(teacher_env="LunarLander-v3"), "not an MK-V env id"),
    (_spec(learners={"ppo": {"env": ["MKV-v1"]}}, budgets={"ppo": [200]}), "env must be one"),
    (_spec(name={"a": 1}), "name must be"),
])
def test_bad_specs_are_refused_in_one_line(spec, match):
    with pytest.raises(sweep.SpecError, match=match) as e:
        sweep.check_spec(spec)
    assert "\n" not in str(e.value)


def test_spec_files_with_infinities_or_deep_nesting_are_one_line_errors(tmp_path):
    p = tmp_path / "inf.json"
    p.write_text(json.dumps(BASE).replace("[0]", "[Infinity]"))
    with pytest.raises(sweep.SpecError, match="seeds"):
        sweep.load_spec(str(p))
    p = tmp_path / "inf.yml"
    p.write_text("env: [MKVJam-v1]\nseeds: [.inf]\nlearners: {sfm: {}}\nbudgets: {sfm: [200]}\n")
    with pytest.raises(sweep.SpecError, match="seeds"):
        sweep.load_spec(str(p))
    p = tmp_path / "deep.json"
    p.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(sweep.SpecError, match="nested too deeply"):
        sweep.load_spec(str(p))


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
@pytest.mark.parametrize("name", ["spec.json", "spec.yml"])
def test_a_fifo_as_spec_is_refused_at_once(tmp_path, capsys, name):
    fifo = tmp_path / name
    os.mkfifo(fifo)
    assert main(["sweep", str(fifo), "--out", str(tmp_path / "out")]) == 2
    assert "not a regular file" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


_json = st.recursive(
    st.none() | st.booleans() | st.integers(-10**15, 10**15)
    | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=12),
    lambda kids: st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=8), kids,
                                                               max_size=4),
    max_leaves=12)


@settings(max_examples=300, deadline=None)
@given(field=st.sampled_from(["name", "env", "teacher_env", "eval", "seeds", "learners",
                              "budgets"]), value=_json)
def test_any_value_in_any_field_is_a_spec_or_a_one_line_error(field, value):
    spec = _spec(**{field: value})
    try:
        out = sweep.check_spec(spec)
    except sweep.SpecError as e:
        assert "\n" not in str(e)
    else:
        assert sweep.plan(out)


@settings(max_examples=200, deadline=None)
@given(name=st.text(max_size=10), opts=_json)
def test_any_learner_name_and_options_are_a_spec_or_a_one_line_error(name, opts):
    spec = _spec(learners={name: opts}, budgets={name: [200]})
    try:
        out = sweep.check_spec(spec)
    except sweep.SpecError as e:
        assert "\n" not in str(e)
    else:
        assert sweep.LEARNER_NAME.fullmatch(name) and all(
            os.path.basename(n) == n and not n.startswith(".")
            for job in sweep.plan(out) for n in job.names)


@pytest.fixture(scope="module")
def done(tmp_path_factory):
    d = tmp_path_factory.mktemp("sweep") / "done"
    sweep.run_sweep(sweep.check_spec(BASE), str(d))
    return d


@pytest.mark.parametrize("content, why", [
    ({"learner": "sfm", "seed": 0, "budget": 300, "status": "ok", "metrics": "abc"},
     "status ok without"),
    ([1, 2, 3], "not a JSON object"),
    ({"seed": 0, "budget": 300, "status": "ok", "metrics": {}}, "no learner"),
    ({"learner": "sfm", "seed": 0, "budget": 300, "status": "ok"}, "status ok without"),
    ({"learner": "sfm", "seed": 0, "budget": 300, "status": "weird"}, "neither"),
])
def test_summary_and_resume_report_damaged_rows_in_one_line_each(done, tmp_path, capsys,
                                                                  content, why):
    d = tmp_path / "copy"
    shutil.copytree(done, d)
    (d / "rows" / "sfm__s9__b300.json").write_text(json.dumps(content))
    assert main(["sweep", "--summary", str(d)]) == 0
    out = capsys.readouterr().out
    lines = [line for line in out.splitlines() if line.startswith("damaged row")]
    assert len(lines) == 1 and why in lines[0] and "sfm__s9__b300.json" in lines[0]
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps(BASE))
    assert main(["sweep", str(spec), "--out", str(d), "--quiet"]) == 0
    assert "damaged row sfm__s9__b300.json" in capsys.readouterr().out


def test_summary_plot_never_overwrites_an_input(done, tmp_path, capsys):
    d = tmp_path / "copy"
    shutil.copytree(done, d)
    user_spec = tmp_path / "my_spec.yml"
    user_spec.write_text("env: [MKVJam-v1]\n")
    row = next((d / "rows").iterdir())
    data = next((d / "data").iterdir())
    for target in (d / "spec.json", row, data, user_spec):
        before = target.read_bytes()
        assert main(["sweep", "--summary", str(d), "--plot", str(target)]) == 2
        assert target.read_bytes() == before
    capsys.readouterr()
    assert main(["sweep", "--summary", str(d), "--plot", str(tmp_path / "c.png")]) == 0


def test_address_rules_are_the_same_as_eval(tmp_path, capsys):
    spec = tmp_path / "s.json"
    spec.write_text(json.dumps(BASE))
    assert main(["sweep", str(spec), "--out", str(tmp_path / "o"), "--address", "h:1"]) == 2
    assert "--address needs --backend ray" in capsys.readouterr().err
    assert main(["sweep", str(spec), "--out", str(tmp_path / "o"), "--backend", "ray",
                 "--address", ""]) == 2
    assert "--address is empty" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_a_sweep_refused_for_its_ray_address_writes_nothing(tmp_path, capsys):
    pytest.importorskip("ray")
    spec = tmp_path / "s.json"
    spec.write_text(json.dumps(BASE))
    out = tmp_path / "o"
    assert main(["sweep", str(spec), "--out", str(out), "--backend", "ray",
                 "--address", "127.0.0.1:9"]) == 2
    assert "cannot reach" in capsys.readouterr().err
    assert not out.exists()


def test_eval_workers_beyond_local_cpus_are_for_ray(capsys):
    from sfm_learn.cli.eval import MAX_RAY_WORKERS, max_workers

    assert main(["eval", "--env", "MKV-v0", "--policy", "random", "--episodes", "1",
                 "--workers", str(max_workers() + 1)]) == 2
    err = capsys.readouterr().err
    assert "4 per CPU" in err and "--backend ray" in err and err.count("\n") == 1
    assert main(["eval", "--env", "MKV-v0", "--policy", "random", "--episodes", "1",
                 "--workers", str(MAX_RAY_WORKERS + 1), "--backend", "ray"]) == 2


def test_a_cluster_token_at_hand_switches_on_token_auth(monkeypatch, tmp_path):
    """Clusters started by `ray start --head` want token auth; with the token in
    ~/.ray/auth_token (or RAY_AUTH_TOKEN) the driver uses it, unless the user chose a mode."""
    from sfm_learn.evaluation.ray_eval import use_cluster_token

    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.delenv("RAY_AUTH_MODE", raising=False)
    monkeypatch.delenv("RAY_AUTH_TOKEN", raising=False)
    use_cluster_token()
    assert "RAY_AUTH_MODE" not in os.environ  # no token: nothing changes
    (tmp_path / ".ray").mkdir()
    (tmp_path / ".ray" / "auth_token").write_text("t")
    use_cluster_token()
    assert os.environ["RAY_AUTH_MODE"] == "token"
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    use_cluster_token()
    assert os.environ["RAY_AUTH_MODE"] == "disabled"  # the user's choice stands
