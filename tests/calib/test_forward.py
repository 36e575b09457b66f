"""The maximum-likelihood forward fit (calib.estimators.forward) and the joint route on logs
without static
poses: noise-free recovery, the optimum reached, equivariance to units/order/offsets, the oracle
ratio and the coverage of the predicted held-out error."""

import functools
import warnings
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calib.data.result import CalibrationError
from calib.estimators.forward.fit import fit_forward
from calib.estimators.forward.problem import (
    SEARCH_POSES,
    Problem,
    cost,
    curvature,
    grid,
    solve,
    sphere_minimum,
)
from calib.estimators.forward.refits import dof_of_logs, reweighting_dof
from calib.estimators.forward.variances import _trigamma_inverse, moderate_variances
from calib.estimators.least_squares import fit_least_squares
from calib.routes.joint import choose_known_poses, fit_joint
from calib.simulation.simulate import sample_directions, simulate_payload_rig
from calib.verdict.predicted_error import gls_inverse, predict_error
from calib.verdict.reliability import assess


def _random_sensor(rng, p, cap, poses, readings=1, noise=0.0):
    """A linear sensor with channel scales over 1e-2..1e2, poses within ``cap`` degrees, 4 known
    loads on the most spread poses; returns the Problem and the truth."""
    r = 3
    A = rng.normal(size=(p, r)) * np.exp(rng.uniform(np.log(1e-2), np.log(1e2), p))[:, None]
    o = rng.normal(size=p) * np.abs(A).sum(axis=1) * 3
    U = sample_directions(poses, r, rng, cap_half_angle_deg=cap)
    g = 7.5
    M = g * U
    Y = M @ A.T + o
    sd = noise * np.abs(A).sum(axis=1) * g
    Y = Y + rng.normal(size=Y.shape) * sd / np.sqrt(readings)
    known = choose_known_poses(U, 4)
    pr = Problem(Y, np.full(poses, float(readings)), sd if readings > 1 else None, known,
                 M[known], magnitude=g)
    return pr, A, o, M


@pytest.mark.parametrize("p,cap,readings", [(3, 180, 1), (6, 45, 1), (8, 90, 1), (12, 60, 1),
                                            (5, 120, 200), (8, 45, 50)])
def test_noise_free_random_sensors_are_recovered(p, cap, readings):
    rng = np.random.default_rng(p * 1000 + cap + readings)
    pr, A, o, M = _random_sensor(rng, p, cap, poses=24, readings=readings)
    f = fit_forward(pr)
    assert np.max(np.abs(f["A"] - A) / np.abs(A).max(axis=1, keepdims=True)) < 1e-6
    assert np.max(np.abs(f["o"] - o) / np.abs(A).sum(axis=1)) < 1e-6
    assert np.max(np.abs(f["M"] - M)) < 1e-6 * 7.5
    # the diagnostics report every start under the returned fit's weights (the bookkeeping the
    # summary relies on; that the optimum is reached is the next test's, against the oracle)
    assert min(s["cost"] for s in f["starts"]) == pytest.approx(f["cost"], rel=1e-12, abs=1e-20)


def test_the_search_reaches_the_optimum_from_bad_starts():
    """Every start given as wrong directions (mirror images, one direction for all): the
    search (alternation, random directions, restarts) still reaches the oracle's cost."""
    rng = np.random.default_rng(3)
    pr, A, o, M = _random_sensor(rng, 6, 90, poses=30, noise=0.01)
    U = M[pr.unknown] / np.linalg.norm(M[pr.unknown], axis=1, keepdims=True)
    oracle = fit_forward(pr, only={"truth": U})
    bad = {"mirrored": -np.vstack([M]), "all one way": np.tile([[0.0, 0.0, 1.0]], (pr.P, 1))}
    f = fit_forward(pr, start_loads=bad)
    Wf = f["W"]
    at_oracle = solve(pr, oracle["U"], oracle["g"], Wf)
    assert f["cost"] <= at_oracle["cost"] * (1 + 1e-6)
    assert cost(pr, f["A"], f["o"], f["M"], Wf) == pytest.approx(f["cost"], rel=1e-9)


def _payload_split(seed, **kw):
    d = simulate_payload_rig(seed, **kw)
    tr, te = d.split("poses")
    Z, M = d.Z[tr], d.stated_loads[d.pose[tr]]
    known = choose_known_poses(M / np.linalg.norm(M, axis=1, keepdims=True), 4)
    return d, Z, M, known, d.Z[te], d.stated_loads[d.pose[te]]


def _heldout(cal, Zt, Mt):
    return float(np.sqrt(np.mean(np.sum((cal.apply(Zt) - Mt) ** 2, axis=1))))


def _joint(Z, Zk, Mk):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fit_joint(Z, Zk, Mk, 3, known_samples=1)


# equivariance to units, order, offsets and a redundant channel, every route: test_equivariance.py


@functools.cache
def _payload_rig(seed):
    """A default payload rig (60 poses, one reading each, 4 known loads) fitted once by the
    joint route, for the oracle and interval tests below (seeds 500-539): a namespace of
    ``cal`` and its held-out error ``e``; ``e_ls``, least squares' with every load known;
    ``e_or``, the oracle's (the same model fitted from the true directions); ``Zk, Mk`` (the
    known pairs)."""
    d, Z, M, known, Zt, Mt = _payload_split(seed, poses=60)
    cal = _joint(Z, Z[known], M[known])
    pr = Problem(np.vstack([Z]), None, None, known, M[known], magnitude=d.magnitude)
    U = M[pr.unknown] / np.linalg.norm(M[pr.unknown], axis=1, keepdims=True)
    o = fit_forward(pr, only={"truth": U})
    C = gls_inverse(o["A"], o["v"])
    return SimpleNamespace(
        cal=cal, e=_heldout(cal, Zt, Mt),
        e_ls=_heldout(fit_least_squares(Z, M, bias=True), Zt, Mt),
        e_or=float(np.sqrt(np.mean(np.sum(((Zt - o["o"]) @ C.T - Mt) ** 2, axis=1)))),
        Zk=Z[known], Mk=M[known])


