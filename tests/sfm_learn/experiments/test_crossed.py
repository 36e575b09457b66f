"""The crossed (training sets x episodes) bootstrap: coverage on simulated data with known
levels and effects, where an interval over training sets alone under-covers; Holm's family-wise
error; the minimum detectable effect."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import expit

from sfm_learn.experiments import crossed

MU, SET_SD, EPISODE_SD = 2.5, 0.6, 1.8


def _truth(mu=MU) -> float:
    r = np.random.default_rng(0)
    return float(expit(mu + r.normal(0, SET_SD, (3000, 1)) + r.normal(0, EPISODE_SD,
                                                                          (1, 3000))).mean())


def _simulate(r, n_sets=20, per_bank=50, banks=2, mu=MU, episodes=None):
    """Escapes (0/1) of ``n_sets`` policies on shared episodes: a training-set effect and an
    episode difficulty, both random (``episodes``: the difficulties, to share them)."""
    a = r.normal(0, SET_SD, (n_sets, 1))
    e = r.normal(0, EPISODE_SD, (1, per_bank * banks)) if episodes is None else episodes
    y = (r.random((n_sets, per_bank * banks)) < expit(mu + a + e)).astype(float)
    return y, np.repeat(np.arange(banks), per_bank), e


@pytest.mark.parametrize("banks", [1, 2, 3])
def test_the_level_interval_covers_at_its_rate_where_sets_only_does_not(banks):
    truth, reps = _truth(), 100
    crossed_hits = sets_hits = 0
    for k in range(reps):
        y, b, _ = _simulate(np.random.default_rng(1000 + k), banks=banks)
        lo, hi = crossed.percentile_interval(
            crossed.crossed_bootstrap(y, b, seed=k, resamples=1000), 0.95)
        crossed_hits += lo <= truth <= hi
        means = y.mean(axis=1)  # the old interval: training sets resampled, episodes fixed
        idx = np.random.default_rng(k).integers(0, len(means), (1000, len(means)))
        lo1, hi1 = np.percentile(means[idx].mean(axis=1), [2.5, 97.5])
        sets_hits += lo1 <= truth <= hi1
    assert 0.88 <= crossed_hits / reps <= 1.0, crossed_hits
    assert sets_hits / reps < 0.85 and sets_hits < crossed_hits, (sets_hits, crossed_hits)


def test_the_interval_covers_a_fresh_bank_of_the_same_policies():
    """The acceptance check in small: policies' level on their own two banks; a third, fresh
    bank's value of the same policies lies inside the interval at about its stated rate (the
    fresh bank's own sampling variance included, so the rate is at least ~80 %)."""
    reps, hits = 100, 0
    for k in range(reps):
        r = np.random.default_rng(5000 + k)
        a = r.normal(0, SET_SD, (20, 1))
        y = (r.random((20, 100)) < expit(MU + a + r.normal(0, EPISODE_SD, (1, 100)))).astype(float)
        fresh = (r.random((20, 50)) < expit(MU + a + r.normal(0, EPISODE_SD, (1, 50)))).mean()
        lo, hi = crossed.percentile_interval(
            crossed.crossed_bootstrap(y, np.repeat([0, 1], 50), seed=k, resamples=1000), 0.95)
        hits += lo <= fresh <= hi
    assert hits / reps >= 0.8, hits


@pytest.mark.parametrize("banks", [2, 3])
def test_the_replication_interval_covers_a_rerun_at_its_rate_where_the_ci_does_not(banks):
    """The acceptance test of a claim in small: 20 *new* training sets on a *new* bank of 50
    episodes. Their mean lands in the replication interval at about its stated rate (95 %);
    the confidence interval of the level, which is about the mean alone, covers it less often."""
    reps, rep_hits, ci_hits = 100, 0, 0
    for k in range(reps):
        r = np.random.default_rng(40_000 + k)
        y, b, _ = _simulate(r, banks=banks)
        rerun, _, _ = _simulate(r, banks=1)  # new set effects, new episodes
        value = rerun.mean()
        lo, hi = crossed.replication_interval(y, b, 0.95, seed=k, resamples=1000)
        rep_hits += lo <= value <= hi
        clo, chi = crossed.percentile_interval(crossed.crossed_bootstrap(y, b, k, 1000), 0.95)
        ci_hits += clo <= value <= chi
    assert 0.9 <= rep_hits / reps <= 1.0, rep_hits
    assert ci_hits < rep_hits - 5, (ci_hits, rep_hits)


