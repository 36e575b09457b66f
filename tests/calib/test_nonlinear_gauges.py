"""Gauges that are not linear: a misfit no affine model holds (docs/calib.md, "Limits";
docs/calib_design.md).

``simulate_payload_rig(nonlinearity=x)`` adds to every channel up to ``x`` of its spread as a random
quadratic form of the load's direction, on training and test readings alike. The forward fit
still reaches its model's optimum (the oracle, the same model from the true directions, measures
the same), but that model loses to least squares with every load known as ``x`` grows, and its
predicted error and ratio take the misfit for noise: at 5 % one fit of 30 was written at 3.73x
least squares, at 8 % six (3.0-3.7x), where the oracle is as far (a refusal would be right).

What the fit does about it: it tells.
:func:`calib.estimators.forward.misfit.direction_misfit` tests
whether the residuals of nearby load directions agree (a misfit of the direction) beyond noise;
where they do, ``fit_joint`` warns that the predicted error and ratio can be low, and
(:func:`calib.verdict.predicted_error.one_sided`) states no upper end of the error: the lower end
holds.
"""

import json
import warnings

import numpy as np
import pytest

from calib import fit_joint, fit_least_squares
from calib.cli import main
from calib.data.io import write_csv
from calib.data.result import CalibrationError
from calib.estimators.forward.correlated import fit_correlated
from calib.estimators.forward.fit import fit_forward
from calib.estimators.forward.misfit import DIRECTION_ALPHA, direction_misfit
from calib.estimators.forward.problem import Problem
from calib.routes.joint import choose_known_poses
from calib.simulation.simulate import simulate_payload_rig
from calib.verdict.predicted_error import gls_inverse
from calib.verdict.reliability import assess


def rms(a):
    return float(np.sqrt(np.mean(np.sum(a**2, axis=1))))


