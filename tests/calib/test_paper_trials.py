"""The paper's section 8 settings over many seeds: offsets at least 5x better than the paper's."""

import numpy as np
import pytest

from calib.simulation.simulate import PAPER_C, paper_shape_matrix, paper_trial
from calib.simulation.trials import paper_mean_abs_error, run_trial, smoothed_std

SEEDS = range(100)


@pytest.fixture(scope="module")
def trials():
    return {t: run_trial(t, SEEDS) for t in (2, 3, 4)}


def test_paper_numbers_transcribed():
    # the issue quotes the paper's Trial 3 errors as averaging about 7.4 units
    assert paper_mean_abs_error(3) == pytest.approx(7.41, abs=0.01)
    assert paper_mean_abs_error(2) == pytest.approx(0.825, abs=1e-3)
    assert paper_mean_abs_error(4) == pytest.approx(14.39, abs=0.01)


def test_paper_scale_gives_peak_signal_150():
    d = paper_trial(1, rng=0, n=5000)
    peak = np.max(np.abs(d.Z - d.offset))
    assert 140 < peak <= 150.0 + 1e-9
    assert np.allclose(np.linalg.pinv(paper_shape_matrix().T), PAPER_C)


@pytest.mark.parametrize("trial", [2, 3, 4])
@pytest.mark.parametrize("method", ["centered", "paper"])
def test_offsets_five_times_better_than_paper(trials, trial, method):
    med = np.median(trials[trial][method]["mean_abs_error"])
    assert med * 5 <= paper_mean_abs_error(trial), (trial, method, med)


@pytest.mark.parametrize("trial", [2, 3, 4])
def test_regression_numbers(trials, trial):
    # seeded regression values of the centered route (100 seeds); a change means the science changed
    expected = {2: 0.1252, 3: 0.6179, 4: 0.7332}[trial]
    med = np.median(trials[trial]["centered"]["mean_abs_error"])
    assert med == pytest.approx(expected, rel=0.02)


@pytest.mark.parametrize("trial", [2, 3, 4])
def test_offset_calc_beats_plain_sfm_on_biased_data(trials, trial):
    # the point of the paper: with offsets, the bias-aware fit gives a steadier magnitude
    with_off = np.median(trials[trial]["centered"]["mag_std_smooth"])
    without = np.median(trials[trial]["sfm_no_offset"]["mag_std_smooth"])
    assert with_off < 0.5 * without
    assert abs(np.median(trials[trial]["centered"]["mag_mean"]) - 1) < 0.01


def test_smoothed_std():
    x = np.array([0.0, 1.0] * 50)
    assert smoothed_std(x, 2) == pytest.approx(0.0)
    assert smoothed_std(x, 1) == pytest.approx(0.5)


def test_ft6_sfm_beats_least_squares_with_same_known_loads():
    from calib.simulation.trials import ft6_comparison

    r = ft6_comparison(range(20))
    assert r["sfm"] < 0.6 * r["ls_same"], r


def test_table1_sfm_steadier_than_least_squares():
    from calib.simulation.trials import table1

    t = table1(range(10))
    for _load, d in t.items():
        assert d["sfm"]["smooth"] < d["ls"]["smooth"]
        assert d["sfm"]["error_pct"] < 1.0
