"""Gauges that are not linear: a misfit no affine model holds (stop 64; docs/calib.md, "Gauges
that are not linear (open)").

``simulate_payload_rig(nonlinearity=x)`` adds to every channel up to ``x`` of its spread as a random
quadratic form of the load's direction, on training and test readings alike. The forward fit
still reaches its model's optimum (the oracle, the same model from the true directions, measures
the same), but that model loses to least squares with every load known as ``x`` grows, and its
predicted error and ratio take the misfit for noise: at 5 % one fit of 30 was written at 3.73x
least squares, at 8 % six (3.0-3.7x), where the oracle is as far (a refusal would be right).
"""

import warnings

import numpy as np
import pytest

from calib import fit_joint, fit_least_squares
from calib.forward import Problem, fit_correlated, gls_inverse
from calib.joint import choose_known_poses
from calib.reliability import assess
from calib.simulate import simulate_payload_rig


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


@pytest.mark.xfail(strict=True, reason="open (stop 64): under 5 % gauge nonlinearity a fit at "
                   "3.73x least squares is written; the verdict takes the misfit for noise")
def test_a_strongly_nonlinear_sensor_is_not_written_beyond_3x_least_squares():
    joint, oracle, written = _fit(10_019, 0.05)  # 3.73x (oracle 3.74x), written
    assert not written or joint <= 3.0
