"""Partial coverage (bounded errors + warning) and every bad-input case (clear one-line errors)."""

import warnings

import numpy as np
import pytest

from calib.data.result import CalibrationError, CalibrationWarning
from calib.estimators.bias import fit_bias
from calib.estimators.ellipsoid import fit_ellipsoid
from calib.estimators.least_squares import fit_least_squares
from calib.estimators.sfm import fit_sfm
from calib.simulation.simulate import paper_trial, random_shape, simulate


@pytest.mark.parametrize("method", ["centered", "paper"])
@pytest.mark.parametrize("trial,bound,whiten", [(2, 15.0, False), (3, 75.0, False),
                                                (2, 15.0, True), (3, 150.0, True)])
def test_60_degree_cap_bounded_and_warned(method, trial, bound, whiten):
    # whiten=False is the paper's method on the paper's own sensor (isotropic in its raw
    # channels); whitened (the default, units never matter) the centered route's isotropy prior
    # speaks of the noise-scaled channels and Trial 3 (10 % noise) loses: worst offset 102
    # counts over these seeds (raw 44); bounded by the signal (150 counts) all the same
    errs = []
    for seed in range(30):
        d = paper_trial(trial, rng=seed, cap_half_angle_deg=60)
        with warnings.catch_warnings():  # the other warnings of a 60 degree cap are expected
            warnings.simplefilter("ignore", CalibrationWarning)
            with pytest.warns(CalibrationWarning, match="poor excitation"):
                cal = fit_bias(d.Z, 3, method=method, whiten=whiten)
        assert np.all(np.isfinite(cal.C)) and np.all(np.isfinite(cal.offset))
        assert cal.diagnostics["excitation_poor"]
        # the cap of the *fitted* directions: trial 3's 10 % noise spreads them beyond the true
        # 60 degrees (72.6 measured on one seed with whitened channels), still far from a sphere
        assert cal.diagnostics["coverage"]["cap_half_angle_deg"] < 80
        errs.append(np.mean(np.abs(cal.offset - d.offset)))
    # bounded: below the 150-count signal (half of it for 10 % noise on the raw channels)
    assert max(errs) < bound, max(errs)


def test_full_sphere_does_not_warn():
    d = paper_trial(3, rng=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CalibrationWarning)
        cal = fit_bias(d.Z, 3)
    cov = cal.diagnostics["coverage"]
    assert cov["isotropy"] > 0.8 and cov["covered_fraction"] == 1.0
    assert cal.diagnostics["rank_gap"] > 5


def test_hyperboloid_on_short_arc_is_rejected_with_warning():
    # a noisy short arc of a circle: the unconstrained conic fit is a hyperbola for some seeds
    rng = np.random.default_rng(0)
    seen = 0
    for _ in range(40):
        t = rng.uniform(-0.5, 0.5, 30)
        Y = np.column_stack([np.sin(t), np.cos(t)]) * [3.0, 1.0] + rng.normal(size=(30, 2)) * 0.05
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always", CalibrationWarning)
            fit = fit_ellipsoid(Y)
        assert np.linalg.eigvalsh(fit.W)[0] > 0  # always an ellipse
        if any("hyperboloid" in str(x.message) for x in w):
            seen += 1
            assert fit.info["start"].startswith("sphere")
    assert seen > 0


def noisy3(seed=0, n=100, p=8):
    rng = np.random.default_rng(seed)
    S = random_shape(3, p, rng)
    return simulate(S, n, rng, magnitude=5, offset=rng.normal(size=p), noise=0.01)


@pytest.mark.parametrize(
    "fit",
    [
        lambda Z: fit_bias(Z, 3, method="centered"),
        lambda Z: fit_bias(Z, 3, method="paper"),
        lambda Z: fit_sfm(Z, 3),
    ],
)
def test_nan_rows_error_or_explicit_drop(fit):
    d = noisy3()
    Z = d.Z.copy()
    Z[[3, 17], 2] = np.nan
    Z[40, 0] = np.inf
    with pytest.raises(CalibrationError, match=r"3 row\(s\) with NaN/inf \(first at row 3\)"):
        fit(Z)


def test_drop_nonfinite_reports_count():
    d = noisy3()
    Z = d.Z.copy()
    Z[[3, 17], 2] = np.nan
    cal = fit_bias(Z, 3, drop_nonfinite=True)
    assert cal.diagnostics["n_dropped_nonfinite"] == 2
    assert cal.diagnostics["n_samples"] == len(Z) - 2


@pytest.mark.parametrize("method", ["centered", "paper"])
def test_too_few_samples(method):
    d = noisy3(n=8)
    with pytest.raises(CalibrationError, match="8 samples, at least 10"):
        fit_bias(d.Z, 3, method=method)


