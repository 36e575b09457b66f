"""``mkv sweep``: spec checks, resumable rows, failing jobs, summary."""

import json
import os

import pytest

from sfm_learn.cli import main
from sfm_learn.experiments import sweep
from sfm_learn.experiments.summary import aggregate, t_interval

SPEC = {
    "name": "tiny",
    "teacher_env": "MKV-v1",
    "env": ["MKVJam-v1"],
    "eval": {"episodes": 2, "seed": 4_100_000},
    "seeds": [0, 1],
    "learners": {"sfm": {}, "sfm-paper": {"preset": "paper"}},
    "budgets": {"sfm": [200, 400], "sfm-paper": [300]},
}
VOLATILE = ("wall_s", "train_s", "policy", "_file")


def stable(rows):
    return sorted(json.dumps({k: v for k, v in r.items() if k not in VOLATILE}, sort_keys=True)
                   for r in rows)


def write_spec(tmp_path, spec, name="spec.json"):
    p = tmp_path / name
    p.write_text(json.dumps(spec))
    return str(p)


@pytest.fixture(scope="module")
def full(tmp_path_factory):
    d = tmp_path_factory.mktemp("sweep") / "full"
    counts = sweep.run_sweep(sweep.check_spec(SPEC), str(d))
    assert counts == {"jobs": 6, "skipped": 0, "ok": 6, "error": 0}
    return d


def test_rows_one_per_job_with_metrics(full):
    rows = sweep.read_rows(str(full))
    assert sorted(r["_file"] for r in rows) == sorted(
        sweep.row_name(n, s, b) for n, bs in SPEC["budgets"].items() for s in (0, 1) for b in bs)
    for r in rows:
        assert r["status"] == "ok" and r["budget_unit"] == "teacher_steps"
        assert r["steps"] == r["budget"]                      # the teacher ran exactly the budget
        m = r["metrics"]["MKVJam-v1"]
        assert 0.0 <= m["escape_rate"] <= 1.0 and m["distance_m"] >= 0


def test_interrupted_sweep_resumes_to_the_same_rows(full, tmp_path):
    spec = sweep.check_spec(SPEC)
    d = tmp_path / "resumed"
    seen = []

    def stop_after_two(job, rows):
        seen.append(job)
        if len(seen) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        sweep.run_sweep(spec, str(d), on_job=stop_after_two)
    assert len(sweep.read_rows(str(d))) == 2
    assert len(sweep.pending(spec, str(d))) == 4
    counts = sweep.run_sweep(spec, str(d))
    assert counts == {"jobs": 6, "skipped": 2, "ok": 4, "error": 0}
    assert stable(sweep.read_rows(str(d))) == stable(sweep.read_rows(str(full)))
    # a third run has nothing left to do
    assert sweep.run_sweep(spec, str(d))["skipped"] == 6


def test_failing_job_is_reported_and_the_others_finish(tmp_path, capsys, monkeypatch):
    # a budget too small is refused before the sweep starts (below), so the failure here is a
    # job that raises midway: DAgger's training, on a budget it could identify
    from sfm_learn.baselines import dagger

    def broken(*args, **kwargs):
        raise RuntimeError("the teacher env lost its battery")

    monkeypatch.setattr(dagger, "train", broken)
    spec = dict(SPEC, learners={"sfm": {}, "dagger-bad": {"rounds": 1}},
                budgets={"sfm": [200], "dagger-bad": [50]})
    d = tmp_path / "out"
    code = main(["sweep", write_spec(tmp_path, spec), "--out", str(d), "--quiet"])
    out, err = capsys.readouterr()
    assert code == 1
    assert "4 jobs: 0 already done, 2 ran, 2 failed" in out
    rows = {r["_file"]: r for r in sweep.read_rows(str(d))}
    bad = rows[sweep.row_name("dagger-bad", 0, 50)]
    assert bad["status"] == "error" and "lost its battery" in bad["error"]
    assert rows[sweep.row_name("sfm", 1, 200)]["status"] == "ok"
    # a rerun retries only the failed jobs
    assert main(["sweep", write_spec(tmp_path, spec), "--out", str(d), "--quiet"]) == 1
    assert "4 jobs: 2 already done, 0 ran, 2 failed" in capsys.readouterr().out


