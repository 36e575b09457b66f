"""``mkv demo --quick`` end to end, and the report's computed conclusions."""

import json

import pytest

from sfm_learn.cli import main
from sfm_learn.evaluation import EpisodeRecord, Evaluation, aggregate
from sfm_learn.reporting.report import conclusions


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "out"
    assert main(["demo", "--quick", "--out", str(out), "--quiet"]) == 0
    return out


def test_quick_demo_writes_the_report_and_every_file_it_links(demo_dir):
    report = (demo_dir / "report.md").read_text()
    for heading in ("## Set-up", "## The paper's Figure 3, replayed honestly",
                    "## What the paper's own configuration achieves", "## Which features",
                    "## The kept rank", "## Closed loop", "## Learning cost", "## Conclusions",
                    "## Force-sensor calibration", "## How this report was made"):
        assert heading in report
    for png in ("fig3.png", "rank_study.png", "eval/jam.png", "eval/wander.png",
                "learning_cost.png"):
        assert f"({png})" in report
        assert (demo_dir / png).read_bytes()[:4] == b"\x89PNG"
    assert (demo_dir / "calib" / "trials.md").exists()
    assert "Quick run" in report


def test_quick_demo_evaluates_every_policy_on_the_same_seeds(demo_dir):
    head = ["teacher", "random", "stand still", "SfM (2 sets)", "SfM paper (2 sets)",
            "BC (2 sets)", "DAgger (2 sets)", "PPO jam", "PPO wander"]
    for key, env in (("jam", "MKVJam-v1"), ("wander", "MKV-v1")):
        doc = json.loads((demo_dir / "eval" / f"{key}.json").read_text())
        names = [d["policy"] for d in doc]
        assert names[:9] == head
        # then every training set's own evaluation
        assert names[9:] == [f"{n} set {k}" for n in ("SfM", "SfM paper", "BC", "DAgger")
                             for k in range(2)]
        assert all(d["env"] == env and d["seed"] == 2_000_000 for d in doc)
        assert all(set(d["metrics_ci"]) == set(d["metrics"]) for d in doc)
        assert [d.get("training_sets", 1) for d in doc[:9]] == [1, 1, 1, 2, 2, 2, 2, 1, 1]
        # a pooled learner is the mean of its training sets
        pooled = doc[3]["metrics"]["distance_m"]
        sets = [d["metrics"]["distance_m"] for d in doc[9:11]]
        assert abs(pooled - sum(sets) / 2) < 1e-9
        assert doc[2]["metrics"]["distance_m"] < 0.05          # stand still stands still
    report = (demo_dir / "report.md").read_text()
    assert "one PPO seed at the demo's reduced budget" in report
    assert "## Over many training sets (the bundled claims sweeps" in report
    # the claims sentences are the generated ones of the bundled rows, verbatim
    from sfm_learn.experiments import claims

    for line in claims.claim_sentences(claims.load_reference()["rows"]):
        assert f"- {line}" in report
    assert (demo_dir / "sample_efficiency.png").read_bytes()[:4] == b"\x89PNG"
    assert "intra-op thread" in report                          # thread settings printed
    sfm = json.loads((demo_dir / "eval" / "jam.json").read_text())[3]
    assert f"| SfM (2 sets) | {sfm['metrics']['escape_rate']:.3f}" in report
    cmp = json.loads((demo_dir / "compare.json").read_text())
    assert set(cmp["modes"]) == {"teacher_forced", "free_running"}
    assert set(cmp["baselines"]) == {"copy_previous", "constant"}


def test_demo_refuses_a_file_as_output_dir(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["demo", "--quick", "--out", str(f)]) == 2
    assert "not a directory" in capsys.readouterr().err


def _records(values, metric_field="distance_m"):
    return [EpisodeRecord(seed=i, steps=10, duration_s=1.0, episode_return=0.0,
                          distance_m=float(v), stuck_steps=0, collisions=0, jams=0, escapes=0,
                          escaped=None, escape_time_s=None) for i, v in enumerate(values)]


def _ev(name, values):
    recs = _records(values)
    return Evaluation("MKV-v1", name, len(recs), 0, aggregate(recs), recs)


def test_conclusions_say_when_a_baseline_beats_sfm_and_when_it_is_a_tie():
    import numpy as np

    rng = np.random.default_rng(0)
    base = rng.uniform(5, 10, 40)
    evals = {"jam": [], "wander": [_ev("SfM", base), _ev("PPO", base + 3.0),
                                   _ev("BC", base + rng.normal(0, 0.5, 40))]}
    lines = conclusions(evals)
    ppo = [line for line in lines if "PPO" in line]
    assert len(ppo) == 2
    assert ppo[0].startswith("**PPO beats SfM** on: distance per episode [m] on MKV-v1")
    assert "difference -3.000" in ppo[0]
    bc = [line for line in lines if "BC" in line]
    assert any(line.startswith("No clear difference between SfM and BC") for line in bc)


def test_every_policy_kind_gives_the_same_numbers_for_any_worker_count(demo_dir):
    from sfm_learn.evaluation import evaluate_many, evaluations_json

    specs = [f"sfm:{demo_dir / 'policies' / 'sfm_0.npz'}",
             f"bc:{demo_dir / 'policies' / 'bc_0.zip'}",
             f"ppo:{demo_dir / 'policies' / 'ppo_jam.zip'}",
             f"dagger:{demo_dir / 'policies' / 'dagger_0.zip'}"]
    one = evaluations_json(evaluate_many("MKVJam-v1", specs, 4, 77, workers=1))
    two = evaluations_json(evaluate_many("MKVJam-v1", specs, 4, 77, workers=2))
    assert one == two
    doc = json.loads(one)
    assert [set(d) for d in doc] == [{"env", "policy", "episodes", "seed", "metrics",
                                      "metrics_ci"}] * 4
