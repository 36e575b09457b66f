"""A load that changes during a one-reading log, and the check that finds it (calib.halves).

The forward fit assumes one load magnitude at every unknown pose. A payload that changes during
the log breaks it: the gripper picks something up, a finger moves, a cable starts to pull. On
the payload study's default case with the last quarter of the training log 5 % heavier (stated
as before), least squares with every load known on the same readings measured 1.3-4.1x its
error on clean readings, and the joint fit 1.3-58x that least squares; before the check, 3 of 15
rigs were written beyond 3x with exit 0 (3.5x, 5.6x, 18.5x; docs/calib.md, "A load that changes
during the log"). Its own predicted error does not see it: the misfit passes for noise the
channels share. The log's halves, fitted alone, do not agree.
"""

import warnings

import numpy as np

from calib import fit_joint, fit_least_squares
from calib.halves import HALVES_P
from calib.joint import choose_known_poses
from calib.reliability import assess
from calib.simulate import simulate_payload_rig


def rms(a):
    return float(np.sqrt(np.mean(np.sum(a**2, axis=1))))


def _fit(seed, heavier=1.0, scale=None, order=None):
    rig = simulate_payload_rig(seed, poses=80)
    tr, te = rig.split("poses")
    M = rig.stated_loads[rig.pose]
    Z = rig.Z[tr].copy()
    q = len(Z) * 3 // 4
    o = fit_least_squares(rig.Z[tr], M[tr], bias=True).offset
    Z[q:] = o + heavier * (Z[q:] - o)  # the last quarter heavier, stated as before
    if scale is not None:  # units and channel order: the check must not notice them
        Z = (Z * scale)[:, order]
    kn = choose_known_poses(M[tr] / np.linalg.norm(M[tr], axis=1, keepdims=True), 4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = fit_joint(Z, Z[kn], M[tr][kn], 3, known_samples=1)
    return rig, tr, te, M, Z, kn, cal


def test_a_load_that_changes_during_the_log_is_not_written_far_beyond_least_squares():
    rig, tr, te, M, Z, kn, cal = _fit(10_010, 1.05)
    ls = fit_least_squares(Z, M[tr], bias=True)
    ratio = rms(cal.apply(rig.Z[te]) - M[te]) / rms(ls.apply(rig.Z[te]) - M[te])
    assert ratio > 3.0  # the fit itself is still far off (18.5x): the verdict must say so
    reasons = assess(cal, Z[kn], M[tr][kn])
    assert any("not one rig throughout" in r for r in reasons), reasons
    assert cal.diagnostics["joint"]["halves"]["p"] < HALVES_P


def test_the_halves_check_passes_logs_of_one_rig_and_ignores_units_and_order():
    ps = []
    for seed in (10_020, 10_021, 10_022):
        _, _, _, _, Z, kn, cal = _fit(seed)
        hv = cal.diagnostics["joint"]["halves"]
        assert hv["checked"] and hv["readings"] == [20, 20]
        assert not any("not one rig" in r for r in assess(cal)), hv
        ps.append(hv["p"])
    assert max(ps) > 0.05  # p-values of logs without a change are not all small
    rng = np.random.default_rng(3)
    scale = np.exp(rng.uniform(np.log(1e-4), np.log(1e4), 8))
    order = rng.permutation(8)
    *_, cal2 = _fit(10_020, scale=scale, order=order)
    hv0 = _fit(10_020)[-1].diagnostics["joint"]["halves"]
    hv2 = cal2.diagnostics["joint"]["halves"]
    np.testing.assert_allclose(hv2["disagreement_rms"], hv0["disagreement_rms"], rtol=1e-3)
    np.testing.assert_allclose(hv2["noise_sd_ratio"], hv0["noise_sd_ratio"][order], rtol=1e-3)


def test_a_gain_that_jumps_during_the_log_is_found():
    rig = simulate_payload_rig(10_030, poses=80)
    tr, _ = rig.split("poses")
    M = rig.stated_loads[rig.pose]
    Z = rig.Z[tr].copy()
    o = rig.offset
    Z[20:, 0] = o[0] + 1.3 * (Z[20:, 0] - o[0])  # channel 0's gain 30 % up from mid-log
    kn = choose_known_poses(M[tr] / np.linalg.norm(M[tr], axis=1, keepdims=True), 4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = fit_joint(Z, Z[kn], M[tr][kn], 3, known_samples=1)
    assert cal.diagnostics["joint"]["halves"]["p"] < HALVES_P
