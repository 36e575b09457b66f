"""Evaluation: per-episode records and the aggregate metrics."""

import json

import numpy as np
import pytest

from mkv_env.recorder import record
from sfm_learn.evaluation import (
    METRIC_KEYS,
    EpisodeRecord,
    Evaluation,
    aggregate,
    episode_records,
    evaluate,
    format_table,
    run_episodes,
)


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
    assert set(doc) == {"env", "policy", "episodes", "seed", "metrics"}
    assert set(doc["metrics"]) == set(METRIC_KEYS)
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