def test_payload_rigs_within_oracle_and_least_squares():
    """Simulated robot-held payload rigs (30: seeds 500-529, which the interval test below
    shares), one reading per pose, 4 known loads: the joint fit is within 1.2x of the same
    model fitted from the true directions (median over rigs; 95th percentile within 1.5x),
    never beyond 3x least squares with every load known with a 'reliable' verdict."""
    rigs = [_payload_rig(500 + k) for k in range(30)]
    ratios = [r.e / r.e_or for r in rigs]
    for k, r in enumerate(rigs):
        if r.e / r.e_ls > 3:
            assert assess(r.cal, r.Zk, r.Mk), f"rig {500 + k}: {r.e / r.e_ls:.2f}x passed"
    assert np.median(ratios) <= 1.2
    assert np.percentile(ratios, 95) <= 1.5


def test_predicted_error_interval_covers_the_heldout_error():
    """On simulated payload rigs (seeds 500-539; the first 30 shared with the oracle test) the
    measured held-out error lies in the predicted 95 % interval (the printed one,
    ``INTERVAL_COVERAGE``) for at least 35 of 40 fits: a calibrated 95 % interval covers 34 or
    fewer with probability 0.014. The rigs are taken in order and the test stops once the
    verdict is certain (35 inside, or 6 outside): the verdict is that of all 40."""
    inside = outside = 0
    for k in range(40):
        r = _payload_rig(500 + k)
        pe = r.cal.diagnostics["joint"]["predicted_error"]
        assert pe["coverage"] == 0.95
        lo, hi = pe["interval"]
        ok = lo <= r.e <= hi
        inside += ok
        outside += not ok
        if inside >= 35 or outside >= 6:
            break
    assert inside >= 35, (inside, k + 1)


def _payload_truth(seed, poses=80):
    """A default payload rig's training poses (half of ``poses``) and its true model as a
    fit's dict."""
    d = simulate_payload_rig(seed, poses=poses)
    M = d.stated_loads[d.pose[d.split("poses")[0]]]
    U = M / np.linalg.norm(M, axis=1, keepdims=True)
    known = choose_known_poses(U, 4)
    A, o, v = d.S.T, d.offset, np.diag(d.noise_cov)

    def problem(Y):
        return Problem(Y, None, None, known, M[known], magnitude=d.magnitude)

    pr = problem(M @ A.T + o)
    truth = {"A": A, "o": o, "U": U[pr.unknown], "g": d.magnitude, "M": M, "v": v,
             "v0": None, "W": pr.weights(v)}
    return problem, pr, truth


@pytest.mark.parametrize("seed", [21, 22])
def test_the_measured_degrees_of_freedom_describe_the_variance_estimates_spread(seed):
    """The channel variances the feasible-GLS rounds estimate spread as reweighting_dof says,
    not as the linear count P - sum(leverage) says (the rounds feed back: a channel estimated
    quiet gets weight and absorbs more of the noise). 40 logs of one default payload rig from
    its true model, each fitted by fit_forward from the true directions; the degrees of freedom
    their log-variances imply, 2 / var(log(v_hat / v)), per channel, against reweighting_dof at
    the truth (40 other logs) and against the linear count: the measured ones nearer on
    average over the channels (log distance; on development seeds 0 and 1: 0.25 and 0.30
    against 0.50 and 0.47)."""
    problem, pr, truth = _payload_truth(seed)
    v = truth["v"]
    reps = 40
    measured = reweighting_dof(pr, truth, reps=reps, seed=seed)
    linear = pr.P - curvature(pr, truth)["leverage"].sum(axis=0)
    rng = np.random.default_rng([seed, 5])
    logs = []
    for _ in range(reps):
        Y = pr.Y + rng.normal(size=pr.Y.shape) * np.sqrt(v)
        logs.append(np.log(fit_forward(problem(Y), only={"truth": truth["U"]})["v"] / v))
    refits = dof_of_logs(np.array(logs))  # the refits' own, measured the same way
    near = np.mean(np.abs(np.log(refits / measured)))
    far = np.mean(np.abs(np.log(refits / linear)))
    assert near < far, (near, far)
    assert near < 0.4, near


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(3, 60), shift=st.floats(-2.0, 3.0),
       scale=st.floats(0.01, 3.0))
