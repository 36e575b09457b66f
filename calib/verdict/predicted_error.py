"""The held-out load error a calibration is expected to reach, with its interval
(:func:`predict_error`), and the one-sided statement where no upper end is known
(:func:`one_sided`).
"""

from __future__ import annotations

import numpy as np

from calib.estimators.forward.problem import Problem, _unit
from calib.estimators.forward.refits import REWEIGHT_REPS, _global_cov, reweighting_dof
from calib.estimators.forward.shared_noise import (
    _radial_share,
    _shared_covariance,
    attenuation,
    range_level,
    shared_noise,
)

#: The central share of the predicted held-out error's distribution its printed interval spans
#: (:func:`predict_error`). 95 %, not 90 %: the interval is asked to hold the measured error on at
#: least 90 % of fits, and a 90 % interval that is exactly calibrated does that only on average
#: (on 60 rigs below 90 % about half the time; on the payload study's cases, 60 held-out rigs
#: each, its coverage was 85-97 %, 90.8 % pooled, and on 580 development rigs 92.4 % with the
#: measured error's rank among the draws uniform within sampling error, Kolmogorov-Smirnov
#: p 0.06): on sensors not seen, whose noise departs from the model, it would leave no margin.
#: The 95 % interval on the study's held-out rigs: 93-100 % per case, gauge-mixed 89.8 % (53 of
#: 59; 92.5 % of 120 development rigs: short of 95 % there, docs/calib_study.md), 96.5 % pooled.
#: The verdict does not move with it: :data:`RATIO_COVERAGE`.
#: Decision: docs/calib_design.md D56.
INTERVAL_COVERAGE = 0.95


#: The central share of the fit-to-least-squares ratio's distribution whose upper end (its 95th
#: percentile) the verdict holds to its ceiling
#: (:data:`calib.verdict.reliability.PREDICTED_RATIO_MAX`).
#: Decision: docs/calib_design.md D63.
RATIO_COVERAGE = 0.90


def _range_draws(sn: dict, rng, draws: int, burn: int = 50) -> np.ndarray:
    """Draws (draws, r, r) of the range's own covariance ``K`` (of ``eps``, in coordinates
    where independent channel noise is white, so that the model of :func:`shared_noise` is
    ``K = c I``) from its posterior given the regression's residuals: one radial component
    at each unknown pose, all three at a known one. Data augmentation (Tanner and Wong): each
    sweep draws the components a pose did not show from their conditional given ``K`` and the
    one it showed, then ``K`` from its inverse-Wishart given the completed vectors. The
    likelihood is tempered by ``(n - d) / n`` (``d`` the rows' degrees of freedom the fit and
    the regression took; the residuals scaled up to match) so it carries what the rows carry.
    Prior: inverse-Wishart with ``r + 2`` degrees of freedom and mean ``c I``. Beyond
    ``MC_TEST_READINGS`` unknown poses (a sweep's tens of thousands of readings) the sweeps
    augment that many evenly strided ones, each weighing for the rows it stands for, at a fixed
    cost per sweep (12.8 s of a 100,000-reading sweep's fit before): the posterior is nearly as
    concentrated as every row makes it (on 10,000 rows of a known ``K`` the trace's spread 2.2 %
    of its mean, against 1.5 % augmenting every row and 3.2 % with the strided rows unweighted;
    tested)."""
    a, yu, Ek, n, d = sn["radial"]
    r = a.shape[1]
    c = sn["parts"][2]
    lam = max(n - d, 1) / n
    scale = np.sqrt(1.0 / lam)
    yu, Ek = yu * scale, Ek * scale
    N = len(yu) + len(Ek)
    weight = 1.0  # how many unknown poses each augmented one stands for
    if len(yu) > MC_TEST_READINGS:
        keep = np.linspace(0, len(yu) - 1, MC_TEST_READINGS).round().astype(int)
        weight = len(yu) / len(keep)
        a, yu = a[keep], yu[keep]
    nu0 = r + 2
    Psi0 = c * np.eye(r)
    K = c * np.eye(r)
    out = np.empty((draws, r, r))
    for it in range(burn + draws):
        Ka = a @ K  # (n_u, r): K a_j
        s = np.einsum("ja,ja->j", Ka, a)
        # eps_j | a_j^T eps_j = y_j ~ N(K a y / s, K - K a a^T K / s)
        mean = Ka * (yu / s)[:, None]
        Z = rng.standard_normal((len(yu), r))
        Lk = np.linalg.cholesky(K + 1e-12 * c * np.eye(r))
        X = Z @ Lk.T
        X = X - Ka * (np.einsum("ja,ja->j", X, a) / s)[:, None]  # projected to the constraint
        Eu = mean + X
        Psi = Psi0 + lam * (weight * (Eu.T @ Eu) + Ek.T @ Ek)
        nu = nu0 + lam * N
        # K ~ IW(Psi, nu): the inverse of a Wishart(Psi^-1, nu) draw (Bartlett)
        Lp = np.linalg.cholesky(np.linalg.inv(Psi))
        B = np.tril(rng.standard_normal((r, r)), -1)
        B[np.diag_indices(r)] = np.sqrt(rng.chisquare(nu - np.arange(r)))
        LB = Lp @ B
        K = np.linalg.inv(LB @ LB.T)
        K = 0.5 * (K + K.T)
        if it >= burn:
            out[it - burn] = K
    return out