def test_constant_channel():
    d = noisy3()
    Z = d.Z.copy()
    Z[:, 5] = 4.2
    with pytest.raises(CalibrationError, match=r"channel\(s\) \[5\] are constant"):
        fit_bias(Z, 3)


@pytest.mark.parametrize("method", ["centered", "paper"])
def test_rank_deficient_excitation(method):
    # the load only turns in one plane: the force directions span 2 of 3 dimensions
    rng = np.random.default_rng(3)
    S = random_shape(3, 8, rng)
    t = rng.uniform(0, 2 * np.pi, 100)
    U = np.column_stack([np.cos(t), np.sin(t), np.zeros_like(t)])
    Z = 5 * U @ S + rng.normal(size=8)
    with pytest.raises(CalibrationError, match="rank-deficient excitation"):
        fit_bias(Z, 3, method=method)
    with pytest.raises(CalibrationError, match="rank-deficient excitation"):
        fit_sfm(5 * U @ S, 3)


def test_paper_needs_r_plus_one_channels():
    rng = np.random.default_rng(4)
    d = simulate(random_shape(3, 3, rng), 100, rng, offset=[1.0, 2.0, 3.0])
    with pytest.raises(CalibrationError, match=r"p >= r\+1 = 4 channels for dof=3, got p=3"):
        fit_bias(d.Z, 3, method="paper")
    cal = fit_bias(d.Z, 3, method="centered")  # the centered route handles p = r
    assert np.allclose(cal.offset, [1, 2, 3], atol=1e-8)


def test_bad_dof_and_method():
    d = noisy3()
    with pytest.raises(CalibrationError, match="dof must be 2, 3 or 6"):
        fit_bias(d.Z, 4)
    with pytest.raises(CalibrationError, match="method must be one of"):
        fit_bias(d.Z, 3, method="magic")
    with pytest.raises(CalibrationError, match="known loads"):
        fit_bias(d.Z, 6)


def test_least_squares_needs_spanning_loads():
    rng = np.random.default_rng(5)
    S = random_shape(3, 8, rng)
    M = np.column_stack([rng.normal(size=(20, 2)), np.zeros(20)])
    with pytest.raises(CalibrationError, match="span 2 of 3"):
        fit_least_squares(M @ S, M)
    with pytest.raises(CalibrationError, match="at least 3 known loads"):
        fit_least_squares(M[:2] @ S, M[:2])


def test_mirror_ambiguity_warned_with_two_pairs_resolved_with_three():
    rng = np.random.default_rng(6)
    S = random_shape(3, 8, rng)
    d = simulate(S, 100, rng, magnitude=2.0)
    M = rng.normal(size=(3, 3))
    with pytest.warns(CalibrationWarning, match="mirror"):
        fit_sfm(d.Z, 3, known_Z=M[:2] @ S, known_M=M[:2])
    with warnings.catch_warnings():
        warnings.simplefilter("error", CalibrationWarning)
        cal = fit_sfm(d.Z, 3, known_Z=M @ S, known_M=M)
    assert np.allclose(cal.C, d.C, atol=1e-9)


def test_shape_from_motion_without_offsets_does_not_warn_of_a_cap():
    """Without an offset to find, a cap costs the shape nothing measurable (4 known pairs,
    noise 5 % of each channel's signal, 20 random sensors: the 60 degree cap's held-out load
    error within 1.3x the sphere's, median), so the sfm route records its coverage and does
    not warn that the shape is unreliable."""
    from calib.simulation.simulate import sample_directions

    def error(cap, seed):
        rng = np.random.default_rng(seed)
        S = random_shape(3, 8, rng, condition=rng.uniform(1, 5))
        F = 10.0 * sample_directions(300, 3, rng, cap_half_angle_deg=cap)
        Z = F @ S + rng.normal(size=(300, 8)) * 0.05 * np.abs(F @ S).std(axis=0)
        with warnings.catch_warnings():
            warnings.simplefilter("error", CalibrationWarning)
            cal = fit_sfm(Z, 3, known_Z=Z[:4], known_M=F[:4])
        Ft = 10.0 * sample_directions(300, 3, rng)
        err = np.sqrt(np.mean(np.sum((cal.apply(Ft @ S) - Ft) ** 2, axis=1)))
        return err, cal.diagnostics["excitation_poor"]

    cap = [error(60.0, s) for s in range(20)]
    sphere = [error(180.0, s) for s in range(20)]
    assert all(poor for _, poor in cap) and not any(poor for _, poor in sphere)
    assert np.median([e for e, _ in cap]) < 1.3 * np.median([e for e, _ in sphere])