def test_dof_of_logs_counts_the_undershoots_and_agrees_on_symmetric_spreads(seed, n, shift,
                                                                              scale):
    """The degrees of freedom of a variance estimate's spread: never fewer than the variance
    alone gives, nor than the estimates below the truth give (2 / (2 mean(min(log, 0)^2)));
    on a spread mirrored about the truth the two agree (but for the variance's n / (n - 1));
    raising the estimates above the truth (a channel the rounds let go) never takes degrees
    of freedom away below what the undershoots alone give; at least 1."""
    rng = np.random.default_rng(seed)
    logs = rng.normal(shift, scale, size=(n, 3))
    dof = dof_of_logs(logs)
    var_dof = 2.0 / np.var(logs, axis=0, ddof=1)
    under = 2.0 * np.mean(np.minimum(logs, 0.0) ** 2, axis=0)
    assert np.all(dof >= 1.0)
    assert np.all(dof >= np.minimum(var_dof, 1e12) * (1 - 1e-12))
    with np.errstate(divide="ignore"):
        assert np.all(dof >= np.minimum(2.0 / under, 1e12) * (1 - 1e-12))
    mirrored = np.vstack([logs - logs.mean(axis=0), logs.mean(axis=0) - logs])
    m_dof = dof_of_logs(mirrored)
    m_var = 2.0 / np.var(mirrored, axis=0, ddof=1)
    big = 2 * n  # var divides by 2n - 1, the undershoots' mean square by 2n
    assert np.allclose(m_dof, np.maximum(m_var * big / (big - 1), 1.0), rtol=1e-9)
    # a channel let go: its overshoots grow tenfold, its undershoots stay; 2 / var alone would
    # fall with them, the undershoots' count is kept
    raised = np.where(logs > 0, logs * 10.0, logs)
    with np.errstate(divide="ignore"):
        floor = np.maximum(np.minimum(2.0 / under, 1e12), 1.0)
    assert np.all(dof_of_logs(raised) >= floor * (1 - 1e-12))


def test_the_tangents_cross_products_are_numpys_to_the_bit():
    """tangents' row-wise cross product is np.cross's arithmetic in the same order: the fits
    are unchanged by it, bit for bit."""
    from calib.estimators.forward.problem import _cross

    rng = np.random.default_rng(7)
    for m in (1, 5, 1000):
        a, b = rng.normal(size=(m, 3)), rng.normal(size=(m, 3)) * 1e3
        assert np.array_equal(_cross(a, b), np.cross(a, b))


def test_a_channel_the_rounds_let_go_is_not_given_a_truth_far_above_its_estimate():
    """The refits' log ratios of a channel whose estimate rises when the rounds let it go
    (40 draws: 34 between 0 and 6, 6 undershoots down to -1.1, the shape measured on a
    gauge-mixed payload rig's channel): the variance alone gives under 1 degree of freedom
    (a chi-square that puts the truth 250x above the estimate at its 5 % point), the
    undershoots about 9."""
    rng = np.random.default_rng(0)
    logs = np.r_[rng.uniform(0.0, 6.0, 34), -rng.uniform(0.3, 1.1, 6)][:, None]
    assert 2.0 / np.var(logs, ddof=1) < 1.0
    assert 5.0 < dof_of_logs(logs)[0] < 20.0


def test_reweighting_dof_is_seeded():
    _, pr, truth = _payload_truth(3)
    a = reweighting_dof(pr, truth, reps=5, seed=1)
    assert a.shape == (pr.p,) and np.all(a >= 1)
    assert np.array_equal(a, reweighting_dof(pr, truth, reps=5, seed=1))
    assert reweighting_dof(pr, truth, reps=2) is None


def test_a_long_logs_degrees_of_freedom_are_measured_on_its_search_subset():
    """Beyond SEARCH_POSES unknown poses (a sweep) the variances settle in the rounds on the
    search's strided subset, and the final re-estimate on every pose inherits their spread:
    the degrees of freedom are measured there (the same numbers as on that subset), not left
    to the linear count of every pose (hundreds: on development sweeps the variances spread
    1.7x wider than it says)."""
    _, pr, truth = _payload_truth(4, poses=2 * (SEARCH_POSES + 60))
    nu = len(pr.unknown)
    assert nu > SEARCH_POSES
    pick = np.unique(np.linspace(0, nu - 1, SEARCH_POSES).round().astype(int))
    rows = np.sort(np.r_[pr.known, pr.unknown[pick]])
    sub = {**truth, "M": truth["M"][rows], "U": truth["U"][pick]}
    a = reweighting_dof(pr, truth, reps=4, seed=2)
    assert a is not None and a.shape == (pr.p,)
    assert np.array_equal(a, reweighting_dof(pr.sub(pr.unknown[pick]), sub, reps=4, seed=2))
    assert np.median(a) < np.median(pr.P - curvature(pr, truth)["leverage"].sum(axis=0))


def test_stated_load_accuracy_widens_the_interval_to_cover_kinematic_errors():
    """Stated loads off by a robot's kinematics (0.5 deg per pose): the 90 % interval
    (``coverage=0.90``, the level this test's bounds were set for) that takes
    them as exact misses many held-out errors measured against them; stating their accuracy
    (``load_sd``, the per-component error 0.5 deg gives; ``known_sigma`` of the joint route)
    brings the coverage back near 90 % (at least 70 % of 24, against at most 60 % without: a
    90 % interval covers 14 or fewer of 24 with probability 1e-4). Measured (the
    variances' degrees of freedom as the rounds give them): 19 and 13 of 24."""
    n, inside_exact, inside_stated = 24, 0, 0
    for seed in range(n):
        d, Z, M, known, Zt, Mt = _payload_split(900 + seed, poses=60, misalignment_deg=0.5)
        pr = Problem(Z, None, None, known, M[known], magnitude=d.magnitude)
        f = fit_forward(pr, random_starts=2, restarts=0)
        C = gls_inverse(f["A"], f["v"])
        e = float(np.sqrt(np.mean(np.sum(((Zt - f["o"]) @ C.T - Mt) ** 2, axis=1))))
        dof = reweighting_dof(pr, f)  # measured once, shared by both predictions
        lo, hi = predict_error(pr, f, draws=500, coverage=0.90, dof=dof)["interval"]
        inside_exact += lo <= e <= hi
        sd = d.magnitude * np.radians(0.5) * np.sqrt(2 / 9)
        lo2, hi2 = predict_error(pr, f, draws=500, load_sd=sd, coverage=0.90,
                                 dof=dof)["interval"]
        assert lo2 > lo and hi2 > hi
        inside_stated += lo2 <= e <= hi2
    assert inside_exact <= 0.6 * n, (inside_exact, inside_stated)
    assert inside_stated >= 0.7 * n, inside_stated