def gls_inverse(A, v) -> np.ndarray:
    """The calibration of a fitted forward model: ``C = (A^T V^-1 A)^-1 A^T V^-1`` (dof, p), the
    maximum-likelihood load of a new reading ``z`` being ``C (z - o)``."""
    Ai = A / v[:, None]
    return np.linalg.solve(A.T @ Ai, Ai.T)


#: At most this many test readings in :func:`predict_error`'s Monte Carlo (evenly strided poses
#: of larger rigs: the interval is then that of a 2,000-reading test set, a little wider than a
#: larger one's).
#: Decision: docs/calib_design.md D55.
MC_TEST_READINGS = 2000


def _label_cov(W, X, A, sd, tangent=False) -> np.ndarray:
    """Covariance ``(p (r+1), p (r+1))`` of the weighted normal equations' right-hand side that
    errors of the stated loads cause: a pose's load off by ``delta`` reads as the reading error
    ``A delta`` (correlated across channels through ``A``). ``delta`` has sd ``sd`` per
    component: isotropic, or with ``tangent`` a direction error (loads of one known magnitude:
    the error lies in the plane perpendicular to the load, total variance ``3 sd^2`` as the
    isotropic one's)."""
    W2 = W**2
    G = np.einsum("jc,je,jd,jf->cdef", W2, W2, X, X) * (A @ A.T)[:, None, :, None]
    if tangent:
        B = _unit(X[:, :-1]) @ A.T  # (n, p): each pose's load direction read through A
        WB = W2 * B
        G = 1.5 * (G - np.einsum("jc,je,jd,jf->cdef", WB, WB, X, X))
    n = G.shape[0] * G.shape[1]
    return (sd**2 * G).reshape(n, n)


def _label_error(rng, M, sd, tangent) -> np.ndarray:
    """One draw of the stated loads' error at loads ``M`` (see :func:`_label_cov`)."""
    d = sd * rng.standard_normal(M.shape)
    if tangent:
        u = _unit(M)
        d = np.sqrt(1.5) * (d - np.sum(d * u, axis=1, keepdims=True) * u)
    return d


def _sampler(cov) -> np.ndarray:
    """A factor ``L`` with ``L L^T = cov`` (cov symmetric positive semi-definite)."""
    try:
        return np.linalg.cholesky(cov + 1e-300 * np.eye(len(cov)))
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(0.5 * (cov + cov.T))
        return V * np.sqrt(np.clip(w, 0, None))


#: Readings (draws x test readings x channels) :func:`predict_error` holds at once where the
#: test noise is independent: its Monte Carlo runs in chunks of draws this size (8 MB a chunk).
#: Decision: docs/calib_design.md D77.
DRAW_CHUNK = 1_000_000


