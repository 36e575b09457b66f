"""Evaluation: per-episode records, aggregate metrics, bootstrap intervals, workers, reports."""

import json
import time

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from mkv_env.policies import PolicySpecError
from mkv_env.recorder import record
from mkv_env.teacher import ScriptedTeacher
from sfm_learn.evaluation.bootstrap import (
    bootstrap_ci,
    paired_difference_ci,
    resample_rng,
    resampled_metrics,
)
from sfm_learn.evaluation.records import (
    METRIC_KEYS,
    EpisodeRecord,
    Evaluation,
    aggregate,
    episode_records,
    evaluations_json,
)
from sfm_learn.evaluation.runner import evaluate, evaluate_many, plan_units, run_episodes
from sfm_learn.reporting.plots import plot_evaluations
from sfm_learn.reporting.tables import METRIC_LABELS, format_cell, format_markdown, format_table


def bootstrap_indices(n, n_boot):
    """The resample indices the bootstrap draws for n records (its first n_boot rows)."""
    return resample_rng(n).integers(0, n, size=(n_boot, n))


def rec(steps=100, escaped=None, escape_time_s=None, **kw):
    base = dict(seed=0, steps=steps, duration_s=steps * 0.1, episode_return=1.0, distance_m=2.0,
                stuck_steps=0, collisions=0, jams=0, escapes=0, escaped=escaped,
                escape_time_s=escape_time_s)
    base.update(kw)
    return EpisodeRecord(**base)


def test_aggregate_known_values():
    records = [
        rec(steps=100, escaped=True, escape_time_s=2.0, stuck_steps=10, collisions=3,
            episode_return=4.0, distance_m=1.0),
        rec(steps=300, escaped=False, stuck_steps=30, collisions=1, episode_return=-2.0,
            distance_m=3.0),
        rec(steps=50, escaped=True, escape_time_s=5.0, collisions=2, episode_return=1.0,
            distance_m=2.0),
    ]
    m = aggregate(records)
    assert m["escape_rate"] == pytest.approx(2 / 3)
    assert m["mean_escape_time_s"] == pytest.approx(3.5)
    assert m["distance_m"] == pytest.approx(2.0)
    assert m["stuck_fraction"] == pytest.approx(40 / 450)
    assert m["collisions_per_min"] == pytest.approx(6 / (45.0 / 60.0))
    assert m["mean_return"] == pytest.approx(1.0)


def test_escape_metrics_undefined_without_escapes():
    m = aggregate([rec(), rec()])
    assert m["escape_rate"] is None and m["mean_escape_time_s"] is None
    m = aggregate([rec(escaped=False), rec(escaped=False)])
    assert m["escape_rate"] == 0.0 and m["mean_escape_time_s"] is None
    with pytest.raises(ValueError):
        aggregate([])


def test_records_from_a_dataset():
    data = record("MKVJam-v0", "teacher", episodes=4, seed=20)
    records = episode_records(data)
    assert [r.seed for r in records] == [20, 21, 22, 23]
    for r, rows in zip(records, data.episode_slices(), strict=True):
        assert r.steps == rows.stop - rows.start
        assert r.episode_return == pytest.approx(data["rewards"][rows].sum())
        assert r.escaped == bool(data["escaped"][rows.stop - 1])
        if r.escaped:
            first = int(np.argmax(data["escaped"][rows]))
            assert r.escape_time_s == pytest.approx((first + 1) * 0.1)
        assert r.scenario in ("wall", "corner", "dead_end", "wedge")


def test_worker_split_gives_the_same_records():
    """Seeds can be shared out (to worker processes) and the records concatenated."""
    whole = evaluate("MKVJam-v0", "teacher", episodes=5, seed=40)
    parts = (run_episodes("MKVJam-v0", "teacher", seeds=[40, 41])
             + run_episodes("MKVJam-v0", "teacher", seeds=[42, 43, 44]))
    assert parts == whole.records
    assert aggregate(parts) == whole.metrics


def test_teacher_beats_random_on_jams():
    teacher = evaluate("MKVJam-v0", "teacher", episodes=6, seed=0)
    rand = evaluate("MKVJam-v0", "random", episodes=6, seed=0)
    assert teacher.metrics["escape_rate"] >= 5 / 6
    assert teacher.metrics["mean_escape_time_s"] < 10.0
    assert rand.metrics["mean_return"] < teacher.metrics["mean_return"]