def test_a_ctrl_c_python_wrapped_is_not_a_failed_job(tmp_path, capsys, monkeypatch):
    """A Ctrl-C inside an extension's initialisation arrives as ImportError("initialization
    failed") whose cause is the KeyboardInterrupt: the sweep stops (exit 130), it does not write
    the job as failed (which a rerun would then retry as an error, not resume)."""
    from sfm_learn.baselines import dagger

    def interrupted(*args, **kwargs):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as ki:
            raise ImportError("initialization failed") from ki

    monkeypatch.setattr(dagger, "train", interrupted)
    spec = dict(SPEC, learners={"dagger": {"rounds": 1}}, budgets={"dagger": [50]})
    d = tmp_path / "out"
    assert main(["sweep", write_spec(tmp_path, spec), "--out", str(d), "--quiet"]) == 130
    assert capsys.readouterr().err.strip().splitlines() == [
        "mkv sweep: interrupted; no output written"]
    assert sweep.read_rows(str(d)) == []


def test_local_pool_of_two_workers_writes_the_same_rows(full, tmp_path):
    d = tmp_path / "pool"
    sweep.run_sweep(sweep.check_spec(SPEC), str(d), workers=2)
    assert stable(sweep.read_rows(str(d))) == stable(sweep.read_rows(str(full)))


def test_summary_prints_tables_and_draws_curves(full, capsys, tmp_path):
    pytest.importorskip("matplotlib")
    png = tmp_path / "c.png"
    assert main(["sweep", "--summary", str(full), "--plot", str(png)]) == 0
    out = capsys.readouterr().out
    assert "escape rate on **MKVJam-v1**" in out and "| sfm | 400 | 400 | teacher steps |" in out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_t_interval_and_aggregate():
    m, lo, hi = t_interval([1.0, 2.0, 3.0])
    assert m == 2.0 and lo == pytest.approx(2 - 4.302653 / 3 ** 0.5, rel=1e-5)
    rows = [{"status": "ok", "learner": "a", "budget": 10, "steps": 10,
             "metrics": {"E": {"escape_rate": v}}} for v in (0.0, 1.0)]
    pts = aggregate(rows + [{"status": "error", "learner": "a", "budget": 10}])
    (b, steps, mean, lo, hi, n), = pts["curves"][("a", "E", "escape_rate")]
    assert (b, n, mean, lo, hi) == (10, 2, 0.5, 0.0, 1.0)      # clipped to [0, 1]
    assert len(pts["errors"]) == 1


