"""Noise the channels share: found where it is, not where it is not, and used.

A commercial F/T sensor's wrench is mixed from its gauges by the factory matrix, so one gauge's
noise reads on several channels at once (`simulate_payload_rig(wrench=True, gauges=8)`). The
forward route regresses the residual's part along the span of ``A`` on its part outside it
(:func:`calib.estimators.forward.shared_noise.shared_noise`), tests the regression
(:func:`calib.estimators.forward.correlated.noise_correlation`)
and refits in whitened channels where it finds it."""

import warnings

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calib.estimators.forward.correlated import (
    CORRELATION_ALPHA,
    fit_correlated,
    noise_correlation,
    round_nll,
)
from calib.estimators.forward.fit import fit_forward
from calib.estimators.forward.problem import Problem
from calib.estimators.forward.shared_noise import _range_and_complement, shared_noise
from calib.routes.joint import choose_known_poses, fit_joint
from calib.simulation.simulate import simulate_payload_rig
from calib.verdict.predicted_error import gls_inverse


def _split(rig):
    M = rig.stated_loads[rig.pose]
    tr, te = rig.split("poses")
    kn = choose_known_poses(M[tr] / np.linalg.norm(M[tr], axis=1, keepdims=True), 4)
    return M, tr, te, kn


def _err(rig, te, M, C, o):
    return float(np.sqrt(np.mean(np.sum(((rig.Z[te] - o) @ C.T - M[te]) ** 2, axis=1))))


def _with_and_without(rig):
    """The joint route's calibration and the held-out errors of it and of the same fit that
    ignores the correlation (the per-channel forward fit)."""
    M, tr, te, kn = _split(rig)
    Z = rig.Z[tr]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = fit_joint(Z, Z[kn], M[tr][kn], 3, known_samples=1)
        fit = fit_forward(Problem(Z, None, None, kn, M[tr][kn], magnitude=rig.magnitude),
                          random_starts=2)
    return (cal, _err(rig, te, M, cal.C, cal.offset),
            _err(rig, te, M, gls_inverse(fit["A"], fit["v"]), fit["o"]))


def test_independent_channel_noise_is_rarely_taken_for_correlated():
    """20 payload rigs whose channels' noise is independent (40 training poses, one reading
    each): the 1 % test fires on at most 3 (its F null runs a little hot on fitted residuals:
    0-5 % of the payload study's rigs with independent noise; 3 of 20 is a 1-in-60 tail at 5 %)."""
    fired = 0
    for seed in range(20):
        rig = simulate_payload_rig(1_000 + seed, poses=80)
        M, tr, _, kn = _split(rig)
        pr = Problem(rig.Z[tr], None, None, kn, M[tr][kn], magnitude=rig.magnitude)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fit = fit_forward(pr, random_starts=2)
        c = noise_correlation(pr, fit)
        assert c["p_value"] is not None and 0 <= c["p_value"] <= 1
        fired += c["used"]
    assert fired <= 3, fired


def test_gauge_mixed_wrench_noise_is_found_and_used():
    """6 rigs of a 6-axis sensor whose wrench is mixed from 8 gauges (100 training poses): the
    forward route finds the correlation on every one (measured 6 of 6; 10 of 12 with 40
    poses), says so, and its calibration beats the same fit that ignores it (held-out error,
    ratio measured 0.38-0.91, median 0.62). It does not quite reach least squares with every
    load known: 1.13-1.27x on these rigs, docs/calib.md."""
    used, ratios = 0, []
    for seed in range(6):
        cal, e, e_ind = _with_and_without(
            simulate_payload_rig(2_000 + seed, poses=200, wrench=True, gauges=8))
        d = cal.diagnostics["joint"]["noise_correlation"]
        used += d["used"]
        if d["used"]:
            assert d["p_value"] < CORRELATION_ALPHA and d["max_abs_correlation"] > 0
            ratios.append(e / e_ind)
    assert used >= 5, used
    assert np.median(ratios) < 0.8 and max(ratios) < 1.0, ratios


def test_a_long_sweep_settles_the_correlation_on_a_subset_and_fits_every_reading():
    """A 1,600-reading sweep of a gauge-mixed wrench: the rounds run on 400 strided poses, the
    final fit on every reading, and it beats the fit that ignores the correlation."""
    rig = simulate_payload_rig(2_200, poses=1_600, sweep=True, wrench=True, gauges=8)
    cal, e, e_ind = _with_and_without(rig)
    d = cal.diagnostics["joint"]
    assert d["noise_correlation"]["used"] and d["n_poses"] == len(rig.split("poses")[0])
    assert e < e_ind, (e, e_ind)