def test_the_joint_route_passes_the_stated_accuracy_to_the_prediction():
    d, Z, M, known, _, _ = _payload_split(3, poses=40, misalignment_deg=0.5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        exact = fit_joint(Z, Z[known], M[known], 3, known_samples=1)
        stated = fit_joint(Z, Z[known], M[known], 3, known_sigma=0.05 * d.magnitude)
    a = exact.diagnostics["joint"]["predicted_error"]
    b = stated.diagnostics["joint"]["predicted_error"]
    assert b["rms"] > 1.5 * a["rms"] and b["ls_rms"] > 1.5 * a["ls_rms"]
    for huge in (d.magnitude, 1e200):  # as large as the loads: refused, never an overflow
        with pytest.raises(CalibrationError, match="as large as the known loads"):
            fit_joint(Z, Z[known], M[known], 3, known_sigma=huge)


def test_the_verdict_holds_the_interval_upper_end_to_the_ceiling():
    """A forward fit is refused where the upper end of its predicted 90 % interval of the ratio
    to least squares with every load known exceeds 3x, even with its median below; a good fit
    is written."""
    _, Z, M, known, _, _ = _payload_split(11, poses=60)
    cal = _joint(Z, Z[known], M[known])
    pe = cal.diagnostics["joint"]["predicted_error"]
    assert pe["upper_ratio"] >= pe["ratio"] > 0
    assert pe["interval_ratio"] == pytest.approx(pe["interval"][1] / pe["ls_rms"])
    assert not assess(cal, Z[known], M[known])
    pe.update(ratio=1.5, upper_ratio=4.0)
    reasons = assess(cal, Z[known], M[known])
    assert any("could reach 4x" in r and "at the ratio's 95th percentile" in r
               for r in reasons), reasons


def test_the_ceiling_compares_the_fit_with_least_squares_on_the_same_noise():
    """A 20-pose payload rig (development seed 570 of the payload study's generator) whose
    channels' variances are known from few degrees of freedom: in draws where the noise is
    higher both the fit and least squares err more, so with the linear count of degrees of
    freedom (``reweight_reps=0``) the fit's error interval reaches 4.6x least squares' median
    while their ratio within a draw stays below 2x (measured 1.51x; the assertion keeps room
    for other BLAS builds' roundoff in the search). The verdict holds the paired ratio to 3x
    and writes the fit; it measures 1.03x least squares (the oracle, fitted from the true
    directions, the same). (With the degrees of freedom the rounds give, this rig's variances
    are better determined: the interval's upper end 2.0x least squares.)"""
    rig = simulate_payload_rig(10_570, poses=40)
    M = rig.stated_loads[rig.pose]
    tr, te = rig.split("poses")
    Z = rig.Z[tr]
    kn = choose_known_poses(M[tr] / np.linalg.norm(M[tr], axis=1, keepdims=True), 4)
    cal = _joint(Z, Z[kn], M[tr][kn])
    pe = cal.diagnostics["joint"]["predicted_error"]
    assert pe["upper_ratio"] < 2, pe
    pr = Problem(Z, None, None, kn, M[tr][kn], magnitude=rig.magnitude)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        f = fit_forward(pr)
    linear = predict_error(pr, f, reweight_reps=0)
    assert linear["interval_ratio"] > 3 > 2 > linear["upper_ratio"], linear
    assert not assess(cal, Z[kn], M[tr][kn])
    ls = fit_least_squares(Z, M[tr], bias=True)
    assert _heldout(cal, rig.Z[te], M[te]) < 1.2 * _heldout(ls, rig.Z[te], M[te])


def test_degrees_of_freedom_measured_once_give_the_same_prediction():
    """``predict_error(..., dof=reweighting_dof(...))`` is the prediction it would measure
    itself (the same refits, the same draws), and a ``dof`` of the wrong shape or sign is a
    one-line ValueError."""
    d, Z, M, known, _, _ = _payload_split(11, poses=40)
    pr = Problem(Z, None, None, known, M[known], magnitude=d.magnitude)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        f = fit_forward(pr, random_starts=2, restarts=0)
    own = predict_error(pr, f, draws=300, seed=4)
    shared = predict_error(pr, f, draws=300, seed=4, dof=reweighting_dof(pr, f, seed=4))
    assert own["rms"] == shared["rms"] and own["interval"] == shared["interval"]
    for bad in (np.ones(pr.p - 1), -np.ones(pr.p), np.full(pr.p, np.nan)):
        with pytest.raises(ValueError, match="positive degrees of freedom"):
            predict_error(pr, f, draws=10, dof=bad)
    for bad in (0.0, 1.0, -0.5, float("nan")):  # interval levels
        with pytest.raises(ValueError, match="strictly between 0 and 1"):
            predict_error(pr, f, draws=10, coverage=bad)
        with pytest.raises(ValueError, match="strictly between 0 and 1"):
            predict_error(pr, f, draws=10, ratio_coverage=bad)


def test_narrow_coverage_is_refused():
    """Directions within 34 degrees of their mean: the offset is not identified and the fit is
    not reliable (exit 3 in the CLI), whatever its in-sample fit."""
    d, Z, M, known, _, _ = _payload_split(7, poses=60, tilt_deg=(0, 34))
    cal = _joint(Z, Z[known], M[known])
    reasons = assess(cal, Z[known], M[known])
    assert any("offset is not identified" in r for r in reasons)


def _cli(argv, capsys):
    from calib.cli import main

    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _write_payload(tmp_path, seed, **kw):
    from calib.data.io import write_csv

    d, Z, M, known, Zt, Mt = _payload_split(seed, **kw)
    ch = [f"g{i}" for i in range(Z.shape[1])]
    write_csv(tmp_path / "raw.csv", ch, Z)
    write_csv(tmp_path / "known.csv", ch + ["Fx", "Fy", "Fz"], np.hstack([Z[known], M[known]]))
    return Zt, Mt


def test_cli_fits_one_reading_per_pose_with_a_predicted_error(tmp_path, capsys):
    """`calib fit --method joint` on a one-reading-per-pose payload log: the forward fit, exit 0,
    the summary names the route and prints the predicted held-out error with its interval."""
    from calib.data.io import load_calibration

    Zt, Mt = _write_payload(tmp_path, 11, poses=60)
    code, out, err = _cli(["fit", tmp_path / "raw.csv", "--dof", 3, "--method", "joint",
                           "--known", tmp_path / "known.csv", "--known-samples", 1,
                           "--out", tmp_path / "cal.json"], capsys)
    assert code == 0, err
    assert "every reading its own pose" in out and "predicted held-out error" in out
    assert out.rstrip().endswith("; reliable")
    cal, _ = load_calibration(tmp_path / "cal.json")
    pe = cal.diagnostics["joint"]["predicted_error"]
    assert pe["interval"][0] < pe["rms"] < pe["interval"][1]
    assert len(cal.diagnostics["joint"]["starts"]) >= 4


def test_cli_default_route_is_joint_with_two_known_loads_else_centered(tmp_path, capsys):
    """`calib fit --bias` without --method: joint with >= 2 known loads, centered with fewer;
    a joint-only option with too few known loads is one line, exit 2, nothing written."""
    import csv

    from calib.data.io import load_calibration

    _write_payload(tmp_path, 11, poses=60)
    out = tmp_path / "cal.json"
    base = ["fit", tmp_path / "raw.csv", "--dof", 3, "--bias", "--out", out,
            "--allow-unreliable"]
    code, _, err = _cli(base + ["--known", tmp_path / "known.csv"], capsys)
    assert code == 0, err
    assert load_calibration(out)[0].method == "joint"
    rows = list(csv.reader(open(tmp_path / "known.csv")))
    with open(tmp_path / "one.csv", "w", newline="") as f:
        csv.writer(f).writerows(rows[:2])  # the header and one known load
    out.unlink()
    code, _, err = _cli(base + ["--magnitude", 7.5], capsys)  # no known loads: centered
    assert code == 0, err
    assert load_calibration(out)[0].method == "centered"
    out.unlink()
    code, _, err = _cli(base + ["--known", tmp_path / "one.csv", "--known-samples", 1], capsys)
    assert code == 2 and err.count("\n") == 1 and "--known-samples" in err, err
    # one known load and no joint option: the centered route, which needs 2 to fix the frame
    code, _, err = _cli(base + ["--known", tmp_path / "one.csv"], capsys)
    assert code == 2 and err.count("\n") == 1 and "rotation" in err, err
    assert not out.exists()


def test_cli_refuses_a_narrow_log_in_one_line(tmp_path, capsys):
    _write_payload(tmp_path, 7, poses=60, tilt_deg=(0, 34))
    code, out, err = _cli(["fit", tmp_path / "raw.csv", "--dof", 3, "--method", "joint",
                           "--known", tmp_path / "known.csv", "--known-samples", 1,
                           "--out", tmp_path / "cal.json"], capsys)
    assert code == 3 and not (tmp_path / "cal.json").exists()
    assert err.count("\n") == 1 and "offset is not identified" in err


def test_plan_reports_the_single_reading_ratio():
    from calib.simulation.plan import plan

    U = simulate_payload_rig(0, poses=100).directions
    res = plan(U, 4, samples=1)
    # parameter errors dominate the bound's ratio; a new reading's own noise dilutes it
    assert 1.0 < res["ratio_reading"] < res["ratio"]
    assert res["ratio_reading"] <= res["ratio_reading_first"] + 1e-9


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), r=st.sampled_from([2, 3]),
       log_scale=st.floats(-3, 3))
