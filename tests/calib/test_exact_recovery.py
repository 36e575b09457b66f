"""Noise-free data: C and offsets are recovered to 1e-8 relative (2-, 3- and 6-DOF, every route).

With more channels than load components any left inverse of the shape is exact on noise-free
readings; the routes that weigh channels by their noise (the bias routes' whitening)
return a weighted one, not the minimum-norm ``d.C``: for them ``C S^T = I`` is the check."""

import numpy as np
import pytest

from calib.estimators.bias import fit_bias
from calib.estimators.ft6 import fit_ft6, random_known_loads
from calib.estimators.least_squares import fit_least_squares
from calib.estimators.sfm import fit_sfm
from calib.simulation.simulate import random_shape, simulate

TOL = 1e-8


def rel(a, b):
    return np.max(np.abs(a - b)) / np.max(np.abs(b))


def known_pairs(S, z0, k, rng, magnitude):
    dof = S.shape[0]
    M = rng.normal(size=(k, dof)) * magnitude
    return M @ S + z0, M


@pytest.mark.parametrize("dof,p", [(2, 3), (2, 5), (3, 4), (3, 8)])
@pytest.mark.parametrize("seed", range(3))
def test_sfm_without_bias_exact(dof, p, seed):
    rng = np.random.default_rng(seed)
    S = random_shape(dof, p, rng)
    d = simulate(S, 60, rng, magnitude=7.0)
    Zk, Mk = known_pairs(S, 0.0, dof, rng, 7.0)
    cal = fit_sfm(d.Z, dof, known_Z=Zk, known_M=Mk)
    assert rel(cal.C, d.C) < TOL
    assert np.allclose(cal.apply(d.Z), d.loads, rtol=0, atol=TOL * 7)


@pytest.mark.parametrize("method,p", [("centered", 3), ("centered", 8), ("paper", 4), ("paper", 8)])
@pytest.mark.parametrize("seed", range(4))
def test_bias_exact_3dof(method, p, seed):
    rng = np.random.default_rng(100 + seed)
    S = random_shape(3, p, rng)
    z0 = rng.normal(size=p) * 5
    d = simulate(S, 80, rng, magnitude=3.0, offset=z0)
    Zk, Mk = known_pairs(S, z0, 3, rng, 3.0)
    cal = fit_bias(d.Z, 3, method=method, known_Z=Zk, known_M=Mk)
    assert rel(cal.C @ S.T, np.eye(3)) < TOL
    assert rel(cal.offset, z0) < TOL


@pytest.mark.parametrize("method,p", [("centered", 2), ("centered", 6), ("paper", 3), ("paper", 6)])
@pytest.mark.parametrize("seed", range(4))
def test_bias_exact_2dof(method, p, seed):
    rng = np.random.default_rng(200 + seed)
    S = random_shape(2, p, rng)
    z0 = rng.normal(size=p) * 5
    d = simulate(S, 40, rng, magnitude=2.0, offset=z0)
    Zk, Mk = known_pairs(S, z0, 2, rng, 2.0)
    cal = fit_bias(d.Z, 2, method=method, known_Z=Zk, known_M=Mk)
    assert rel(cal.C @ S.T, np.eye(2)) < TOL
    assert rel(cal.offset, z0) < TOL


@pytest.mark.parametrize("method", ["centered", "paper"])
@pytest.mark.parametrize("p", [6, 8])
@pytest.mark.parametrize("seed", range(3))
def test_ft6_exact(method, p, seed):
    rng = np.random.default_rng(300 + seed)
    S = random_shape(6, p, rng)
    z0 = rng.normal(size=p) * 2
    arm = rng.normal(size=3) * 0.1
    d = simulate(S, 150, rng, magnitude=10.0, offset=z0, lever_arm=arm)
    Mk = random_known_loads(6, rng, 10.0, 1.0)
    cal = fit_ft6(d.Z, Mk @ S + z0, Mk, bias=True, method=method)
    assert rel(cal.C, d.C) < TOL
    assert rel(cal.offset, z0) < TOL
    assert np.allclose(cal.diagnostics["lever_arm"], arm, atol=1e-8)


@pytest.mark.parametrize("dof,p", [(2, 4), (3, 8), (6, 8)])
def test_least_squares_exact(dof, p):
    rng = np.random.default_rng(7)
    S = random_shape(dof, p, rng)
    M = rng.normal(size=(3 * dof, dof))
    cal = fit_least_squares(M @ S, M)
    assert rel(cal.C, np.linalg.pinv(S.T)) < TOL
    z0 = rng.normal(size=p)
    cal = fit_least_squares(M @ S + z0, M, bias=True)
    assert rel(cal.C, np.linalg.pinv(S.T)) < TOL
    # only C z0 is identifiable from loads; it must reproduce the loads exactly
    assert np.allclose(cal.apply(M @ S + z0), M, atol=1e-9)


def test_paper_matrix_exact_both_methods():
    from calib.simulation.simulate import paper_trial

    d = paper_trial(1, rng=3)
    for method in ("paper", "centered"):
        cal = fit_bias(d.Z, 3, method=method, magnitude=d.magnitude)
        assert rel(cal.offset, d.offset) < TOL
        assert np.allclose(np.linalg.norm(cal.apply(d.Z), axis=1), d.magnitude, rtol=TOL)