def test_json_document_has_exactly_the_contract_keys():
    ev = evaluate("MKV-v0", "teacher", episodes=1, seed=0,
                  env_kwargs={"max_episode_steps": 50})
    doc = json.loads(ev.to_json())
    assert set(doc) == {"env", "policy", "episodes", "seed", "metrics", "metrics_ci"}
    assert set(doc["metrics"]) == set(METRIC_KEYS) == set(doc["metrics_ci"])
    assert doc["metrics_ci"]["escape_rate"] is None
    assert doc["metrics_ci"]["distance_m"] == [doc["metrics"]["distance_m"]] * 2  # one episode
    assert doc["metrics"]["escape_rate"] is None
    assert doc["metrics"]["mean_escape_time_s"] is None
    assert doc["env"] == "MKV-v0" and doc["policy"] == "teacher" and doc["episodes"] == 1
    assert isinstance(doc["metrics"]["distance_m"], float)


def test_table_lists_every_policy_and_metric():
    a = Evaluation("MKVJam-v0", "teacher", 3, 0, aggregate([rec(escaped=True, escape_time_s=1)]))
    b = Evaluation("MKVJam-v0", "sfm:p.npz", 3, 0, aggregate([rec(escaped=False)]))
    text = format_table([a, b])
    assert "teacher" in text and "sfm:p.npz" in text and "seeds 0..2" in text
    assert len(text.splitlines()) == 2 + len(METRIC_KEYS)
    assert "escape rate" in text and "-" in text.splitlines()[3]


def test_bad_seed_lists():
    with pytest.raises(ValueError, match="consecutive"):
        run_episodes("MKV-v0", "teacher", seeds=[1, 3])


# ---------------------------------------------------------------------- bootstrap intervals
def random_records(rng, n, p_escape=0.7, escapes=True):
    out = []
    for i in range(n):
        steps = int(rng.integers(5, 300))
        escaped = bool(rng.random() < p_escape) if escapes else None
        out.append(rec(seed=i, steps=steps, escaped=escaped,
                       escape_time_s=float(steps * 0.1) if escaped else None,
                       stuck_steps=int(rng.integers(0, steps)),
                       collisions=int(rng.integers(0, 6)),
                       episode_return=float(rng.normal(0, 3)),
                       distance_m=float(rng.uniform(0, 4))))
    return out


def test_vectorised_resamples_match_aggregate():
    records = random_records(np.random.default_rng(3), 30)
    idx = bootstrap_indices(len(records), 40)
    fast = resampled_metrics(records, idx)
    for j, row in enumerate(idx):
        slow = aggregate([records[i] for i in row])
        for key in METRIC_KEYS:
            if slow[key] is None:
                assert np.isnan(fast[key][j])
            else:
                assert fast[key][j] == pytest.approx(slow[key], rel=1e-12)


def test_resample_without_escapes_is_nan_and_dropped():
    records = [rec(escaped=True, escape_time_s=2.0)] + [rec(escaped=False)] * 9
    fast = resampled_metrics(records, bootstrap_indices(10, 500))
    none_escaped = fast["escape_rate"] == 0
    assert none_escaped.any() and np.isnan(fast["mean_escape_time_s"][none_escaped]).all()
    ci = bootstrap_ci(records)
    assert ci["mean_escape_time_s"] == [2.0, 2.0]  # the resamples that define it all say 2.0
    assert ci["escape_rate"][0] == 0.0 and 0.1 < ci["escape_rate"][1] < 0.5


def test_ci_keys_bounds_and_none():
    records = random_records(np.random.default_rng(4), 50)
    metrics = aggregate(records)
    ci = bootstrap_ci(records)
    assert set(ci) == set(METRIC_KEYS)
    for key in METRIC_KEYS:
        low, high = ci[key]
        assert low <= metrics[key] <= high and low < high
    wander = bootstrap_ci(random_records(np.random.default_rng(4), 5, escapes=False))
    assert wander["escape_rate"] is None and wander["mean_escape_time_s"] is None
    assert ci == bootstrap_ci(records)  # a fixed stream: same records, same intervals


def test_bootstrap_is_fast():
    records = random_records(np.random.default_rng(5), 100)
    t0 = time.perf_counter()
    bootstrap_ci(records, n_boot=2000)
    assert time.perf_counter() - t0 < 0.5


@settings(max_examples=8, deadline=None)
@given(p=st.floats(0.2, 0.8), sim_seed=st.integers(0, 2**32 - 1))
def test_ci_covers_a_known_bernoulli_rate(p, sim_seed):
    """Over many simulated evaluations, the 95% interval of the escape rate covers the true
    rate about 95% of the time (percentile bootstrap: a little less for small n)."""
    rng = np.random.default_rng(sim_seed)
    n, trials = 60, 120
    covered = 0
    for _ in range(trials):
        escaped = rng.random(n) < p
        records = [rec(escaped=bool(e), escape_time_s=1.0 if e else None) for e in escaped]
        low, high = bootstrap_ci(records, n_boot=400)["escape_rate"]
        covered += low <= p <= high
    assert covered / trials >= 0.85