def test_sphere_minimum_is_the_global_minimum(seed, r, log_scale):
    """The per-pose global step is exact: no point of a fine grid does better."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(6, r)) * 10.0**log_scale
    Q = (A.T @ A)[None]
    b = rng.normal(size=(1, r)) * 10.0**log_scale * rng.uniform(0, 20)
    u = sphere_minimum(b, Q)[0]
    G = grid(r, 20_000)

    def f(V):
        return -2 * V @ b[0] + np.einsum("ka,ab,kb->k", V, Q[0], V)

    assert abs(np.linalg.norm(u) - 1) < 1e-12
    assert f(u[None])[0] <= f(G).min() + 1e-9 * (np.abs(Q).max() + np.abs(b).max())



def _sphere_minimum_bisection(b, Q):
    """The sphere minimum by 100 rounds of bisection on ``mu`` in Q's eigenbasis: the
    reference :func:`sphere_minimum`'s Newton steps must match."""
    lam, V = np.linalg.eigh(Q)
    c = np.einsum("jab,ja->jb", V, b)
    nb = np.maximum(np.linalg.norm(b, axis=1), 1e-300)
    lo = lam[:, 0] - nb
    hi = lam[:, 0] - 1e-15 * np.maximum(np.abs(lam).max(axis=1), nb)
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        big = np.sum((c / (lam - mid[:, None])) ** 2, axis=1) > 1
        hi, lo = np.where(big, mid, hi), np.where(big, lo, mid)
    x = c / (lam - lo[:, None])
    short = np.sqrt(np.clip(1 - np.sum(x**2, axis=1), 0, None))
    x[:, 0] += np.where(x[:, 0] >= 0, 1.0, -1.0) * short
    u = np.einsum("jab,jb->ja", V, x)
    return u / np.linalg.norm(u, axis=1, keepdims=True)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), r=st.sampled_from([2, 3]),
       log_scale=st.floats(-6, 6), m=st.integers(1, 30), hard=st.booleans())