def _random_numbers(rng, rng_lab, m, dof, bias, nth, p, P, r, level, ng, sd, M, tangent):
    """The random numbers of ``m`` draws of :func:`predict_error`'s Monte Carlo, taken a draw at
    a time in one fixed order (the variances' chi-square, the fit's and least squares' parameter
    normals, the range level's chi-square where ``level`` is given, the shared part's ``ng``
    normals where ``ng``, the test readings' noise; from ``rng_lab`` the stated loads' errors
    where ``sd > 0``), so that blocks of any size give the same numbers."""
    out = {"S": np.empty((m, p)), "N1": np.empty((m, nth)), "N2": np.empty((m, p, r + 1)),
           "T": np.ones(m), "Ng": np.empty((m, ng)), "N3": np.empty((m, P, p))}
    if sd > 0:
        out.update(La=np.empty((m, nth)), Lb=np.empty((m, nth)), LE=np.empty((m, P, r)))
    for j in range(m):
        out["S"][j] = rng.chisquare(dof) / dof * bias
        out["N1"][j] = rng.standard_normal(nth)
        out["N2"][j] = rng.standard_normal((p, r + 1))
        if level is not None:
            out["T"][j] = level[0] * level[1] / rng.chisquare(level[1])
        if ng:
            out["Ng"][j] = rng.standard_normal(ng)
        out["N3"][j] = rng.standard_normal((P, p))
        if sd > 0:
            out["La"][j] = rng_lab.standard_normal(nth)
            out["Lb"][j] = rng_lab.standard_normal(nth)
            out["LE"][j] = _label_error(rng_lab, M, sd, tangent)
    return out


def _held_out_errors(A, o, dd, Z, M, weigh):
    """Each draw's rms load error on its test readings ``Z`` (m, P, p) of the calibration with
    parameters ``(A, o) + dd`` (dd (m, p, r + 1)), weighing its channels by ``weigh``: the
    variances (p,) the fit estimated, or per draw the inverse covariance (m, p, p)."""
    r = A.shape[1]
    Ah, oh = A + dd[:, :, :r], o + dd[:, :, r]
    AtW = (np.swapaxes(Ah, 1, 2) / weigh[None, None, :] if weigh.ndim == 1
           else np.swapaxes(Ah, 1, 2) @ weigh)  # (m, r, p)
    C = np.linalg.solve(AtW @ Ah, AtW)
    E = (Z - oh[:, None, :]) @ np.swapaxes(C, 1, 2) - M
    return np.sqrt(np.mean(np.sum(E**2, axis=2), axis=1))


def _draws(rng, rng_lab, m, dof, bias, v, L, Lls, grow, grow_ls, level, truth, within, sd,
           L_lab, L_lab_ls, M, A, o, tangent, Lg=None, sn=None, Kd=None):
    """``m`` draws of :func:`predict_error`'s Monte Carlo: the random numbers a draw at a time
    (:func:`_random_numbers`), the arithmetic on all ``m`` at once. Returns the fit's and least
    squares' held-out errors, (m,) each.

    Independent test noise (``sn`` None): each channel's true variance ``v / s`` drawn from its
    scaled chi-square, both fits' parameter errors scaled with it (both are fitted to the same
    readings), and with the range level's draw where ``level`` is given. For a fit in whitened
    channels (:func:`fit_correlated`, ``sn`` its :func:`shared_noise`): each draw also moves
    the shared part by its error ``Lg`` (held to what the regression's residuals leave room
    for, :func:`_radial_share`), so the test readings' noise is correlated as the calibration
    does not weigh for and the fits' errors are mixed across channels as that noise is; ``Kd``
    (m, r, r) the range's own covariance per draw (None: ``c I``)."""
    p, r = A.shape
    nth = L.shape[0]
    x = _random_numbers(rng, rng_lab, m, dof, bias, nth, p, len(M), r, level,
                        0 if sn is None else len(Lg), sd, M, tangent)
    S, T = x["S"], x["T"]
    # the fit's error scales with the true noise: each channel's block by sqrt(vi / v)
    d = (x["N1"] @ L.T).reshape(m, p, r + 1) * (grow / np.sqrt(S))[:, :, None]
    dl = (Lls[None] @ x["N2"][..., None])[..., 0] * grow_ls[None, :, None]
    if sn is None:
        vi = v / S * T[:, None]  # the variance an estimate of v could have come from
        dl = dl * np.sqrt(1.0 / S)[:, :, None]
        d, dl = d * np.sqrt(T)[:, None, None], dl * np.sqrt(T)[:, None, None]
        Z = truth + x["N3"] * np.sqrt(vi + within**2)[:, None, :]  # one reading per test load
        weigh_ls = v
    else:
        c = sn["parts"][2]
        dg = (x["Ng"] @ Lg.T).reshape(m, r, p - r)
        q = _radial_share(sn, dg)  # more than the radial residuals hold: to their variance
        dg = dg * np.where(q > c, np.sqrt(c / np.where(q > 0, q, 1.0)), 1.0)[:, None, None]
        Si = _shared_covariance(sn["parts"], dg, Kd) / np.sqrt(S[:, :, None] * S[:, None, :])
        w, V = np.linalg.eigh(Si)
        half = (V * np.sqrt(np.clip(w, 0, None))[:, None, :]) @ np.swapaxes(V, 1, 2)
        mix = half / np.sqrt(v)[None, None, :]
        # (d's per-channel 1 / sqrt(s) undone first: Si carries the variances' draw)
        d, dl = mix @ (d * np.sqrt(S)[:, :, None]), mix @ dl
        Z = truth + x["N3"] @ half
        weigh_ls = np.linalg.pinv(Si)  # least squares with every load known weighs by the truth
    if sd > 0:  # the fits' share of the stated loads' error; the test loads' own
        d = d + (x["La"] @ L_lab.T).reshape(m, p, r + 1)
        dl = dl + (x["Lb"] @ L_lab_ls.T).reshape(m, p, r + 1)
        Z = Z - x["LE"] @ A.T  # the applied, not the stated
    # the calibration weighs by the estimate v; the truth is vi
    return _held_out_errors(A, o, d, Z, M, v), _held_out_errors(A, o, dl, Z, M, weigh_ls)