@settings(max_examples=15, deadline=None)
@given(sim_seed=st.integers(0, 2**32 - 1), n=st.integers(3, 12))
def test_ci_shrinks_with_more_episodes(sim_seed, n):
    """The same spread of episodes, seen 4 times as often, gives narrower intervals."""
    rng = np.random.default_rng(sim_seed)
    records = random_records(rng, n, p_escape=0.5)
    assume(len({r.distance_m for r in records}) > 1)
    assume(0 < sum(bool(r.escaped) for r in records) < n)
    small, big = bootstrap_ci(records), bootstrap_ci(records * 4)
    metrics = aggregate(records)
    for key in ("escape_rate", "distance_m", "mean_return"):
        assert big[key][1] - big[key][0] < small[key][1] - small[key][0], key
        assert big[key][0] <= metrics[key] <= big[key][1]


def test_paired_difference():
    rng = np.random.default_rng(6)
    a = random_records(rng, 40, p_escape=0.9)
    b = [rec(seed=r.seed, steps=r.steps, escaped=False, distance_m=r.distance_m - 1.0)
         for r in a]
    d, (low, high) = paired_difference_ci(a, a, "distance_m")
    assert d == 0.0 and low == high == 0.0
    d, (low, high) = paired_difference_ci(a, b, "distance_m")
    assert d == pytest.approx(1.0) and low == pytest.approx(1.0) and high == pytest.approx(1.0)
    d, (low, high) = paired_difference_ci(a, b, "escape_rate")
    assert 0 < low <= d <= high <= 1
    assert paired_difference_ci(a, b, "mean_escape_time_s") is None  # b never escapes
    with pytest.raises(ValueError, match="same seeds"):
        paired_difference_ci(a, b[::-1], "distance_m")


# ---------------------------------------------------------------------- several policies, workers
def test_plan_units_covers_every_episode_once():
    for n_pol, episodes, workers in [(1, 1, 2), (2, 5, 2), (3, 100, 2), (1, 2400, 4), (2, 7, 1)]:
        units = plan_units(n_pol, episodes, workers)
        for p in range(n_pol):
            mine = [(first, count) for q, first, count in units if q == p]
            starts = [0] + list(np.cumsum([c for _, c in mine]))
            assert [f for f, _ in mine] == starts[:-1] and starts[-1] == episodes
        if workers == 1:
            assert len(units) == n_pol
        elif n_pol * episodes >= 100:
            assert units[0][2] > units[-1][2]  # large units first, small ones last


def test_workers_give_identical_records_metrics_and_json():
    specs = ["teacher", "random", "teacher:backoff_s=2"]
    one = evaluate_many("MKVJam-v0", specs, episodes=5, seed=7, workers=1)
    seen = []
    two = evaluate_many("MKVJam-v0", specs, episodes=5, seed=7, workers=2,
                        on_episode=lambda p, i, n: seen.append((p, i)))
    assert sorted(seen) == [(p, i) for p in range(3) for i in range(5)]
    assert [e.policy for e in two] == specs
    for a, b in zip(one, two, strict=True):
        assert a.records == b.records and a.metrics == b.metrics
        assert a.metrics_ci == b.metrics_ci
        assert [r.seed for r in a.records] == list(range(7, 12))
    assert evaluations_json(one) == evaluations_json(two)
    # each policy is the same as evaluating it alone
    alone = evaluate("MKVJam-v0", "random", episodes=5, seed=7)
    assert alone.records == one[1].records


def test_same_seeds_same_json():
    a = evaluate_many("MKV-v0", ["teacher", "random"], 3, seed=2,
                      env_kwargs={"max_episode_steps": 40})
    b = evaluate_many("MKV-v0", ["teacher", "random"], 3, seed=2,
                      env_kwargs={"max_episode_steps": 40})
    assert evaluations_json(a) == evaluations_json(b)


def test_json_for_several_policies_is_a_list_in_order():
    evs = evaluate_many("MKVJam-v0", ["random", "teacher"], 2, seed=0, n_boot=200)
    docs = json.loads(evaluations_json(evs))
    assert isinstance(docs, list) and [d["policy"] for d in docs] == ["random", "teacher"]
    for d in docs:
        assert set(d) == {"env", "policy", "episodes", "seed", "metrics", "metrics_ci"}
        assert set(d["metrics_ci"]) == set(d["metrics"]) == set(METRIC_KEYS)
        for key, value in d["metrics"].items():
            if value is None:
                assert d["metrics_ci"][key] is None
            else:
                low, high = d["metrics_ci"][key]
                assert low <= value <= high
    single = json.loads(evaluations_json(evs[:1]))
    assert isinstance(single, dict) and single == docs[0]