def test_sphere_minimums_newton_steps_are_never_worse_than_bisection(seed, r, log_scale, m,
                                                                     hard):
    """On many rows at once of any scale, the hard case (b orthogonal to Q's lowest
    eigenvector, to rounding) included: every row's objective at :func:`sphere_minimum`'s
    point is no higher than at 100 rounds of bisection's, to 1e-13 of the row's scale, and
    off the hard case the two points agree to 1e-5 (measured on 3,000 random sets: 2e-15 and
    7e-7; a Newton step that stops one step early, or starts right of the root, fails it).
    Near the hard case the bisection is the one that is off: its smallest ``t`` sits above the
    root, and the objective there was up to 6e-4 of the scale worse than Newton's."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(m, 6, r)) * 10.0**log_scale
    Q = np.einsum("jka,jkb->jab", A, A)
    b = rng.normal(size=(m, r)) * 10.0**log_scale * rng.uniform(0, 20, size=(m, 1))
    if hard:
        low = np.linalg.eigh(Q)[1][:, :, 0]
        b = b - np.sum(b * low, axis=1, keepdims=True) * low
    u, ref = sphere_minimum(b, Q), _sphere_minimum_bisection(b, Q)

    def f(U):
        return -2 * np.sum(b * U, axis=1) + np.einsum("ja,jab,jb->j", U, Q, U)

    scale = np.abs(Q).max(axis=(1, 2)) + np.abs(b).max(axis=1)
    np.testing.assert_allclose(np.linalg.norm(u, axis=1), 1.0, atol=1e-12)
    assert np.all(f(u) <= f(ref) + 1e-13 * scale)
    if not hard:
        assert np.abs(u - ref).max() < 1e-5


def test_known_readings_stated_as_means_weigh_more():
    """Known readings that are not rows of the log, each the mean of 100 readings: stated as such
    (known_samples=100) they weigh 100 readings' worth and the fit follows them more closely
    than when stated as single readings."""
    d = simulate_payload_rig(21, poses=60)
    Z = d.Z
    rng = np.random.default_rng(0)
    Mk = d.magnitude * sample_directions(4, 3, rng)
    noise = (d.Z - (d.true_loads @ d.S + d.offset)).std(axis=0)
    Zk = Mk @ d.S + d.offset + rng.normal(size=(4, Z.shape[1])) * noise / 10.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        one = fit_joint(Z, Zk, Mk, 3, known_samples=1)
        hundred = fit_joint(Z, Zk, Mk, 3, known_samples=100)
    assert one.diagnostics["joint"]["n_known_matched_to_rows"] == 0

    def miss(cal):
        return float(np.sqrt(np.mean((cal.apply(Zk) - Mk) ** 2)))

    assert miss(hundred) < 0.5 * miss(one)


@pytest.mark.parametrize("kw", [{"noise": (-1, 2)}, {"scales": (0, 1)}, {"mass_kg": (3, 1)},
                                {"com_m": (float("nan"), 1)}, {"tilt_deg": (90, 30)},
                                {"poses": 1}, {"readings": 0}, {"nonlinearity": -0.01},
                                {"nonlinearity": float("nan")}, {"nonlinearity": 1.0},
                                {"nonlinearity": "some"}])
def test_payload_simulator_refuses_bad_settings(kw):
    with pytest.raises(CalibrationError):
        simulate_payload_rig(0, **kw)


@pytest.mark.parametrize("kw", [{}, {"wrench": True}, {"wrench": True, "gauges": 8},
                                {"sweep": True}])
def test_payload_simulator_nonlinearity_is_bounded_and_leaves_the_rest_of_the_rig(kw):
    """The gauges' nonlinearity is drawn after everything else (the same seed without it is
    the same rig), reads on every channel at most its fraction of the channel's spread, and is
    not affine in the load: least squares with every load known fits worse with it."""
    plain = simulate_payload_rig(3, poses=60, **kw)
    bent = simulate_payload_rig(3, poses=60, nonlinearity=0.03, **kw)
    assert np.array_equal(plain.Z, simulate_payload_rig(3, poses=60, nonlinearity=0.0, **kw).Z)
    for name in ("pose", "stated_loads", "true_loads", "S", "offset"):
        assert np.array_equal(getattr(plain, name), getattr(bent, name)), name
    spread = plain.magnitude * np.linalg.norm(plain.S, axis=0)
    added = np.abs(bent.Z - plain.Z).max(axis=0) / spread
    assert np.all(added <= 0.03 + 1e-12) and np.all(added > 0.003)

    def misfit(d):
        X = np.column_stack([d.true_loads, np.ones(len(d.Z))])
        return np.linalg.lstsq(X, d.Z, rcond=None)[1] / np.sum((d.Z - d.Z.mean(0)) ** 2, axis=0)

    assert np.all(misfit(bent) > misfit(plain))


def test_the_variance_rounds_settle_and_bring_the_quietest_channel_closer(monkeypatch):
    """The feasible-GLS rounds stop once the variances have settled (another round moves none by
    more than REWEIGHT_TOL of its standard error), and settling brings the variance of the
    channel quietest relative to its span (started from a weight that cannot favour it) closer
    to its truth than the fixed 3 rounds it replaced (on these 8 rigs: mean |log(estimate /
    truth)| 0.28 against 0.42; medians 1.25x and 1.36x)."""
    import calib.estimators.forward.variances as forward
    from calib.estimators.forward.variances import MAX_REWEIGHT_ROUNDS, REWEIGHT_TOL, _reweight_step

    def quiet_error(seed, fixed3):
        d = simulate_payload_rig(900 + seed, poses=120)
        tr, _ = d.split("poses")
        Z, M = d.Z[tr], d.stated_loads[d.pose[tr]]
        known = choose_known_poses(M / np.linalg.norm(M, axis=1, keepdims=True), 4)
        pr = Problem(Z, None, None, known, M[known], magnitude=d.magnitude)
        with monkeypatch.context() as m:
            if fixed3:
                m.setattr(forward, "MAX_REWEIGHT_ROUNDS", 3)
                m.setattr(forward, "REWEIGHT_TOL", -1.0)  # never settled: exactly 3 rounds
            f = fit_forward(pr)
        if not fixed3:
            assert f["rounds"] < MAX_REWEIGHT_ROUNDS
            _, settled = _reweight_step(pr, f, f["v"])
            assert settled, f"seed {seed}: the variances had not settled (tol {REWEIGHT_TOL})"
        truth = np.mean((Z - (d.true_loads[tr] @ d.S + d.offset)) ** 2, axis=0)
        spread = d.magnitude * np.linalg.norm(d.S, axis=0)
        quiet = int(np.argmin(truth / spread**2))
        return abs(np.log(f["v"][quiet] / truth[quiet]))

    settled = [quiet_error(seed, False) for seed in range(8)]
    fixed = [quiet_error(seed, True) for seed in range(8)]
    assert np.mean(settled) < np.mean(fixed), (settled, fixed)
    assert np.exp(np.median(settled)) <= 1.5


def test_unidentified_variances_keep_the_fixed_three_rounds():
    """With p = r = 3 channels the per-channel variances are not identified (Ledermann's bound):
    the rounds do not chase them: exactly UNIDENTIFIED_ROUNDS run, settled or not (settling
    rounds would stop at 2 or run on, depending on the rig)."""
    from calib.estimators.forward.variances import UNIDENTIFIED_ROUNDS

    for seed in range(4):
        d = simulate_payload_rig(950 + seed, poses=60, p=3)
        tr, _ = d.split("poses")
        Z, M = d.Z[tr], d.stated_loads[d.pose[tr]]
        known = choose_known_poses(M / np.linalg.norm(M, axis=1, keepdims=True), 4)
        f = fit_forward(Problem(Z, None, None, known, M[known], magnitude=d.magnitude))
        assert f["rounds"] == UNIDENTIFIED_ROUNDS, (seed, f["rounds"])


def test_a_channel_the_directions_take_over_keeps_its_variance():
    """The Heywood case without repeated readings: a gauge-mixed wrench rig (payload study seed
    15) whose Fz channel the fit had taken every pose's direction from (its leverages summing to
    the poses, its variance at the floor: 1.5e-15 against about 1e-2): 3.64x least squares
    (4.26x, written, with an estimator tried and not kept). That channel's variance now comes
    from the directions the other channels set
    (:func:`calib.estimators.forward.variances._held_out_variances`): no
    channel's estimate falls below 1/100 of its noise as least squares with every load known
    sees it, and the calibration is within 2x of least squares (measured 1.43x)."""
    rig = simulate_payload_rig(10_015, poses=80, wrench=True, gauges=8)
    M = rig.stated_loads[rig.pose]
    tr, te = rig.split("poses")
    Z = rig.Z[tr]
    kn = choose_known_poses(M[tr] / np.linalg.norm(M[tr], axis=1, keepdims=True), 4)
    ls = fit_least_squares(Z, M[tr], bias=True)
    X = np.column_stack([M[tr], np.ones(len(tr))])
    res = Z - X @ np.linalg.lstsq(X, Z, rcond=None)[0]
    v_ls = np.sum(res**2, axis=0) / (len(tr) - 4)
    fit = fit_forward(Problem(Z, None, None, kn, M[tr][kn], magnitude=rig.magnitude),
                      random_starts=2)
    assert np.all(fit["v"] > v_ls / 100), fit["v"] / v_ls
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = fit_joint(Z, Z[kn], M[tr][kn], 3, known_samples=1)

    def err(C, o):
        return float(np.sqrt(np.mean(np.sum(((rig.Z[te] - o) @ C.T - M[te]) ** 2, axis=1))))

    assert err(cal.C, cal.offset) < 2 * err(ls.C, ls.offset)


def test_the_variance_guard_leaves_p_equal_r_alone():
    """Where ``p = r`` the other channels cannot set a direction without the collapsed one, so
    :func:`calib.estimators.forward.variances._held_out_variances` returns the variances unchanged;
    with one more channel it replaces a collapsed channel's floor value by a held-out one."""
    from calib.estimators.forward.problem import curvature
    from calib.estimators.forward.variances import _held_out_variances

    for p in (3, 4):
        rng = np.random.default_rng(p)
        U = sample_directions(30, 3, rng)
        A = rng.normal(size=(p, 3))
        Z = 2.0 * U @ A.T + 0.01 * rng.normal(size=(30, p))
        known = choose_known_poses(U, 4)
        pr = Problem(Z, None, None, known, 2.0 * U[known], magnitude=2.0)
        f = fit_forward(pr)
        lev = np.array(f["leverage"], float)
        lev[:, 0] = 1.0  # channel 0 "took every direction": no degree of freedom left
        floor = np.full(p, 1e-16)
        v = np.array(f["v"], float)
        v[0] = 1e-16
        out = _held_out_variances(pr, {**f, **curvature(pr, f)}, lev, v, floor)
        if p == 3:
            assert np.array_equal(out, v)
        else:
            assert out[0] > 1e-6 and np.array_equal(out[1:], v[1:]), out