def test_a_simultaneous_replication_interval_is_wider_and_within_the_data():
    y, b, _ = _simulate(np.random.default_rng(2), banks=3)
    out = crossed.Outcomes(tuple(range(20)), y, b)
    one, many = crossed.level(out, resamples=1000), crossed.level(out, resamples=1000, family=19)
    assert one["replication"][0] > many["replication"][0] >= 0.0
    assert one["replication"][1] < many["replication"][1] <= 1.0
    assert one["ci"] == many["ci"] and one["ci"][1] - one["ci"][0] < (
        one["replication"][1] - one["replication"][0])


def test_paired_differences_cover_a_known_effect_and_cancel_what_is_shared():
    truth = _truth(MU + 0.5) - _truth(MU)
    reps, hits = 100, 0
    widths_paired, widths_unpaired = [], []
    for k in range(reps):
        r = np.random.default_rng(9000 + k)
        ya, b, e = _simulate(r, mu=MU + 0.5)
        yb, _, _ = _simulate(r, episodes=e)  # same episodes, same training-set seeds
        sets = tuple(range(20))
        res = crossed.paired(crossed.Outcomes(sets, ya, b), crossed.Outcomes(sets, yb, b),
                             seed=k, resamples=1000)
        lo, hi = crossed.percentile_interval(res["draws"], 0.95)
        hits += lo <= truth <= hi
        widths_paired.append(hi - lo)
        la = crossed.percentile_interval(crossed.crossed_bootstrap(ya, b, k, 1000), 0.95)
        lb = crossed.percentile_interval(crossed.crossed_bootstrap(yb, b, k + 1, 1000), 0.95)
        widths_unpaired.append(np.hypot(la[1] - la[0], lb[1] - lb[0]))
    assert 0.88 <= hits / reps <= 1.0, hits
    assert np.median(widths_paired) < 0.8 * np.median(widths_unpaired)


def test_holm_keeps_the_family_wise_error_under_the_null():
    """Five comparisons of learners that are all the same: the share of tables with any
    ranking stays near 5 % with Holm (it would be ~20 % with five unadjusted 95 % intervals)."""
    reps, any_holm, any_raw = 120, 0, 0
    for k in range(reps):
        r = np.random.default_rng(20_000 + k)
        base = [_simulate(r) for _ in range(1)][0]
        e = base[2]
        outs = [crossed.Outcomes(tuple(range(20)), _simulate(r, episodes=e)[0], base[1])
                for _ in range(6)]
        pairs = {f"{i}-{i + 1}": (outs[i], outs[i + 1]) for i in range(5)}
        t = crossed.table(pairs, seed=k, resamples=1000)
        any_holm += any(v["verdict"] for v in t.values())
        any_raw += any(v["p"] < 0.05 for v in t.values())
    assert any_holm / reps <= 0.1, any_holm
    assert any_raw > any_holm


def test_a_clear_effect_is_ranked_and_the_mde_is_below_it():
    r = np.random.default_rng(3)
    ya, b, e = _simulate(r, mu=MU + 1.5)
    yb, _, _ = _simulate(r, episodes=e)
    sets = tuple(range(20))
    t = crossed.table({"a-b": (crossed.Outcomes(sets, ya, b), crossed.Outcomes(sets, yb, b))},
                      resamples=2000)
    row = t["a-b"]
    assert row["verdict"] == "a" and row["ci"][0] > 0 and row["mde"] < row["mean"]
    assert row["confidence"] == pytest.approx(0.95)


def test_holm_steps():
    out = crossed.holm([0.01, 0.04, 0.03, 0.5])
    assert [o["rejected"] for o in out] == [True, False, False, False]
    assert out[0]["confidence"] == pytest.approx(1 - 0.05 / 4)
    assert out[2]["p_adjusted"] == pytest.approx(0.09)
    assert out[1]["p_adjusted"] == pytest.approx(0.09)
    assert all(o["rejected"] for o in crossed.holm([0.001, 0.002]))