@pytest.mark.parametrize("change, message", [
    ({"seeds": []}, "seeds must be a non-empty list"),
    ({"seeds": [1, 1]}, "repeated"),
    ({"learners": {"xgb": {}}, "budgets": {"xgb": [10]}}, "unknown kind 'xgb'"),
    ({"budgets": {"sfm": [200]}}, "budgets lacks learner 'sfm-paper'"),
    ({"learners": {"sfm": {"epochs": 3}}, "budgets": {"sfm": [10]}}, "unknown option"),
    ({"colour": 1}, "unknown sweep spec key"),
    ({"learners": {"sfm": {"min_support": -1}}, "budgets": {"sfm": [10]}},
     "min_support must be an integer in [0, 10000000]"),
    ({"learners": {"bc": {"min_updates": "many"}}, "budgets": {"bc": [10]}},
     "min_updates must be an integer in [0, 10000000]"),
    ({"learners": {"sfm": {"min_updates": 5}}, "budgets": {"sfm": [10]}}, "unknown option"),
    ({"eval": {"episodes": 0}}, "eval.episodes"),
    ({"eval": {"episodes": 2, "seed": 1, "banks": 0}}, "eval.banks"),
    ({"eval": {"episodes": 2, "seed": 1, "banks": 21}}, "eval.banks"),
    ({"eval": {"episodes": 2, "seed": 1, "banks": "three"}}, "eval.banks"),
    ({"eval": {"episodes": 2, "seed": 1, "bank": 2}}, "optionally 'banks'"),
    ({"env": "Nope-v9"}, "Nope-v9"),
])
def test_bad_specs_are_one_line_errors(tmp_path, capsys, change, message):
    spec = dict(SPEC, **change)
    d = tmp_path / "o"
    assert main(["sweep", write_spec(tmp_path, spec), "--out", str(d), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not d.exists()


def test_unreadable_spec_files(tmp_path, capsys):
    bad = tmp_path / "s.yml"
    bad.write_text("learners: [")
    for path, message in ((str(bad), "not valid YAML"), (str(tmp_path / "none.json"),
                                                          "cannot read sweep spec")):
        assert main(["sweep", path, "--out", str(tmp_path / "o"), "--quiet"]) == 2
        assert message in capsys.readouterr().err


def test_another_spec_in_the_same_directory_is_refused(full, tmp_path, capsys):
    spec = dict(SPEC, seeds=[7])
    assert main(["sweep", write_spec(tmp_path, spec), "--out", str(full), "--quiet"]) == 2
    assert "holds a sweep of another spec" in capsys.readouterr().err


def test_summary_of_a_non_sweep_directory(tmp_path, capsys):
    assert main(["sweep", "--summary", str(tmp_path)]) == 2
    assert "not a sweep directory" in capsys.readouterr().err
    assert os.listdir(tmp_path) == []


def test_ppo_hyperparameter_file_is_relative_to_the_spec(tmp_path):
    pytest.importorskip("yaml")
    (tmp_path / "sub").mkdir()
    spec = tmp_path / "sub" / "s.yml"
    spec.write_text("env: MKVJam-v1\nseeds: [0]\nlearners: {ppo: {hyperparams: hp.yml}}\n"
                    "budgets: {ppo: [100]}\n")
    loaded = sweep.load_spec(str(spec))
    assert loaded["learners"]["ppo"]["options"]["hyperparams"] == str(tmp_path / "sub" / "hp.yml")
    assert loaded["learners"]["ppo"]["options"]["env"] == "MKVJam-v1"


def test_bundled_claims_rows_are_complete_and_all_ok():
    from sfm_learn.experiments.claims import load_reference
    from sfm_learn.experiments.summary import combined_table

    doc = load_reference()
    expected = {n for spec in doc["specs"] for j in sweep.plan(spec) for n in j.names}
    rows = doc["rows"]
    assert len(rows) == len(expected) == 20 * 5 * 3 + 10 * 2 * 2
    assert all(r["status"] == "ok" for r in rows)
    assert {sweep.row_name(r["learner"], r["seed"], r["budget"]) for r in rows} == expected
    assert all("policy" not in r for r in rows)          # no paths of the machine that ran it
    agg = aggregate(rows)
    table = combined_table(agg, {"sfm": "teacher steps"},
                           [("MKVJam-v1", "escape_rate", "escape")])
    assert "| sfm | 1,200 teacher steps | " in table


def test_temporary_files_of_an_interrupted_write_are_not_rows(full, tmp_path):
    import shutil

    d = tmp_path / "copy"
    shutil.copytree(full, d)
    name = sweep.row_name("sfm", 0, 200)
    (d / "rows" / f".tmp-abc{name}").write_text((d / "rows" / name).read_text())
    assert len(sweep.read_rows(str(d))) == 6
    assert sweep.run_sweep(sweep.check_spec(SPEC), str(d))["skipped"] == 6
    assert not [n for n in os.listdir(d / "rows") if n.startswith(".")]   # cleaned up


@pytest.mark.parametrize("learner, options, budgets, least", [
    ("sfm", {}, [2], 35),                                 # the budget
    ("sfm", {}, [34, 200], 35),
    ("sfm-paper", {"preset": "paper"}, [12], 13),
    ("sfm-ols", {"kind": "sfm", "preset": "ols"}, [600, 20], 35),
    ("bc", {}, [32], 33),
    ("dagger", {}, [128], 129),                           # 4 rounds: round 0 gets 32 rows
    ("dagger", {"rounds": 1}, [2], 33),
])
def test_budgets_too_small_to_identify_are_refused_before_any_job(tmp_path, capsys, monkeypatch,
                                                                  learner, options, budgets,
                                                                  least):
    def no_job(*args, **kwargs):
        raise AssertionError("a job ran")

    monkeypatch.setattr(sweep, "run_job", no_job)
    spec = dict(SPEC, learners={learner: options}, budgets={learner: budgets})
    d = tmp_path / "o"
    assert main(["sweep", write_spec(tmp_path, spec), "--out", str(d), "--quiet"]) == 2
    out, err = capsys.readouterr()
    small = min(budgets)
    assert err.count("\n") == 1 and out == ""
    assert (f"mkv sweep: error: budgets.{learner}: {small} teacher steps is too small; the "
            f"smallest budget is {least} (") in err
    assert not d.exists()


def test_the_smallest_budgets_pass_the_check_and_the_sfm_one_runs(tmp_path, capsys):
    learners = {"sfm": {}, "sfm-paper": {"preset": "paper"}, "bc": {}, "dagger": {},
                "dagger-1": {"kind": "dagger", "rounds": 1}, "ppo": {"env": "MKVJam-v1"}}
    least = {"sfm": 35, "sfm-paper": 13, "bc": 33, "dagger": 129, "dagger-1": 33, "ppo": 2}
    spec = sweep.check_spec(dict(SPEC, learners=learners,
                                 budgets={n: [b] for n, b in least.items()}))
    sweep.check_budgets(spec)                             # PPO's env steps are not checked
    sensors = [f"s{i}" for i in range(10)]
    assert {n: sweep.min_budget(spec, n, sensors)[0] for n in least if n != "ppo"} == {
        n: b for n, b in least.items() if n != "ppo"}
    # budgets above one episode record whole shares of it: 601 steps are 2 x 300 rows
    assert sweep.teacher_rows(35) == 35 and sweep.teacher_rows(601) == 600
    small = dict(SPEC, eval={"episodes": 1, "seed": 4_100_000}, seeds=[0],
                 learners={"sfm": {}}, budgets={"sfm": [35]})
    d = tmp_path / "o"
    assert main(["sweep", write_spec(tmp_path, small), "--out", str(d), "--quiet"]) == 0
    (row,) = sweep.read_rows(str(d))
    assert row["status"] == "ok" and row["steps"] == 35


def test_banks_keep_every_episode_and_claims_bootstrap_over_them(tmp_path):
    """A small real sweep on two evaluation banks: every row keeps each episode's outcome and
    bank (disjoint seed ranges), its metrics pool both banks, and the claims' intervals then
    cover training sets and episodes."""
    from sfm_learn.experiments import claims

    spec = sweep.check_spec(dict(SPEC, seeds=[0, 1, 2], learners={"sfm": {}},
                                 budgets={"sfm": [300]},
                                 eval={"episodes": 3, "seed": 4_200_000, "banks": 2}))
    assert sweep.bank_seeds(spec["eval"]) == [4_200_000, 4_200_000 + sweep.BANK_STRIDE]
    d = tmp_path / "banks"
    assert sweep.run_sweep(spec, str(d))["ok"] == 3
    rows = sweep.read_rows(str(d))
    for r in rows:
        ep = r["episodes"]["MKVJam-v1"]
        assert ep["bank"] == [0, 0, 0, 1, 1, 1] and len(ep["escaped"]) == 6
        assert r["metrics"]["MKVJam-v1"]["escape_rate"] == sum(ep["escaped"]) / 6
        assert sweep.row_problem(r) is None
    p = claims.point_summary(claims.by_point(rows)[("sfm", 300)])
    assert p["covers"] == "training sets and evaluation episodes (6 in 2 banks)"
    assert p["escape_ci"][0] <= p["escape_mean"] <= p["escape_ci"][1]


@pytest.mark.parametrize("episodes", [
    "x", {"MKVJam-v1": {"bank": [0], "escaped": [2], "distance_m": [1.0]}},
    {"MKVJam-v1": {"bank": [0, 0], "escaped": [1], "distance_m": [1.0, 2.0]}},
    {"MKVJam-v1": {"bank": [0], "escaped": [1], "distance_m": [float("nan")]}},
    {"MKVJam-v1": {"bank": [-1], "escaped": None, "distance_m": [1.0]}},
    {"Other-v0": {"bank": [0], "escaped": [1], "distance_m": [1.0]}},
])
def test_rows_with_malformed_episodes_are_not_used(episodes):
    row = {"learner": "sfm", "seed": 0, "budget": 300, "status": "ok",
           "metrics": {"MKVJam-v1": {"escape_rate": 1.0}}, "episodes": episodes}
    assert "episodes" in sweep.row_problem(row)


def test_a_jam_teacher_budget_gives_its_rows_and_the_job_runs(tmp_path):
    """A jam env as the teacher env: its episodes end at the escape, a few dozen steps in; the
    budget's rows are still recorded (further seeds), so a budget check_budgets passes trains."""
    spec = sweep.check_spec(dict(SPEC, teacher_env="MKVJam-v1", seeds=[0],
                                 learners={"sfm": {}}, budgets={"sfm": [300]}))
    d = tmp_path / "jam"
    assert sweep.run_sweep(spec, str(d))["ok"] == 1
    data = sweep.teacher_data(spec, 0, 300, str(d))
    assert data.n_steps == 300 and data.n_episodes > 1