def _log_chi2_draws(rng, var, d, reps):
    return var * rng.chisquare(d, size=(reps, len(var))) / d


def test_moderated_variances_pool_channels_whose_ratios_agree():
    """When every channel's variance is the same multiple of its scale (scales 1e-4..1e4), the
    moderated estimates are much closer to the truth than each channel's own (6 dof)."""
    rng = np.random.default_rng(0)
    k, d = 8, np.full(8, 6.0)
    ref = 10.0 ** rng.uniform(-4, 4, k)
    truth = 0.3 * ref
    raw, mod = [], []
    for u in _log_chi2_draws(rng, truth, d, 400):
        um, d0 = moderate_variances(u, d, ref)
        raw.append(np.mean(np.log(u / truth) ** 2))
        mod.append(np.mean(np.log(um / truth) ** 2))
    assert np.mean(mod) < 0.5 * np.mean(raw)


def test_moderated_variances_keep_channels_that_differ_near_their_own():
    """When the channels' ratios differ far beyond their sampling noise (a log-sd of 2), the
    prior is weak (d0 small) and the moderated estimates are no worse than the channels' own."""
    rng = np.random.default_rng(1)
    k, d = 8, np.full(8, 6.0)
    raw, mod, d0s = [], [], []
    for _ in range(400):
        ref = 10.0 ** rng.uniform(-4, 4, k)
        truth = ref * np.exp(2.0 * rng.standard_normal(k))
        u = _log_chi2_draws(rng, truth, d, 1)[0]
        um, d0 = moderate_variances(u, d, ref)
        raw.append(np.mean(np.log(u / truth) ** 2))
        mod.append(np.mean(np.log(um / truth) ** 2))
        d0s.append(d0)
    assert np.median(d0s) < 2.0
    assert np.mean(mod) <= 1.05 * np.mean(raw)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10**6), log_scale=st.lists(st.floats(-4, 4), min_size=6,
                                                       max_size=6))
