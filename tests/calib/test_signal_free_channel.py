"""A channel that reads no load, a load weaker than its noise, or repeats another.

Real sensors can have one: an unloaded gauge, or the torque about the tool axis of a commercial
F/T sensor holding a gripper whose centre of mass lies on that axis (``T_z = r_x F_y - r_y F_x``
is then 0 in every pose). With start weights of one spread a channel the fit could collapse onto
a channel of noise alone (that choice made that channel's noise the largest residual the
directions could take up: 17.8x and 106x least squares, written), and the offset rule refused
one-reading fits over such a channel's span (docs/calib.md, "A channel that reads no load").
A channel that repeats another defeats the start weights that regress each channel on every other
(docs/calib_design.md).
"""

import warnings

import numpy as np
import pytest

from calib import fit_joint, fit_least_squares
from calib.routes.joint import choose_known_poses
from calib.simulation.simulate import simulate_payload_rig, simulate_rig
from calib.verdict.reliability import assess


def rms(a):
    return float(np.sqrt(np.mean(a**2)))


def payload_fit(rig, Z):
    """The payload study's protocol on readings ``Z`` of ``rig``: every other pose trains, 4
    known loads on the poses ``choose_known_poses`` picks. Returns (fit, its held-out rms over
    least squares' with every load known, known readings, known loads)."""
    tr, te = rig.split("poses")
    M = rig.stated_loads[rig.pose]
    kn = choose_known_poses(M[tr] / np.linalg.norm(M[tr], axis=1, keepdims=True), 4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = fit_joint(Z[tr], Z[tr][kn], M[tr][kn], 3, known_samples=1)
    ls = fit_least_squares(Z[tr], M[tr], bias=True)
    ratio = rms(cal.apply(Z[te]) - M[te]) / rms(ls.apply(Z[te]) - M[te])
    return cal, ratio, Z[tr][kn], M[tr][kn]


def test_static_rig_with_a_noise_only_channel_is_fitted_well():
    # the rig study's target case plus a ninth channel of noise alone (15x the others' noise):
    # 17.8x least squares, written, with one spread a channel as the start weights
    rig = simulate_rig(18, hysteresis=0, creep=0, wander=0, misalignment_deg=0, mass_error=0,
                       nonlinearity=0.01, drift=0.005)
    Z = np.c_[rig.Z, np.random.default_rng(18).normal(size=len(rig.Z)) * 3.0]
    tr, te = rig.split()
    M = rig.stated_loads[rig.pose]
    kn = choose_known_poses(rig.directions, 4)
    means = np.array([Z[tr][rig.pose[tr] == j].mean(axis=0) for j in range(12)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = fit_joint(Z[tr], means[kn], rig.stated_loads[kn], known_samples=len(tr) // 12,
                        model="auto", drift="none")
    ls = fit_least_squares(Z[tr], M[tr], bias=True)
    ratio = rms(cal.apply(Z[te]) - M[te]) / rms(ls.apply(Z[te]) - M[te])
    assert ratio < 1.5 and not assess(cal, means[kn], rig.stated_loads[kn])  # 1.12x, made


def test_wrench_sensor_with_the_centre_of_mass_on_the_axis_is_not_refused():
    rig = simulate_payload_rig(10_000, poses=80, wrench=True)
    Z = rig.Z.copy()
    rng = np.random.default_rng(7)
    Z[:, 5] = Z[:, 5].mean() + rng.normal(size=len(Z)) * Z[:, 5].std() * 0.01  # T_z: noise
    cal, ratio, Zk, Mk = payload_fit(rig, Z)
    assert ratio < 1.5  # the fit itself is good (1.3x, as the oracle) ...
    # ... and made: T_z's offset (8 % of its span, which is noise) is left out of the rule
    assert not assess(cal, Zk, Mk)
    d = cal.diagnostics
    assert d["offset_identified"] and not d["offset_rule_channels"][5]
    assert d["offset_rule_channels"][:5].all() and d["offset_stderr_rel_span"][5] > 0.05


def test_weak_torque_channel_is_not_refused():
    # T_z reads 1 % of its load, as much as its noise: its column of C is significant, but its
    # span is noise; an offset rule over the channel's span refused 11 of 20 such fits at the
    # oracle's error
    ok = []
    for seed in (0, 1, 2):
        rig = simulate_payload_rig(10_000 + seed, poses=80, wrench=True)
        Z = rig.Z.copy()
        rng = np.random.default_rng(seed + 7)
        c, sd = Z[:, 5].mean(), Z[:, 5].std()
        Z[:, 5] = c + (Z[:, 5] - c) * 0.01 + rng.normal(size=len(Z)) * sd * 0.01
        cal, ratio, Zk, Mk = payload_fit(rig, Z)
        d = cal.diagnostics
        assert ratio < 1.5  # 0.98-1.32x, as the oracle
        assert d["offset_stderr_rel_span"][5] > 0.05  # refused by the old rule (5.2-5.7 %)
        assert d["offset_stderr_reach_load_span"][5] < 1e-3 * 0.05
        ok.append(not assess(cal, Zk, Mk) and not d["offset_rule_channels"][5])
    assert all(ok)


def _rule(C, off_se, span, load_span, cov=None):
    """The offset rule's diagnostics for a fit with map C and offset standard errors off_se;
    ``cov`` the offset's covariance (default: independent), False for none (the rig routes)."""
    from calib.data.result import Calibration, add_uncertainty

    cal = Calibration(C=C, offset=np.zeros(C.shape[1]), dof=C.shape[0], method="joint",
                      diagnostics={})
    kw = {} if cov is False else {
        "offset_cov": np.diag(off_se**2) if cov is None else cov, "load_span": load_span}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        add_uncertainty(cal, off_se, np.full(C.shape, 1e-3), span, **kw)
    return cal.diagnostics


def test_a_channel_is_left_out_only_where_its_offset_barely_reaches_the_loads():
    # channels 0-2 carry the loads one each (span 1, loads' span 1); channel 3 carries 1e-3
    C = np.array([[1.0, 0.0, 0.0, 1e-3], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    span, load_span = np.ones(4), np.ones(3)
    # channel 3's offset at 20 % of its span reaches 0.02 % of the loads: left out
    d = _rule(C, np.array([0.01, 0.01, 0.01, 0.2]), span, load_span)
    assert d["offset_identified"] and list(d["offset_rule_channels"]) == [True] * 3 + [False]
    assert d["offset_stderr_reach_load_span"][3] == pytest.approx(2e-4)
    # channel 0's offset at 30 % of its span reaches 30 % of the loads: judged, refused
    d = _rule(C, np.array([0.3, 0.01, 0.01, 0.2]), span, load_span)
    assert not d["offset_identified"] and d["offset_rule_channels"].all()
    # a lost fit: every channel fails the rule, every channel is judged
    d = _rule(C, np.array([0.1, 0.1, 0.1, 0.2]), span, np.full(3, 1e3))
    assert not d["offset_identified"] and d["offset_rule_channels"].all()
    # the channels' errors, each negligible, add up beyond the limit through their
    # correlations: judged
    C2 = np.c_[np.eye(3), np.full((3, 6), 0.02)]
    off_se = np.r_[np.full(3, 0.01), np.full(6, 0.4)]
    d = _rule(C2, off_se, np.ones(9), np.ones(3))
    assert list(d["offset_rule_channels"]) == [True] * 3 + [False] * 6  # independent: 2.2 %
    d = _rule(C2, off_se, np.ones(9), np.ones(3), cov=np.outer(off_se, off_se) * (
        0.999 * np.ones((9, 9)) + 0.001 * np.eye(9)))
    assert d["offset_rule_channels"].all() and not d["offset_identified"]  # correlated: 5.8 %
    # without the offset's covariance (the rig routes), every channel is judged
    d = _rule(C, np.array([0.01, 0.01, 0.01, 0.2]), span, load_span, cov=False)
    assert not d["offset_identified"] and d["offset_rule_channels"].all()


def test_one_reading_rig_with_an_added_noise_only_channel_is_fitted_well():
    # the payload study's default case (8 gauges, 40 training poses), seed 5, plus a ninth
    # channel of noise alone: with one spread a channel as the start weights the oracle itself
    # measured 9.3x, the joint fit 106x, exit 0
    rig = simulate_payload_rig(10_005, poses=80)
    rng = np.random.default_rng(10_012)
    Z = np.c_[rig.Z, rng.normal(size=len(rig.Z)) * rig.Z.std(axis=0).mean() * 0.01]
    cal, ratio, Zk, Mk = payload_fit(rig, Z)
    assert ratio < 1.5 and not assess(cal, Zk, Mk)  # 1.00x, made


# A channel that repeats another: one gauge read twice, or a wrench logged beside the gauges
# it was mixed from. Its noise is the other's, so regressed on every other channel (the
# start weights that regress each channel on every other) both are predicted to the repeat's own
# noise (the Heywood case) and take almost all the weight.


def _factor_readings(rng, P=200, p=8, r=3):
    """Readings of a random linear sensor (p channels of mixed units) of unit loads in r
    dimensions, each channel with its own independent noise; returns (Y, noise sd, M)."""
    U = rng.normal(size=(P, r))
    M = U / np.linalg.norm(U, axis=1, keepdims=True)
    scale = 10.0 ** rng.uniform(-2, 2, p)
    A = rng.normal(size=(p, r)) * scale[:, None]
    sd = scale * rng.uniform(0.002, 0.02, p)
    return M @ A.T + rng.normal(size=(P, p)) * sd + rng.normal(size=p) * scale, sd, M


@pytest.mark.parametrize("seed", range(5))
def test_start_variances_are_about_each_channels_noise_even_where_a_channel_is_repeated(seed):
    from calib.estimators.forward.problem import Problem
    from calib.estimators.forward.variances import start_variances

    rng = np.random.default_rng(seed)
    Y, sd, M = _factor_readings(rng)
    P = len(Y)
    # channel 8 repeats channel 1 (its own noise 1e-4 of channel 1's); channel 9 reads no load
    Y = np.c_[Y, -3.0 * Y[:, 1] + 1e-4 * sd[1] * rng.normal(size=P),
              5.0 + 0.7 * rng.normal(size=P)]
    v = start_variances(Problem(Y, None, None, np.arange(4), M[:4]))
    ratio = np.sqrt(v[:8]) / sd
    # about each channel's noise, at or above it (Guttman: the variance left after regressing
    # on the others bounds a channel's own from above; measured 0.9-15x)
    assert np.all((ratio > 0.7) & (ratio < 30.0)), ratio
    # the repeated pair too: regressed on every other channel it would get the repeat's
    # own noise, 1e-4 of its real noise
    assert 0.7 < np.sqrt(v[8]) / (3.0 * sd[1]) < 30.0
    assert np.sqrt(v[9]) == pytest.approx(Y[:, 9].std(), rel=0.05)  # its whole variance
    # equivariant: units (factors 1e-4..1e4) and order
    f = 10.0 ** rng.uniform(-4, 4, Y.shape[1])
    perm = rng.permutation(Y.shape[1])
    v2 = start_variances(Problem((Y * f)[:, perm], None, None, np.arange(4), M[:4]))
    np.testing.assert_allclose(v2, (v * f**2)[perm], rtol=1e-6)


def test_one_reading_rig_with_a_repeated_channel_is_fitted_well():
    # the payload study's default case, seed 2, channel 1 repeated (x2, its own noise 1e-4 of
    # its span): with the start weights that regress each channel on every other 3.55x least
    # squares, written outside its interval; 1.08x without the repeat
    rig = simulate_payload_rig(10_002, poses=80)
    tr, _ = rig.split("poses")
    rng = np.random.default_rng(2)
    Z = np.c_[rig.Z, 2 * rig.Z[:, 1] + 1e-4 * np.ptp(rig.Z[tr, 1]) * rng.normal(size=len(rig.Z))]
    cal, ratio, Zk, Mk = payload_fit(rig, Z)
    assert ratio < 2.0 and not assess(cal, Zk, Mk)  # 1.41x, made