def _fit(seed, nonlinearity):
    """The payload study's protocol: returns (joint / LS, oracle / LS, written)."""
    rig = simulate_payload_rig(seed, poses=80, nonlinearity=nonlinearity)
    tr, te = rig.split("poses")
    M = rig.stated_loads[rig.pose]
    Z, Mt = rig.Z[tr], M[tr]
    kn = choose_known_poses(Mt / np.linalg.norm(Mt, axis=1, keepdims=True), 4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = fit_joint(Z, Z[kn], Mt[kn], 3, known_samples=1)
        pr = Problem(Z, None, None, kn, Mt[kn], magnitude=rig.magnitude)
        U = Mt[pr.unknown] / np.linalg.norm(Mt[pr.unknown], axis=1, keepdims=True)
        _, f, T, T_inv, _ = fit_correlated(pr, only={"truth": U})
    ls = rms(fit_least_squares(Z, Mt, bias=True).apply(rig.Z[te]) - M[te])
    joint = rms(cal.apply(rig.Z[te]) - M[te])
    oracle = rms((rig.Z[te] - T_inv @ f["o"]) @ (gls_inverse(f["A"], f["v"]) @ T).T - M[te])
    return joint / ls, oracle / ls, not assess(cal, Z[kn], Mt[kn])


@pytest.mark.parametrize("seed", [10_000, 10_002, 10_007])
def test_nonlinear_gauges_are_fitted_to_the_models_optimum(seed):
    """At 2 % nonlinearity the fit measures what its model fitted from the true directions
    measures (30 rigs: within 1.03x), and it is written (below 3x least squares)."""
    joint, oracle, written = _fit(seed, 0.02)
    assert joint <= 1.05 * oracle, (joint, oracle)
    assert written and joint < 3.0


@pytest.mark.xfail(strict=True, reason="open: under 5 % gauge nonlinearity a fit at "
                   "3.73x least squares is written (with no upper end of its error "
                   "stated); the verdict's ratio takes the misfit for noise")
def test_a_strongly_nonlinear_sensor_is_not_written_beyond_3x_least_squares():
    joint, oracle, written = _fit(10_019, 0.05)  # 3.73x (oracle 3.74x), written
    assert not written or joint <= 3.0


def _warned(seed, **kw):
    """fit_joint on the payload study's training readings: (direction_misfit's diagnostics,
    whether it warned)."""
    rig = simulate_payload_rig(seed, poses=80, **kw)
    tr, _ = rig.split("poses")
    Mt = rig.stated_loads[rig.pose][tr]
    kn = choose_known_poses(Mt / np.linalg.norm(Mt, axis=1, keepdims=True), 4)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cal = fit_joint(rig.Z[tr], rig.Z[tr][kn], Mt[kn], 3, known_samples=1)
    said = any("nearby load directions agree" in str(w.message) for w in caught)
    return cal.diagnostics["joint"]["direction_misfit"], said


@pytest.mark.parametrize("seed", [10_000, 10_001, 10_002])
def test_a_sensor_far_from_linear_is_told(seed):
    """5 % nonlinear gauges: found (measured on 10 rigs: 10 of 10, at 2 %: 8 of 10)."""
    d, said = _warned(seed, nonlinearity=0.05)
    assert d["tested"] and d["p_value"] < DIRECTION_ALPHA and d["rho"] > 0.2
    assert said


@pytest.mark.parametrize("kw", [{}, {"wrench": True}, {"wrench": True, "gauges": 8},
                                {"p": 12, "noise": (0.01, 0.05)}])
def test_linear_gauges_are_not_taken_for_nonlinear(kw):
    """Linear gauges, independent or mixed noise: not flagged (measured on 40 rigs: p >= 0.18;
    here 3 rigs a case)."""
    for seed in (10_003, 10_004, 10_005):
        d, said = _warned(seed, **kw)
        assert d["tested"] and d["p_value"] >= DIRECTION_ALPHA and not said


def test_the_direction_test_is_unit_free_and_order_free():
    """The same rho and p with every channel rescaled (1e-4..1e4), permuted and offset."""
    rig = simulate_payload_rig(10_001, poses=80, nonlinearity=0.03)
    tr, _ = rig.split("poses")
    Mt = rig.stated_loads[rig.pose][tr]
    kn = choose_known_poses(Mt / np.linalg.norm(Mt, axis=1, keepdims=True), 4)
    Z = rig.Z[tr]
    rng = np.random.default_rng(0)
    scale = np.exp(rng.uniform(np.log(1e-4), np.log(1e4), Z.shape[1]))
    perm = rng.permutation(Z.shape[1])
    shift = rng.normal(size=Z.shape[1]) * 1e3

    def test(Zx):
        pr = Problem(Zx, None, None, kn, Mt[kn], magnitude=rig.magnitude)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return direction_misfit(pr, fit_forward(pr))

    a, b = test(Z), test((Z * scale + shift)[:, perm])
    assert a["p_value"] < DIRECTION_ALPHA
    assert abs(a["rho"] - b["rho"]) < 1e-6 and a["p_value"] == b["p_value"]


def _calib_fit(tmp_path, capsys, rig):
    """``calib fit --method joint`` on the rig's training log, 4 known poses as `calib plan`
    picks them: (exit code, stdout, stderr)."""
    tr, _ = rig.split("poses")
    Z, Mt = rig.Z[tr], rig.stated_loads[rig.pose][tr]
    kn = choose_known_poses(Mt / np.linalg.norm(Mt, axis=1, keepdims=True), 4)
    ch = [f"g{i}" for i in range(Z.shape[1])]
    write_csv(tmp_path / "log.csv", ch, Z)
    write_csv(tmp_path / "known.csv", ch + ["Fx", "Fy", "Fz"], np.hstack([Z[kn], Mt[kn]]))
    code = main(["fit", str(tmp_path / "log.csv"), "--dof", "3", "--method", "joint",
                 "--known", str(tmp_path / "known.csv"), "--known-samples", "1",
                 "--out", str(tmp_path / "cal.json")])
    out, err = capsys.readouterr()
    return code, out, err


def test_calib_fit_prints_the_warning_and_still_writes(tmp_path, capsys):
    """The command line: one warning line, exit 0, the file written."""
    code, out, err = _calib_fit(tmp_path, capsys,
                                simulate_payload_rig(10_000, poses=80, nonlinearity=0.05))
    assert code == 0, err
    assert (tmp_path / "cal.json").is_file()
    lines = [x for x in err.splitlines() if "nearby load directions agree" in x]
    assert len(lines) == 1 and lines[0].startswith("calib: warning:")
    # the summary's word says as much, not a plain "reliable"
    assert out.rstrip().endswith("reliable only as far as an affine sensor goes: this one reads "
                                 "as not linear in the load, so its error has no stated upper "
                                 "end (calib evaluate on known loads left out of the fit "
                                 "measures it)")
    # and the predicted error is stated as what it is: a lower end only
    assert "predicted held-out error at least " in out and "no upper end" in out
    saved = json.loads((tmp_path / "cal.json").read_text())
    pe = saved["diagnostics"]["joint"]["predicted_error"]
    assert pe["upper_bounded"] is False and pe["interval"][1] is None
    assert pe["interval"][0] == pe["interval_if_linear"][0] < pe["interval_if_linear"][1]
    assert "calib evaluate" in lines[0]


def test_a_linear_sensors_summary_says_plainly_reliable(tmp_path, capsys):
    code, out, err = _calib_fit(tmp_path, capsys, simulate_payload_rig(10_003, poses=80))
    assert code == 0, err
    assert out.rstrip().endswith("; reliable") and "nearby load directions" not in err
    assert "predicted held-out error at least" not in out
    pe = json.loads((tmp_path / "cal.json").read_text())["diagnostics"]["joint"]["predicted_error"]
    assert pe["upper_bounded"] is True and pe["interval"][0] < pe["rms"] < pe["interval"][1]


@pytest.fixture(scope="module")
def strongly_nonlinear_fits(payload_joint):
    """12 payload rigs 5 % nonlinear (seeds 14,000 on: not used while the one-sided interval was
    built): (measured held-out error, predicted_error) per rig."""
    fits = [payload_joint(seed, nonlinearity=0.05) for seed in range(14_000, 14_012)]
    return [(f.err, f.cal.diagnostics["joint"]["predicted_error"]) for f in fits]


def test_the_stated_interval_holds_where_the_sensor_is_not_linear(strongly_nonlinear_fits):
    """Where the direction test finds the sensor not linear, no upper end is stated, and the
    lower end holds: every miss of the affine interval lies above it (seeds 20,000-20,029: 12 of
    30 at 5 %, 5 of 30 at 2 %, none below). So the interval as stated covers the measured error
    on at least 11 of 12 rigs; the affine interval, still in the diagnostics, misses at least 2
    (it would be stated otherwise: this test fails without
    :func:`calib.verdict.predicted_error.one_sided`)."""
    res = strongly_nonlinear_fits
    inside = sum(pe["interval"][0] <= e <= pe["interval"][1] for e, pe in res)
    assert inside >= 11, [(e, pe["interval"]) for e, pe in res]
    one_sided = [(e, pe) for e, pe in res if pe["upper_bounded"] is False]
    assert len(one_sided) >= 10  # found on 30 of 30 at 5 %
    assert all(e >= pe["interval"][0] for e, pe in one_sided)
    affine = sum(pe["interval_if_linear"][0] <= e <= pe["interval_if_linear"][1]
                 for e, pe in one_sided)
    assert affine <= len(one_sided) - 2, (affine, len(one_sided))


def test_a_channels_own_signal_bent_is_the_same_rig_plus_its_bend():
    """``nonlinearity_kind="signal"``: each channel reads its linear signal bent, ``spread (a x^2
    + b x^3)`` with ``|a|, |b| <= nonlinearity``; every other draw is the linear rig's."""
    lin = simulate_payload_rig(10_001, poses=80)
    bent = simulate_payload_rig(10_001, poses=80, nonlinearity=0.05, nonlinearity_kind="signal")
    spread = lin.magnitude * np.linalg.norm(lin.S, axis=0)
    x = (lin.true_loads @ lin.S) / spread
    extra = (bent.Z - lin.Z) / spread
    assert np.all(np.abs(extra) <= 0.1 * np.max(x**2, axis=0) + 1e-12)
    # a quadratic plus a cubic of the channel's own signal, to rounding
    for c in range(x.shape[1]):
        coef = np.linalg.lstsq(np.column_stack([x[:, c] ** 2, x[:, c] ** 3]), extra[:, c],
                               rcond=None)[0]
        assert np.all(np.abs(coef) <= 0.05 + 1e-12)
        assert np.allclose(np.column_stack([x[:, c] ** 2, x[:, c] ** 3]) @ coef, extra[:, c],
                           atol=1e-12)


def test_an_unknown_nonlinearity_kind_is_a_one_line_error():
    with pytest.raises(CalibrationError, match="nonlinearity_kind must be 'direction' or "
                       "'signal', got 'cubic'"):
        simulate_payload_rig(1, nonlinearity=0.02, nonlinearity_kind="cubic")