def test_moderated_variances_are_equivariant_to_units_and_order(seed, log_scale):
    rng = np.random.default_rng(seed)
    u = rng.uniform(0.1, 10, 6)
    d = rng.uniform(2, 10, 6)
    ref = rng.uniform(0.1, 10, 6)
    k2 = 10.0 ** (2 * np.asarray(log_scale))
    perm = rng.permutation(6)
    base, d0 = moderate_variances(u, d, ref)
    got, d0b = moderate_variances((u * k2)[perm], d[perm], (ref * k2)[perm])
    np.testing.assert_allclose(got, (base * k2)[perm], rtol=1e-9)
    assert d0b == pytest.approx(d0, rel=1e-9) or (np.isinf(d0) and np.isinf(d0b))


@pytest.mark.parametrize("y", [1e-3, 0.1, 0.5, 1.0, 3.0, 30.0, 1e4])
def test_trigamma_inverse_inverts_trigamma(y):
    from scipy.special import polygamma

    assert _trigamma_inverse(float(polygamma(1, y))) == pytest.approx(y, rel=1e-6)


def test_the_known_pairs_order_does_not_matter_where_some_are_rows_of_the_log():
    # a known reading that is not a row of the log, given first, the others rows of it: the
    # problem puts the rows' first; the closed-form starts take the pairs in that order too
    rig = simulate_payload_rig(10_040, poses=80)
    tr, te = rig.split("poses")
    M = rig.stated_loads[rig.pose]
    Z, Mt = rig.Z[tr], M[tr]
    kn = choose_known_poses(Mt / np.linalg.norm(Mt, axis=1, keepdims=True), 4)
    j = te[0]
    Zk, Mk = np.vstack([rig.Z[j], Z[kn[:3]]]), np.vstack([M[j], Mt[kn[:3]]])
    perm = [1, 2, 3, 0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = fit_joint(Z, Zk, Mk, 3, known_samples=1)
        b = fit_joint(Z, Zk[perm], Mk[perm], 3, known_samples=1)
    np.testing.assert_allclose(a.apply(rig.Z[te]), b.apply(rig.Z[te]), rtol=1e-6, atol=1e-9)