@settings(max_examples=40, deadline=None)
@given(n_sets=st.integers(1, 6), per_bank=st.integers(1, 8), banks=st.integers(1, 4),
       seed=st.integers(0, 2**31))
def test_the_bootstrap_is_a_distribution_of_means_of_the_data(n_sets, per_bank, banks, seed):
    r = np.random.default_rng(seed)
    y = r.random((n_sets, per_bank * banks))
    draws = crossed.crossed_bootstrap(y, np.repeat(np.arange(banks), per_bank), seed, 200)
    assert draws.shape == (200,) and np.all(np.isfinite(draws))
    assert y.min() - 1e-12 <= draws.min() and draws.max() <= y.max() + 1e-12
    const = crossed.crossed_bootstrap(np.full_like(y, 0.7), np.repeat(np.arange(banks), per_bank),
                                      seed, 50)
    assert np.allclose(const, 0.7)


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="do not match"):
        crossed.Outcomes((0, 1), np.zeros((3, 4)), np.zeros(4))
    with pytest.raises(ValueError, match="finite"):
        crossed.Outcomes((0,), np.array([[np.nan]]), np.zeros(1))
    with pytest.raises(ValueError, match="same evaluation episodes"):
        crossed.Outcomes((0,), np.zeros((1, 2)), np.zeros(2)).common(
            crossed.Outcomes((0,), np.zeros((1, 2)), np.ones(2)))


@settings(max_examples=40, deadline=None)
@given(resamples=st.integers(1, 30), n=st.integers(1, 12), k=st.integers(1, 40),
       seed=st.integers(0, 2**31))
def test_counts_are_add_at_of_ones(resamples, n, k, seed):
    r = np.random.default_rng(seed)
    rows = r.integers(0, resamples, size=(k, 1))
    cols = r.integers(0, n, size=(k, 3))
    expected = np.zeros((resamples, n))
    np.add.at(expected, (rows, cols), 1.0)
    np.testing.assert_array_equal(crossed._counts(rows, cols, (resamples, n)), expected)
    pooled = crossed._counts([rows, rows[:1]], [cols, cols[:1]], (resamples, n))
    np.add.at(expected, (rows[:1], cols[:1]), 1.0)
    np.testing.assert_array_equal(pooled, expected)


def test_a_remembered_level_or_pair_is_the_computed_one_and_a_copy():
    """level and paired remember results by their inputs: a repeat returns what computing gives
    (a changed value, seed or family is not served from memory), and changing a returned result
    changes no later one."""
    rng = np.random.default_rng(3)
    vals = rng.binomial(1, 0.7, size=(6, 30)).astype(float)
    banks = np.repeat(np.arange(3), 10)
    out = crossed.Outcomes(tuple(range(6)), vals, banks)
    first = crossed.level(out, seed=1)
    assert first == crossed._level(out, 1, crossed.RESAMPLES, 1 - crossed.ALPHA, 1)
    first["ci"] = None
    assert crossed.level(out, seed=1)["ci"] is not None
    assert crossed.level(out, seed=2) == crossed._level(out, 2, crossed.RESAMPLES,
                                                       1 - crossed.ALPHA, 1)
    assert crossed.level(out, seed=1, family=5)["replication"] != \
        crossed.level(out, seed=1)["replication"]
    other = vals.copy()
    other[0, 0] = 1 - other[0, 0]
    changed = crossed.Outcomes(tuple(range(6)), other, banks)
    assert crossed.level(changed, seed=1)["mean"] == other.mean() != first["mean"]
    b = crossed.Outcomes(tuple(range(6)), rng.binomial(1, 0.5, size=(6, 30)).astype(float),
                         banks)
    p = crossed.paired(out, b, seed=4)
    fresh = crossed._paired(out, b, 4, crossed.RESAMPLES)
    assert {k: v for k, v in p.items() if k != "draws"} == \
        {k: v for k, v in fresh.items() if k != "draws"}
    np.testing.assert_array_equal(p["draws"], fresh["draws"])
    p["draws"][:] = 99.0
    assert not np.any(crossed.paired(out, b, seed=4)["draws"] == 99.0)