def predict_error(pr: Problem, fit: dict, draws: int = 2000, seed: int = 0,
                  coverage: float = INTERVAL_COVERAGE, load_sd: float = 0.0,
                  whitened: bool = False, reweight_reps: int = REWEIGHT_REPS,
                  ratio_coverage: float = RATIO_COVERAGE, dof=None,
                  serial: dict | None = None) -> dict:
    """The held-out load error expected of the fit's calibration on new single readings at the
    rig's poses (as many as it has poses), with an interval, and the same for least squares
    with every load known (the reference the verdict compares with).

    Monte Carlo over what varies: the fitted (A, o) drawn from their covariance (the inverse
    Schur complement: the unknown directions are nuisance parameters), each channel's variance
    from its scaled chi-square (degrees of freedom as the feasible-GLS rounds give them,
    measured on ``reweight_reps`` logs simulated from the fit, :func:`reweighting_dof`, a
    sweep's on its search subset; ``reweight_reps`` 0: the linear count ``P - sum(leverage)``
    of :func:`estimate_variances`), and the
    test readings' noise. ``rms`` is the median over draws, ``interval`` the central
    ``coverage`` range; ``ls_rms`` least squares with every load known, predicted the same way;
    ``ratio`` their quotient; ``upper_ratio`` the upper end of the central ``ratio_coverage``
    range of the ratio within each draw (the fit's error over least squares' on the same test
    readings and the same variances, both fits' parameter errors scaled by the draw's true
    noise: what :func:`calib.verdict.reliability.assess` holds to its ceiling; the two parameter
    errors are drawn independently: drawn together through the linearised fits' common noise,
    the verdicts of 200 development rigs did not change), and
    ``interval_ratio`` the error interval's upper end over ``ls_rms`` (draws mixed: where the
    noise level itself is uncertain, a few poses' variances, both errors grow together, and
    this one counts the fit's high draws against least squares' typical one: on 20-pose rigs it
    said 4.6x for a fit whose paired ratio is 1.5x and which measured 1.03x). Returns None
    when the covariance does not exist (a singular fit: nothing identified).

    ``dof``: the channels' variance degrees of freedom where already measured for this fit
    (``reweighting_dof(pr, fit, reweight_reps, seed)``: predictions of one fit at several
    ``load_sd`` then share its simulated refits); None: measured here.

    ``range_level`` (where the channels' variances are not identified, p <= 5 channels for 3
    load components, and the noise is independent): each draw's noise level along the span of
    ``A`` is also drawn from what the radial residuals measure (:func:`range_level`: their
    variance ``c`` over the fitted variances' prediction, a scaled inverse chi-square on its
    degrees of freedom), the fit's, least squares' and the test readings' errors scaled alike.

    ``serial``: :func:`serial_correlation`'s result for the fit's log (None: independent
    readings): the fit's parameter draws are widened per channel by the square root of its
    ``parameter_factor``, least squares' by its ``ls_factor``, each channel's true variance is
    drawn around ``v / variance_bias``, and the variances' degrees of freedom are its ``dof``
    (where ``dof`` is not given).

    ``load_sd``: the stated loads' own error (standard deviation per component, load units; a
    robot's kinematics, a weighing): the known poses' loads then move the fit (linearised: the
    error ``delta`` of a known load reads as the reading error ``A delta``; for least squares,
    every pose's), and the held-out error is measured against loads stated as accurately. 0:
    stated loads exact.

    ``whitened``: the fit is in channels whitened by an estimate of the noise the channels
    share (:func:`fit_correlated`). That estimate is uncertain: each draw also moves the shared
    part by its error, so the test readings' noise is correlated in a way the calibration does
    not weigh for, and the fit's own error is mixed across channels as that noise is. The error
    is the regression's (:func:`shared_noise`'s ``gamma_cov``) divided by its attenuation
    (:func:`attenuation`: the rounds stop where the attenuated estimate is 0), and held to what
    the regression's residuals leave room for (:func:`_radial_share`: a shared part adding
    more variance to the rows than they have is scaled back to it)."""
    for name, level in (("coverage", coverage), ("ratio_coverage", ratio_coverage)):
        if not 0.0 < level < 1.0:
            raise ValueError(f"{name} must lie strictly between 0 and 1, not {level!r}")
    rng = np.random.default_rng(seed)
    # the stated loads' error from a stream of its own: the other draws are then the same with
    # and without it (common random numbers: ``load_sd`` widens the interval, the Monte Carlo
    # noise does not blur that)
    rng_lab = np.random.default_rng([seed, 1])
    r, p = pr.r, pr.p
    cov = _global_cov(fit)
    if cov is None:
        return None
    nth = p * (r + 1)
    cov = cov[:nth, :nth]
    A, o, v = fit["A"], fit["o"], fit["v"]
    M = Mfull = fit["M"]
    if len(M) > MC_TEST_READINGS:  # the test set of the Monte Carlo: evenly strided poses
        M = M[np.linspace(0, len(M) - 1, MC_TEST_READINGS).round().astype(int)]
    P = len(M)
    if dof is not None:
        dof = np.asarray(dof, float)
        if dof.shape != (pr.p,) or not np.all(dof > 0):
            raise ValueError(f"dof must hold {pr.p} positive degrees of freedom, one a channel")
    elif serial is not None:
        dof = np.asarray(serial["dof"], float)
    else:
        dof = reweighting_dof(pr, fit, reps=reweight_reps, seed=seed)
    if dof is None:
        dof = np.maximum(pr.P - fit["leverage"].sum(axis=0), 1.0)
    grow = grow_ls = bias = np.ones(p)
    if serial is not None:
        bias = np.asarray(serial.get("variance_bias", bias), float)
        grow = np.sqrt(np.asarray(serial["parameter_factor"], float))
        grow_ls = np.sqrt(np.asarray(serial["ls_factor"], float))
    L = _sampler(cov)
    # least squares with every load known: per channel (X^T W^2 X)^-1 at the fit's weights
    X = np.column_stack([Mfull, np.ones(len(Mfull))])
    W2 = fit["W"] ** 2
    Hinv = np.linalg.inv(np.einsum("jc,jd,je->cde", W2, X, X))
    Lls = np.linalg.cholesky(Hinv + 1e-300 * np.eye(r + 1))  # (p, r+1, r+1)
    sd = float(load_sd)
    # loads of one magnitude (a proof mass, a gripper: the fit holds g): a stated load can then be
    # wrong only in its direction (a weighing's error is common to every pose and cancels), so
    # its error lies in the plane perpendicular to it
    tangent = not pr.fit_g
    if sd > 0:  # what the stated loads' error does to each fit (its own draw, not the noise's)
        K = pr.known
        L_lab = _sampler(cov @ _label_cov(fit["W"][K], X[K], A, sd, tangent) @ cov)
        Hb = np.zeros((nth, nth))
        for c in range(p):
            Hb[c * (r + 1):(c + 1) * (r + 1), c * (r + 1):(c + 1) * (r + 1)] = Hinv[c]
        L_lab_ls = _sampler(Hb @ _label_cov(fit["W"], X, A, sd, tangent) @ Hb)
    err, err_ls = np.empty(draws), np.empty(draws)
    truth = M @ A.T + o  # noise-free readings at the poses' loads
    sn = shared_noise(pr, fit) if whitened else None
    level = range_level(pr, fit) if not whitened and serial is None else None
    if sn is not None:
        Lg = _sampler(sn["gamma_cov"])
        lam = attenuation(pr, fit, sn)
        if lam is not None:  # what is left of the shared part: the regression's error / Lambda
            try:
                Lg = np.linalg.solve(lam, Lg)
            except np.linalg.LinAlgError:
                pass
        try:  # the range's own covariance: its posterior given the rows (not one number)
            Kd = _range_draws(sn, rng, draws)
        except (np.linalg.LinAlgError, ValueError):
            Kd = None
    m = max(1, min(draws, DRAW_CHUNK // max(P * p, 1)))  # the draws in blocks
    for i in range(0, draws, m):
        j = min(draws, i + m)
        err[i:j], err_ls[i:j] = _draws(
            rng, rng_lab, j - i, dof, bias, v, L, Lls, grow, grow_ls, level, truth, pr.within,
            sd, L_lab if sd > 0 else None, L_lab_ls if sd > 0 else None, M, A, o, tangent,
            Lg=Lg if sn is not None else None, sn=sn,
            Kd=None if sn is None or Kd is None else Kd[i:j])
    lo, hi = np.quantile(err, [(1 - coverage) / 2, (1 + coverage) / 2])
    med, med_ls = float(np.median(err)), float(np.median(err_ls))
    return {"rms": med, "interval": [float(lo), float(hi)], "coverage": coverage,
            "ls_rms": med_ls, "ratio": med / med_ls if med_ls > 0 else float("inf"),
            "upper_ratio": float(np.quantile(err / np.maximum(err_ls, 1e-300),
                                             (1 + ratio_coverage) / 2)),
            "ratio_coverage": ratio_coverage,
            "interval_ratio": float(hi) / med_ls if med_ls > 0 else float("inf"),
            # (one_sided: not where the sensor reads nonlinear)
            "upper_bounded": True,
            "test_readings": int(P),
            "range_level": None if level is None else {"c": level[0], "dof": level[1]}}


def one_sided(pred: dict, because: str = "not linear") -> dict:
    """The predicted error of a fit whose sensor reads as not linear in the load
    (:func:`calib.estimators.forward.misfit.direction_misfit` found): no upper end is stated.

    The Monte Carlo of :func:`calib.verdict.predicted_error.predict_error` takes the misfit for
    independent
    noise, and the fitted directions take up the part of it across the load that the held-out
    loads then carry: the measured error lies above the interval, never below it (payload rigs
    2 % and 5 % nonlinear, seeds 20,000-20,029: 5 of 30 and 12 of 30 above, every one of them
    found by the test; 0 below). Nothing in a one-reading log prices that part (docs/calib.md,
    "Gauges that are not linear"), so the upper end is withdrawn (``inf``; ``null`` in the
    written file) rather than stated at a coverage it does not have; the lower end stays (the
    error of an affine sensor is the least this one's can be). The affine model's interval is
    kept as ``interval_if_linear``. The verdict's ratio (``ratio``, ``upper_ratio``) stays the
    affine model's: the fit is at its model's optimum, and refusing every fit found would
    refuse those the oracle makes within 1.5x least squares. ``because`` (stored as
    ``no_upper_end_because``): "not linear", or "readings far from the model" where
    :func:`calib.estimators.forward.misfit.outlying_readings` flagged unknown readings (spikes the
    noise model does not hold; ``robust=True`` leaves them out)."""
    lo, hi = pred["interval"]
    return {**pred, "interval": [lo, float("inf")], "upper_bounded": False,
            "no_upper_end_because": because,
            "interval_if_linear": [lo, hi], "interval_ratio": float("inf"),
            "interval_ratio_if_linear": pred["interval_ratio"]}
