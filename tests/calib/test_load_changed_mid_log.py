"""A load that changes during a one-reading log, and offsets that drift over a short one: both
open (strict xfails).

The forward fit assumes one load magnitude at every unknown pose. A payload that changes during
the log breaks it: the gripper picks something up, a finger moves, a cable starts to pull. On
the payload study's default case with the last quarter of the training log 5 % heavier (stated
as before), least squares with every load known on the same readings measured 1.3-4.1x its
error on clean readings, and the joint fit 1.3-58x that least squares; of 15 rigs 3 were
written beyond 3x with exit 0 (3.5x, 5.6x, 18.5x; docs/calib.md, "A load that changes during
the log"). Its own predicted error does not see it: the Monte Carlo draws least squares' error
under the same misfit noise model, so their ratio stays small. A check of the log's halves
fitted alone is rejected: it refused the real wrist sensor's good fit (docs/calib_design.md).
"""

import warnings

import numpy as np
import pytest

from calib import fit_joint, fit_least_squares
from calib.routes.joint import choose_known_poses
from calib.simulation.simulate import simulate_payload_rig
from calib.verdict.reliability import assess


def rms(a):
    return float(np.sqrt(np.mean(np.sum(a**2, axis=1))))


def _written_or_within_3x(rig, tr, te, Z):
    """The payload study's protocol on training readings ``Z`` (rows ``tr`` of ``rig``, held-out
    rows ``te`` clean): refused, or within 3x least squares fitted on the same readings."""
    M = rig.stated_loads[rig.pose]
    kn = choose_known_poses(M[tr] / np.linalg.norm(M[tr], axis=1, keepdims=True), 4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = fit_joint(Z, Z[kn], M[tr][kn], 3, known_samples=1)
    ls = fit_least_squares(Z, M[tr], bias=True)
    ratio = rms(cal.apply(rig.Z[te]) - M[te]) / rms(ls.apply(rig.Z[te]) - M[te])
    return bool(assess(cal, Z[kn], M[tr][kn])) or ratio <= 3.0


@pytest.mark.xfail(strict=True, reason="open: a load that changes during the log is "
                   "fitted and written far beyond least squares; docs/calib.md")
def test_a_load_that_changes_during_the_log_is_not_written_far_beyond_least_squares():
    rig = simulate_payload_rig(10_010, poses=80)
    tr, te = rig.split("poses")
    M = rig.stated_loads[rig.pose]
    Z = rig.Z[tr].copy()
    q = len(Z) * 3 // 4
    o = fit_least_squares(rig.Z[tr], M[tr], bias=True).offset
    Z[q:] = o + 1.05 * (Z[q:] - o)  # the last quarter 5 % heavier, stated as before
    assert _written_or_within_3x(rig, tr, te, Z)  # 18.5x, written with exit 0


@pytest.mark.xfail(strict=True, reason="open: offsets drifting 2 % over a 20-reading "
                   "log are written at 3.1-4.0x least squares on the same readings; docs/calib.md")
def test_offsets_drifting_over_a_short_log_are_not_written_far_beyond_least_squares():
    # the payload study's 20-pose case (seed 10,002): every channel's offset drifts 2 % of its
    # span over the training log; one-reading logs have no drift term. 3.97x, written
    rig = simulate_payload_rig(10_002, poses=40)
    tr, te = rig.split("poses")
    Z = rig.Z[tr] + np.linspace(0, 1, len(tr))[:, None] * 0.02 * np.ptp(rig.Z[tr], axis=0)
    assert _written_or_within_3x(rig, tr, te, Z)