def test_bad_evaluate_many_arguments():
    teacher = ScriptedTeacher(seed=0)
    with pytest.raises(ValueError, match="workers=1"):
        evaluate_many("MKVJam-v0", [teacher, "random"], 4, workers=2)
    with pytest.raises(ValueError, match="more than once"):
        evaluate_many("MKVJam-v0", ["random", "random"], 1)
    with pytest.raises(ValueError, match="no policies"):
        evaluate_many("MKVJam-v0", [], 1)
    with pytest.raises(ValueError, match="workers"):
        evaluate_many("MKVJam-v0", ["random"], 1, workers=0)
    # a policy object works in this process
    ev = evaluate_many("MKVJam-v0", [teacher], 2, workers=1, policy_names=["mine"])[0]
    assert ev.policy == "mine" and len(ev.records) == 2


def test_worker_errors_reach_the_caller():
    with pytest.raises(PolicySpecError, match="unknown policy"):
        evaluate_many("MKVJam-v0", ["teacher", "bogus"], 4, workers=2)


# ---------------------------------------------------------------------- reports
def two_evaluations():
    recs_a = [rec(escaped=True, escape_time_s=1.0, distance_m=1.0),
              rec(escaped=False, distance_m=3.0)]
    recs_b = [rec(escaped=False), rec(escaped=False)]
    out = []
    for name, recs in (("teacher", recs_a), ("sfm:/tmp/x|y.npz", recs_b)):
        m = aggregate(recs)
        out.append(Evaluation("MKVJam-v0", name, 2, 10, m, recs,
                              metrics_ci=bootstrap_ci(recs, metrics=m)))
    return out


def test_markdown_table():
    evs = two_evaluations()
    text = format_markdown(evs)
    lines = text.splitlines()
    assert lines[0].startswith("**MKVJam-v0**, 2 episodes per policy on env seeds 10..11")
    assert "95% bootstrap" in lines[0]
    header = lines[2]
    assert header.startswith("| policy |") and all(METRIC_LABELS[k] in header
                                                   for k in METRIC_KEYS)
    assert lines[3].startswith("|:---|---:|")
    assert len(lines) == 4 + 2
    teacher = lines[4].split(" | ")
    assert teacher[0] == "| teacher" and teacher[1] == "0.500 [0.000, 1.000]"
    assert teacher[2] == "1.00 [1.00, 1.00]"
    sfm = lines[5]
    assert "sfm:/tmp/x\\|y.npz" in sfm  # pipes escaped
    assert sfm.split(" | ")[2] == "-"  # no escapes: undefined time
    assert format_cell(None) == "-" and format_cell(0.98, [0.94, 1.0]) == "0.980 [0.940, 1.000]"


def test_markdown_with_different_seeds_gets_columns():
    a, b = two_evaluations()
    b.seed = 50
    lines = format_markdown([a, b]).splitlines()
    assert "| policy | env | seeds |" in lines[2] and "| 50..51 |" in lines[5]


def test_plot_is_written(tmp_path, monkeypatch):
    monkeypatch.setenv("MPLBACKEND", "Agg")
    pytest.importorskip("matplotlib")
    out = tmp_path / "bars.png"
    plot_evaluations(two_evaluations(), str(out))
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000
    assert [p.name for p in tmp_path.iterdir()] == ["bars.png"]


def test_a_killed_worker_is_a_clear_error():
    """A worker that dies (OOM killer, kill -9) ends the evaluation with one clear error."""
    psutil = pytest.importorskip("psutil")
    import signal

    killed = []

    def kill_a_worker(p, i, n):
        if killed:
            return
        me = psutil.Process()
        for server in me.children():
            try:  # (a child may end between the listing and the look: not the one to kill)
                for worker in server.children():  # forkserver -> workers
                    worker.send_signal(signal.SIGKILL)
                    killed.append(worker.pid)
            except psutil.NoSuchProcess:
                continue

    with pytest.raises(RuntimeError, match="worker process died") as e:
        evaluate_many("MKVJam-v0", ["random"], 400, seed=0, workers=2,
                      env_kwargs={"max_episode_steps": 20}, on_episode=kill_a_worker)
    assert killed and "\n" not in str(e.value)
