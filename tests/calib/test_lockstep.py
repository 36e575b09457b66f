"""The lockstep refits (:mod:`calib.estimators.forward.lockstep`) take the serial solver's
decisions: every simulated log reaches the point :func:`solve` and the feasible-GLS rounds
reach one log at a time, on rigs of every shape the refits meet."""

import numpy as np
import pytest

import calib.estimators.forward.refits as refits
from calib.estimators.forward.lockstep import Batch, solve_batch
from calib.estimators.forward.problem import Problem, curvature, solve
from calib.routes.joint import choose_known_poses
from calib.simulation.simulate import sample_directions


def _rig(seed, p, r, poses, readings, fit_g, noise=0.02):
    """A random linear sensor (channel scales 1e-2..1e2) and its truth as a fit's dict."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(p, r)) * np.exp(rng.uniform(np.log(1e-2), np.log(1e2), p))[:, None]
    o = rng.normal(size=p) * np.abs(A).sum(axis=1) * 3
    U = sample_directions(poses, r, rng, cap_half_angle_deg=120)
    g = 7.5
    M = g * U
    sd = noise * np.abs(A).sum(axis=1) * g * np.exp(rng.uniform(-1, 1, p))
    Y = M @ A.T + o + rng.normal(size=(poses, p)) * sd / np.sqrt(readings)
    known = choose_known_poses(U, 4)
    pr = Problem(Y, np.full(poses, float(readings)), sd if readings > 1 else None, known,
                 M[known], magnitude=None if fit_g else g)
    v = sd**2 * (0.5 if readings > 1 else 1.0)
    fit = {"A": A, "o": o, "U": U[pr.unknown], "g": g, "M": M, "v": v, "v0": None,
           "W": pr.weights(v)}
    return pr, fit


CASES = [  # (p, r, poses, readings per pose, g fitted)
    (8, 3, 30, 1, False), (8, 3, 30, 1, True), (6, 3, 80, 1, False), (12, 3, 25, 1, True),
    (3, 3, 40, 1, False), (5, 3, 14, 20, False), (4, 2, 20, 1, False), (7, 2, 12, 10, True)]


@pytest.mark.parametrize("p,r,poses,readings,fit_g", CASES)
def test_the_lockstep_refits_are_the_serial_refits(monkeypatch, p, r, poses, readings, fit_g):
    """Each case's 8 simulated logs, refitted in lockstep and one by one (the lockstep path
    forced to fail): the same variance logs, parameter spreads and residual autocorrelation
    to 1e-7 (measured: about 1e-12; a wrong damping, acceptance or stopping rule moves them
    by 1e-4 or more: a solver stopped one iteration early fails this)."""
    pr, fit = _rig(1000 + p * 10 + poses, p, r, poses, readings, fit_g)
    kw = {"reps": 8, "seed": 3, "rho": np.full(p, 0.3), "n": pr.P, "spreads": True}
    fit = {**fit, "schur": curvature(pr, fit)["schur"]}
    lock = refits._refits(pr, fit, **kw)

    def fail(*a, **k):
        raise ValueError("forced")

    monkeypatch.setattr(refits, "_refit_lockstep", fail)
    serial = refits._refits(pr, fit, **kw)
    assert lock is not None and serial is not None
    for key in ("logs", "fit_spread", "ls_spread", "lag1"):
        np.testing.assert_allclose(lock[key], serial[key], rtol=1e-7, atol=1e-9, err_msg=key)


@pytest.mark.parametrize("fit_g", [False, True])
def test_solve_batch_stops_where_solve_stops(fit_g):
    """From random directions (steps rejected, the damping raised and lowered): every log's
    cost, iterations and convergence flag as :func:`solve` gives them one at a time (a damping
    divided by 3 instead of 5 on acceptance changes the iterations and fails this)."""
    pr, fit = _rig(77, 8, 3, 30, 1, fit_g)
    rng = np.random.default_rng(5)
    Ys = pr.Y[None] + rng.normal(size=(5, *pr.Y.shape)) * np.sqrt(fit["v"])
    U0 = rng.normal(size=fit["U"].shape)  # random directions: steps rejected, damping raised
    bt = Batch(pr, Ys)
    W = np.broadcast_to(pr.weights(fit["v"]), Ys.shape)
    b = len(Ys)
    out = solve_batch(bt, np.broadcast_to(U0, (b, *U0.shape)), np.full(b, 7.0), W,
                      np.broadcast_to(fit["A"], (b, *fit["A"].shape)),
                      np.broadcast_to(fit["o"], (b, pr.p)), max_iter=30)
    for i in range(b):
        one = solve(bt.problem(i), U0, 7.0, W[i], fit["A"], fit["o"], max_iter=30)
        assert out["iterations"][i] == one["iterations"]
        assert out["converged"][i] == one["converged"]
        np.testing.assert_allclose(out["cost"][i], one["cost"], rtol=1e-9)
        np.testing.assert_allclose(out["A"][i], one["A"], rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("p,r,fit_g", [(8, 3, False), (5, 3, True), (4, 2, False)])
def test_the_random_starts_alternate_in_lockstep_as_one_by_one(p, r, fit_g):
    """Eight random starts alternated at once reach the directions each reaches alone
    (:func:`alternate`), whichever iteration each stops at (to 1e-6: the alternation stops
    short of the optimum, where the batched products' rounding moved directions by up to 7e-9;
    a wrong global step, or a start stopped once its poses move by less than 1e-2, fails it)."""
    from calib.estimators.forward.lockstep import alternate_batch
    from calib.estimators.forward.problem import alternate

    pr, fit = _rig(300 + p, p, r, 40, 1, fit_g)
    rng = np.random.default_rng(8)
    Us = rng.normal(size=(8, len(pr.unknown), r))
    Us /= np.linalg.norm(Us, axis=2, keepdims=True)
    W = pr.weights(fit["v"])
    together = alternate_batch(pr, Us, 7.5, W)
    for i, U in enumerate(Us):
        np.testing.assert_allclose(together[i], alternate(pr, U, 7.5, W), atol=1e-6)


@pytest.mark.parametrize("fit_g", [False, True])
def test_the_starts_refitted_under_the_final_weights_are_solves_one_by_one(fit_g):
    """:func:`fit_forward`'s last step, every start solved again under the final weights, in
    lockstep: each start's cost, convergence and iterations as :func:`solve` gives them."""
    from calib.estimators.forward.fit import _refit_starts

    pr, fit = _rig(91, 8, 3, 30, 1, fit_g)
    rng = np.random.default_rng(2)
    starts = [{"U": fit["U"] + s * rng.normal(size=fit["U"].shape), "g": 7.0, "start": f"s{i}"}
              for i, s in enumerate([0.0, 0.05, 0.3, 1.0, 3.0])]
    W = pr.weights(fit["v"])
    got = _refit_starts(pr, starts, W)
    assert [f["start"] for f in got] == [f["start"] for f in starts]
    for f, s in zip(got, starts, strict=True):
        one = solve(pr, s["U"], s["g"], W)
        assert (f["iterations"], f["converged"]) == (one["iterations"], one["converged"])
        np.testing.assert_allclose(f["cost"], one["cost"], rtol=1e-9)
        np.testing.assert_allclose(f["M"], one["M"], rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("fit_g", [False, True])
def test_the_forward_fit_in_lockstep_is_the_fit_one_start_at_a_time(monkeypatch, fit_g):
    """:func:`fit_forward` with its starts alternated and solved in lockstep, and with the
    lockstep forced to fail (every start then run one at a time): the same starts in the same
    order, the same costs (to 1e-9) and the same chosen fit (loads to 1e-6 of their scale)."""
    import calib.estimators.forward.fit as fit_mod

    pr, _ = _rig(55, 8, 3, 30, 1, fit_g)
    lock = fit_mod.fit_forward(pr, seed=4)

    def fail(*a, **k):
        raise ValueError("forced")

    monkeypatch.setattr(fit_mod, "alternate_batch", fail)
    monkeypatch.setattr(fit_mod, "solve_batch", fail)
    one = fit_mod.fit_forward(pr, seed=4)
    assert [s["start"] for s in lock["starts"]] == [s["start"] for s in one["starts"]]
    np.testing.assert_allclose([s["cost"] for s in lock["starts"]],
                               [s["cost"] for s in one["starts"]], rtol=1e-9)
    assert lock["chosen_start"] == one["chosen_start"]
    np.testing.assert_allclose(lock["M"], one["M"], atol=1e-6 * np.abs(one["M"]).max())


def test_refits_in_groups_are_the_refits_in_one_group(monkeypatch):
    """More logs than a group holds: refitted group by group, the same logs as in one group
    (a group boundary that drops, repeats or reorders a log fails it)."""
    pr, fit = _rig(12, 8, 3, 30, 1, False)
    one = refits._refits(pr, fit, 20, 3)
    monkeypatch.setattr(refits, "LOCKSTEP_READINGS", refits.LOCKSTEP_MIN_LOGS * pr.P * pr.p)
    grouped = refits._refits(pr, fit, 20, 3)  # groups of 8, 8 and 4
    np.testing.assert_allclose(grouped["logs"], one["logs"], rtol=1e-9, atol=1e-12)