def _synthetic_residuals(seed, n=60, p=7, r=3, shared=0.3):
    """A fit at the truth whose residuals are noise of a known shared part: in channels scaled
    by the noise, ``xi ~ N(0, I)`` outside the span of ``A_s``, ``eta = Gamma xi + eps`` along it
    (``Gamma`` of entries ``N(0, shared^2)``, ``eps ~ N(0, G0)``: the regression's model
    exactly); the first 4 poses known, the others' residuals keep only their radial part ``u (u
    . eta)`` (what a fitted direction leaves)."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(p, r)) * np.exp(rng.uniform(-3, 3, p))[:, None]
    v = np.exp(rng.uniform(-2, 2, p)) ** 2
    U = rng.normal(size=(n, r))
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    M = 2.0 * U
    pr = Problem(M @ A.T, None, None, np.arange(4), M[:4], magnitude=2.0)
    fit = {"A": A, "o": np.zeros(p), "v": v, "M": M}
    Bm, _, _, sd, G0 = _range_and_complement(pr, fit)  # (the residuals are all zero here)
    gamma = rng.normal(size=(r, p - r)) * shared
    xi = rng.normal(size=(n, p - r))
    eta = xi @ gamma.T + rng.multivariate_normal(np.zeros(r), G0, n)
    eta[4:] = U[4:] * np.sum(U[4:] * eta[4:], axis=1, keepdims=True)
    E = (np.column_stack([eta, xi]) @ Bm.T) * sd
    return Problem(M @ A.T + E, None, None, np.arange(4), M[:4], magnitude=2.0), fit, gamma


def test_the_shared_part_is_recovered_within_its_stated_standard_errors():
    """Residuals of exactly the regression's model (:func:`_synthetic_residuals`, 30 rigs):
    the estimate's Wald distance from the true ``Gamma`` over its stated covariance follows its
    chi-square (mean over the rigs within 0.7-1.4 of the m degrees of freedom; 1 expected,
    standard error 0.06), and a large shared part is kept, not shrunk away."""
    w = []
    for seed in range(30):
        pr, fit, gamma = _synthetic_residuals(seed)
        sn = shared_noise(pr, fit)
        d = (sn["gamma_ls"] - gamma).ravel()
        w.append(float(d @ np.linalg.solve(sn["gamma_cov"], d)) / sn["m"])
        assert sn["p_value"] < CORRELATION_ALPHA and sn["shrink"] > 0.5
    assert 0.7 < np.mean(w) < 1.4, np.mean(w)


@settings(max_examples=20, deadline=None, suppress_health_check=list(HealthCheck))
@given(log_scale=st.lists(st.floats(-4, 4), min_size=7, max_size=7), perm_seed=st.integers(0, 99),
       seed=st.integers(0, 50))
def test_shared_noise_is_equivariant(log_scale, perm_seed, seed):
    """Channels rescaled by 1e-4..1e4 and permuted: the same test result and shrinkage, and
    the covariance carried through (``S -> D S D``, reordered), to 1e-8 relative."""
    pr, fit, _ = _synthetic_residuals(seed)
    s = 10.0 ** np.asarray(log_scale)
    perm = np.random.default_rng(perm_seed).permutation(pr.p)
    pr2 = Problem((pr.Y * s)[:, perm], None, None, pr.known, pr.known_M, magnitude=2.0)
    fit2 = {"A": (fit["A"] * s[:, None])[perm], "o": np.zeros(pr.p),
            "v": (fit["v"] * s**2)[perm], "M": fit["M"]}
    a, b = shared_noise(pr, fit), shared_noise(pr2, fit2)
    assert abs(a["wald"] - b["wald"]) <= 1e-8 * a["wald"]
    assert abs(a["shrink"] - b["shrink"]) <= 1e-8
    Sa = (a["S"] * np.outer(s, s))[np.ix_(perm, perm)]
    assert np.allclose(Sa, b["S"], rtol=1e-8, atol=1e-10 * np.abs(Sa).max())


def test_no_shared_part_is_shrunk_toward_none():
    """Independent noise (``Gamma = 0``): the James-Stein factor pulls the estimate toward 0
    (median shrink factor below 0.5 over 30 rigs; the rigs where the test fires keep some)."""
    shrinks = [shared_noise(*_synthetic_residuals(100 + seed, shared=0.0)[:2])["shrink"]
               for seed in range(30)]
    assert np.median(shrinks) < 0.5, shrinks


def _world(seed, delta_sd=0.0):
    """A gauge-mixed wrench rig's whitened fit and readings simulated from it: the fitted model
    read with noise of its own estimated covariance in the fitted channels, with no shared part
    (or one of entries ``delta_sd`` times the regression's standard errors). Returns the fit,
    its problem, the world's covariance parts and a sampler of refits at the fit's weights,
    each started from the truth (first order: the linearisation the estimates are exact to)."""
    from calib.estimators.forward.correlated import fit_correlated
    from calib.estimators.forward.problem import solve
    from calib.estimators.forward.shared_noise import _shared_covariance

    rig = simulate_payload_rig(7_000 + seed, poses=80, wrench=True, gauges=8)
    M, tr, _, kn = _split(rig)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pr, fit, _, _, _ = fit_correlated(Problem(rig.Z[tr], None, None, kn, M[tr][kn],
                                                  magnitude=rig.magnitude))
    sn = shared_noise(pr, fit)
    rng = np.random.default_rng(seed)
    r, p = pr.r, pr.p
    delta = delta_sd * rng.normal(size=(r, p - r)) * np.sqrt(np.diag(sn["gamma_cov"])).reshape(
        r, p - r)
    L = np.linalg.cholesky(_shared_covariance(sn["parts"], delta))
    truth = fit["M"] @ fit["A"].T + fit["o"]

    def refit():
        q = Problem(truth + rng.standard_normal(truth.shape) @ L.T, None, None, pr.known,
                    pr.known_M, pr.magnitude)
        f = solve(q, fit["U"], fit["g"], fit["W"], fit["A"], fit["o"])
        return shared_noise(q, {**f, "v": fit["v"]})

    return pr, fit, sn, delta, refit


def test_the_range_variance_counts_the_degrees_of_freedom_the_fit_takes():
    """Readings simulated from a fitted gauge-mixed rig (40 poses, 4 known) with a known range
    variance ``c`` and refitted: ``c``'s estimate is unbiased (mean over 80 refits within 15 %
    of the truth, standard error 3 %; measured 1.08). Dividing by the regression's rows less
    its ``m`` and the ``P / (P - r - 1)`` of the complement, as before, gave 0.77x."""
    pr, fit, sn, _, refit = _world(0)
    est = [refit()["parts"][2] for _ in range(80)]
    assert 0.85 < np.mean(est) / sn["parts"][2] < 1.15, np.mean(est) / sn["parts"][2]


def test_the_attenuation_predicts_what_the_regression_recovers():
    """A shared part ``delta`` put into readings simulated from a fitted gauge-mixed rig and
    refitted 150 times: the regression recovers on average ``Lambda delta``
    (:func:`calib.estimators.forward.shared_noise.attenuation`), not ``delta`` (0.78 of it on this
    rig): the mean
    estimate lies within 15 % of ``Lambda delta`` (measured 5 %) and several times closer to it
    than to ``delta`` (0.13 of the distance)."""
    from calib.estimators.forward.shared_noise import attenuation

    pr, fit, sn, delta, refit = _world(6, delta_sd=4.0)
    lam = attenuation(pr, fit, sn)
    mean = np.mean([refit()["gamma_ls"].ravel() for _ in range(150)], axis=0)
    want, d = lam @ delta.ravel(), delta.ravel()
    assert np.linalg.norm(mean - want) < 0.15 * np.linalg.norm(want), (mean, want)
    assert np.linalg.norm(mean - want) < 0.3 * np.linalg.norm(mean - d), (mean, want, d)


def test_the_complement_test_is_calibrated_and_finds_mixed_gauges():
    """Mauchly's sphericity test on the complement's covariance
    (``calib.estimators.forward.correlated._sphericity``):
    on independent normal components its p-values are close to uniform (10 % below 0.1 over
    400 draws, within 5-15 %), and it fires on gauge-mixed wrench rigs where the shared-part
    regression alone does not (development rigs of the payload study's generator: regression
    p = 0.02-0.34; unwhitened, 534 and 539 measured 3.46x and 2.11x least squares, whitened
    1.95x and 1.69x)."""
    from calib.estimators.forward.correlated import _sphericity

    rng = np.random.default_rng(0)
    ps = [_sphericity(np.cov(rng.normal(size=(36, 5)).T), 35) for _ in range(400)]
    assert 0.05 <= np.mean(np.array(ps) < 0.1) <= 0.15
    missed = 0
    for seed in (518, 531, 534, 539):
        rig = simulate_payload_rig(10_000 + seed, poses=80, wrench=True, gauges=8)
        M, tr, _, kn = _split(rig)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            pr = Problem(rig.Z[tr], None, None, kn, M[tr][kn], magnitude=rig.magnitude)
            corr = noise_correlation(pr, fit_forward(pr, random_starts=2))
        missed += corr["p_gamma"] > CORRELATION_ALPHA  # the regression alone: not found
        assert corr["p_complement"] < CORRELATION_ALPHA / 2 and corr["used"], corr
    # with the earlier start weights the regression finds 518's and 539's (p = 0.0005,
    # 0.003); it misses 531's and 534's (p = 0.20, 0.019), which the complement finds at 3e-8
    # and 8e-8
    assert missed >= 2


def test_a_failing_shared_noise_or_attenuation_falls_back_instead_of_raising(monkeypatch):
    """Where the shared-part regression's or the attenuation's linear algebra fails (a singular
    system on a degenerate fit), the prediction falls back (the regression's error drawn
    unattenuated; no shared part at all) and still returns an interval, never a traceback."""
    import calib.estimators.forward.shared_noise as fw
    from calib.verdict.predicted_error import predict_error

    pr, fit, sn, _, _ = _world(0)
    base = predict_error(pr, fit, draws=200, whitened=True)

    def boom(*a, **k):
        raise np.linalg.LinAlgError("singular")

    monkeypatch.setattr(fw, "_attenuation", boom)
    assert fw.attenuation(pr, fit, sn) is None
    unatt = predict_error(pr, fit, draws=200, whitened=True)
    monkeypatch.setattr(fw, "_shared_noise", boom)
    assert fw.shared_noise(pr, fit) is None
    plain = predict_error(pr, fit, draws=200, whitened=True)
    for pred in (base, unatt, plain):
        lo, hi = pred["interval"]
        assert np.isfinite(pred["rms"]) and 0 < lo <= pred["rms"] <= hi, pred
    # unattenuated, the shared part's drawn error is smaller (Lambda's eigenvalues are <= 1)
    assert unatt["interval"][1] <= base["interval"][1] * 1.05, (unatt, base)


def test_the_range_covariance_posterior_covers_the_truth():
    """:func:`calib.verdict.predicted_error._range_draws` on what the regression's rows show of a
    known range
    covariance ``K`` (one radial component at each of 36 unknown poses in a 70 degree cap, all
    three at 4 known ones): its central 90 % interval of a random quadratic form ``b^T K b``
    and of the trace covers the truth on about 90 % of 120 worlds (measured 87 / 86 % on 200;
    accepted 78-97 %). The model of one number (``c I``) covers an anisotropic ``K`` at no rate
    at all: it has no interval."""
    from calib.estimators.forward.shared_noise import _shared_covariance
    from calib.verdict.predicted_error import _range_draws

    rng = np.random.default_rng(1)
    hits, hits_tr = [], []
    for _ in range(120):
        B = rng.normal(size=(3, 3))
        K = B @ B.T + 0.05 * np.eye(3)
        cz = rng.uniform(np.cos(np.radians(70)), 1, 36)
        ph = rng.uniform(0, 2 * np.pi, 36)
        a = np.column_stack([np.sqrt(1 - cz**2) * np.cos(ph), np.sqrt(1 - cz**2) * np.sin(ph),
                             cz])
        E = rng.multivariate_normal(np.zeros(3), K, size=40)
        y = np.sum(a * E[:36], axis=1)
        c = (np.sum(y**2) + np.sum(E[36:] ** 2)) / 48
        Kd = _range_draws({"radial": (a, y, E[36:], 48, 0), "parts": (None, None, c, None)},
                          rng, 400)
        b = _unit_vector(rng)
        lo, hi = np.quantile(np.einsum("a,iab,b->i", b, Kd, b), [0.05, 0.95])
        hits.append(lo <= b @ K @ b <= hi)
        lo, hi = np.quantile(np.trace(Kd, axis1=1, axis2=2), [0.05, 0.95])
        hits_tr.append(lo <= np.trace(K) <= hi)
    assert 0.78 <= np.mean(hits) <= 0.97 and 0.78 <= np.mean(hits_tr) <= 0.97, (
        np.mean(hits), np.mean(hits_tr))
    # K = c I in the range reproduces the one-number model's covariance
    pr, fit, sn, _, _ = _world(0)
    c = sn["parts"][2]
    np.testing.assert_allclose(_shared_covariance(sn["parts"], sn["gamma"], c * np.eye(3)),
                               sn["S"], rtol=1e-9, atol=1e-12 * np.abs(sn["S"]).max())


def test_the_range_posterior_on_a_sweeps_rows_strides_them_and_keeps_their_weight():
    """A sweep gives tens of thousands of radial rows:
    :func:`calib.verdict.predicted_error._range_draws`
    augments ``MC_TEST_READINGS`` strided ones, each weighing for the rows it stands for. On
    10,000 rows of a known ``K`` its draws' mean is within 10 % of ``K`` (trace and a random
    quadratic form), and the trace's spread is below what 2,000 rows alone give: measured
    2.4 % of its mean (2.2 % on another seed), against 1.5 % augmenting every row and 3.2 %
    with 2,000 rows unweighted."""
    from calib.verdict.predicted_error import MC_TEST_READINGS, _range_draws

    rng = np.random.default_rng(4)
    n = 5 * MC_TEST_READINGS
    B = rng.normal(size=(3, 3))
    K = B @ B.T + 0.1 * np.eye(3)
    a = np.array([_unit_vector(rng) for _ in range(n)])
    E = rng.multivariate_normal(np.zeros(3), K, size=n + 4)
    y = np.sum(a * E[:n], axis=1)
    c = float(np.mean(y**2))
    Kd = _range_draws({"radial": (a, y, E[n:], n + 12, 0), "parts": (None, None, c, None)},
                      rng, 300)
    tr = np.trace(Kd, axis1=1, axis2=2)
    assert abs(tr.mean() / np.trace(K) - 1) < 0.10, (tr.mean(), np.trace(K))
    b = _unit_vector(rng)
    q = np.einsum("a,iab,b->i", b, Kd, b)
    assert abs(q.mean() / (b @ K @ b) - 1) < 0.10, (q.mean(), b @ K @ b)
    assert tr.std() / tr.mean() < 0.027, tr.std() / tr.mean()


def _unit_vector(rng):
    b = rng.normal(size=3)
    return b / np.linalg.norm(b)


def test_the_interval_holds_most_gauge_mixed_fits():
    """Gauge-mixed wrench rigs (40 training poses, 4 known, one reading each): the measured
    held-out error lies in the predicted 95 % interval (the printed one) for at least 19 of 24
    fits (79 %): on the 120 development rigs 10,500-10,619 it held 92.5 % (the 90 % interval
    89.2 %), and a 92.5 % rate gives 18 or fewer of 24 with probability 0.007. Seeds used for
    nothing else (24 of 24 when the interval became 95 %; an earlier 90 % one held 82 % of the
    development rigs 500-539). The rigs are taken in order and the test stops once the rigs
    left cannot change its outcome (each could be unpredicted, inside or outside): the verdict is
    that of all 24."""
    inside = predicted = 0
    for seed in range(24):
        rig = simulate_payload_rig(3_000 + seed, poses=80, wrench=True, gauges=8)
        M, tr, te, kn = _split(rig)
        Z = rig.Z[tr]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cal = fit_joint(Z, Z[kn], M[tr][kn], 3, known_samples=1)
        pe = cal.diagnostics["joint"].get("predicted_error")
        if pe is not None:
            predicted += 1
            lo, hi = pe["interval"]
            inside += lo <= _err(rig, te, M, cal.C, cal.offset) <= hi
        left = 23 - seed
        if predicted >= 20 and inside >= 0.79 * (predicted + left):
            break  # certain to pass: even every rig left predicted and outside
        if predicted + left < 20 or inside + left < 0.79 * (predicted + left):
            break  # certain to fail: even every rig left predicted and inside
    assert predicted >= 20 and inside >= 0.79 * predicted, (inside, predicted, seed + 1)


def test_the_rounds_take_out_a_shared_part_the_directions_mostly_absorb():
    """Gauge-mixed payload rig 10,501 (a development seed): the fit's directions take up about
    two thirds of the shared part along one direction (the attenuation's smallest eigenvalue
    0.32), and rounds that whitened by the James-Stein-shrunk estimate stopped once the rest
    was no longer significant: 4.00x least squares with every load known, written. Whitening
    by the unshrunk estimate (the rounds solve gamma_ls = 0): 1.54x after 8 rounds, 1.14x at the
    likeliest of 30. Least squares' rms from the same training poses is the
    reference."""
    from calib.estimators.least_squares import fit_least_squares

    rig = simulate_payload_rig(10_501, poses=80, wrench=True, gauges=8)
    M, tr, te, kn = _split(rig)
    Z = rig.Z[tr]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = fit_joint(Z, Z[kn], M[tr][kn], 3, known_samples=1)
    ls = fit_least_squares(Z, M[tr], bias=True)
    assert cal.diagnostics["joint"]["noise_correlation"]["used"]
    ratio = _err(rig, te, M, cal.C, cal.offset) / _err(rig, te, M, ls.C, ls.offset)
    assert ratio < 1.4, ratio


def test_the_likeliest_round_is_returned_and_its_likelihood_shown():
    """fit_correlated returns the round whose model is likeliest in the original channels, not
    the last, and shows every round's negative log-likelihood: on a gauge-mixed rig whose
    rounds settle slowly (10,501: more than one round), the chosen round's is the smallest,
    and the returned problem, fit and whitening reproduce it."""
    rig = simulate_payload_rig(10_501, poses=80, wrench=True, gauges=8)
    M, tr, te, kn = _split(rig)
    pr = Problem(rig.Z[tr], None, None, kn, M[tr][kn], magnitude=rig.magnitude)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prw, fit, T, T_inv, corr = fit_correlated(pr)
    nll = corr["round_nll"]
    assert corr["used"] and corr["rounds"] == len(nll) > 1
    assert corr["chosen_round"] == int(np.argmin(nll)) + 1
    assert np.isclose(round_nll(prw, fit, T), min(nll), rtol=0, atol=1e-9)
    assert np.allclose(T @ T_inv, np.eye(pr.p), atol=1e-8)
    assert np.allclose(prw.Y, pr.Y @ T.T)


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.floats(-4, 4), st.integers(0, 10_000))
def test_round_nll_moves_with_the_units_by_a_constant(log_scale, seed):
    """The rounds are compared in the original channels: rescaling a channel (units) moves
    every round's negative log-likelihood by the same constant, ``2 log|scale|``, so the
    choice among them does not depend on the units."""
    rng = np.random.default_rng(seed)
    P, p, r = 30, 6, 3
    M = rng.normal(size=(P, r))
    Y = rng.normal(size=(P, p))
    fit = {"M": M, "A": rng.normal(size=(p, r)), "o": rng.normal(size=p),
           "v": rng.uniform(0.5, 2, p)}
    T = np.eye(p) + 0.3 * rng.normal(size=(p, p))
    pr = Problem(Y @ T.T, None, None, np.arange(4), M[:4])
    c = 10.0**log_scale
    D = np.eye(p)
    D[0, 0] = c
    # the same whitened problem reached from readings whose channel 0 is in other units
    base = round_nll(pr, fit, T)
    scaled = round_nll(pr, fit, T @ np.linalg.inv(D))
    assert np.isclose(scaled - base, 2 * np.log(c), rtol=0, atol=1e-8)


def test_a_round_whose_likelihood_is_not_finite_is_never_chosen(monkeypatch):
    """A round whose likelihood cannot be evaluated (NaN) is not returned while a finite one
    exists: rounds scored NaN, then 1, 2, ... return the second."""
    import calib.estimators.forward.correlated as fwd

    calls = []

    def scored(prw, fit, T):
        calls.append(1)
        return float("nan") if len(calls) == 1 else float(len(calls))

    monkeypatch.setattr(fwd, "round_nll", scored)
    rig = simulate_payload_rig(10_501, poses=80, wrench=True, gauges=8)
    M, tr, te, kn = _split(rig)
    pr = Problem(rig.Z[tr], None, None, kn, M[tr][kn], magnitude=rig.magnitude)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        corr = fwd.fit_correlated(pr)[4]
    assert corr["rounds"] > 2 and corr["chosen_round"] == 2, corr["chosen_round"]
