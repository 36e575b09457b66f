"""Noise correlated across channels: the test (:func:`noise_correlation`) and the fit in
whitened channels (:func:`fit_correlated`).
"""

from __future__ import annotations

import numpy as np

from calib.estimators.forward.fit import _directions, fit_forward
from calib.estimators.forward.misfit import direction_misfit
from calib.estimators.forward.problem import SEARCH_POSES, Problem, _search_pick
from calib.estimators.forward.shared_noise import _shared_covariance, shared_noise
from calib.estimators.forward.variances import REWEIGHT_TOL

#: Significance level of :func:`noise_correlation`'s test: the conventional 1 %. A false
#: positive is shrunk by its own significance (:func:`shared_noise`), not to nothing, and the F
#: null runs a little hot on fitted residuals (a channel's misestimated variance makes its
#: range and complement parts correlate): at 5 % the payload study's rigs with independent
#: noise were whitened on 8-13 % of fits and the 12-gauge case's 95th percentile rose from 1.21
#: to 1.38x least squares; at 1 %, 0-5 % and unchanged (docs/calib.md).
#: Decision: docs/calib_design.md D43.
CORRELATION_ALPHA = 0.01


def _sphericity(C, n) -> float:
    """Mauchly's test that a covariance ``C`` (k, k) estimated on ``n`` degrees of freedom is a
    multiple of the identity: the p-value of ``-(n - (2k^2 + k + 2) / (6k)) ln W``, ``W = det C /
    (tr C / k)^k``, against chi-square with ``k (k + 1) / 2 - 1`` degrees of freedom (1.0 for
    ``k < 2``). Invariant to rotations of ``C``'s basis, so to the channels' order and units
    where ``C`` is taken in an orthonormal basis of scaled channels."""
    from scipy import stats

    k = len(C)
    if k < 2 or not np.all(np.isfinite(C)):
        return 1.0
    t = np.trace(C) / k
    if not t > 0:
        return 1.0
    sign, logdet = np.linalg.slogdet(C / t)
    if sign <= 0:
        return 0.0
    stat = -(n - (2 * k * k + k + 2) / (6 * k)) * logdet
    return float(stats.chi2.sf(max(stat, 0.0), k * (k + 1) / 2 - 1))


def noise_correlation(pr: Problem, fit: dict, alpha: float = CORRELATION_ALPHA) -> dict:
    """Whether the channels' noise is correlated in a way the calibration can use, and the
    whitening that uses it.

    The model above gives each channel its own noise, independent of the others'. A real
    sensor's channels can share a disturbance: a commercial F/T sensor reports a wrench that
    its factory matrix mixed from gauges, so one gauge's drift reads on a force and a torque
    at once. Least squares with every load known then cancels it through the channel that sees
    it without signal; the per-channel model cannot. :func:`shared_noise` regresses the
    residual's part along the span of ``A`` on its part outside it and tests the regression
    (F test, ``p_gamma``); the part outside the span, white if the channels' noise were
    independent (in channels scaled by it), is tested for correlation too (Mauchly's
    sphericity test, ``p_complement``: the regression sees the range one radial component per
    pose and misses some mixed gauges the complement shows plainly: on 40 development gauge
    rigs it whitened 4 more (one fewer by the halved level), from 2.78, 3.46, 2.11 and 1.38x
    least squares to 1.41, 1.95, 1.69 and 1.39x, and fired on 0 of 40 rigs with independent
    noise, 1 of 40 with 12 gauges). ``p_value`` is the smaller doubled (Bonferroni). Where
    ``p_value < alpha``, ``T`` whitens the channels (``z -> T z``) by the covariance that
    follows from the shrunk regression and the complement's covariance (equivariant: channel
    units and order carry through ``T``); :func:`fit_correlated` refits in those channels, in
    rounds.

    Returns ``{"p_value", "p_gamma", "p_complement", "used", "max_abs_correlation", "shrink"}``
    (``max_abs_correlation`` the largest correlation between two channels' scaled residuals,
    ``shrink`` the James-Stein
    factor) and, when used, ``T`` (p, p) and its inverse ``T_inv``; ``p_value`` None where
    there is nothing to test (``p <= r``, or too few poses)."""
    out = {"p_value": None, "used": False, "max_abs_correlation": 0.0, "shrink": 0.0}
    if pr.p <= pr.r or pr.P <= pr.p + pr.r + 1:
        return out
    E = (pr.Y - fit["M"] @ fit["A"].T - fit["o"]) * np.sqrt(pr.counts)[:, None]
    E = E - E.mean(axis=0)
    R = E.T @ E
    dR = np.sqrt(np.diag(R))
    if not np.all(np.isfinite(R)) or np.any(dR <= 0):
        return out
    out["max_abs_correlation"] = float(np.max(np.abs(R / np.outer(dR, dR) - np.eye(pr.p))))
    sn = shared_noise(pr, fit)
    if sn is None:
        return out
    out["shrink"] = sn["shrink"]
    out["p_gamma"] = sn["p_value"]
    out["p_complement"] = _sphericity(sn["parts"][3], pr.P - pr.r - 1)
    # either test may find it (Bonferroni: the smaller p-value doubled)
    out["p_value"] = min(1.0, 2.0 * min(out["p_gamma"], out["p_complement"]))
    step = _whitener(sn["S"])
    if out["p_value"] < alpha and step is not None and (
            sn["shrink"] > 0 or out["p_complement"] < alpha / 2):
        out["used"] = True
        out["T"], out["T_inv"] = step
    return out


#: Rounds of :func:`fit_correlated`'s whitened refits: until the covariance
#: :func:`shared_noise` finds in the whitened channels has no correlation above
#: :data:`REWEIGHT_TOL` of a correlation's standard error (``1 / sqrt(P)``), at most this many;
#: the round whose model is likeliest is returned (:func:`round_nll`), not the last. A budget,
#: not a regulariser: with the last round returned, a cap of 8 stopped rounds that
#: were still improving the fit (payload rig 10,069 written at 3.98x least squares; 1.62x after
#: 30) and 30 let others drift away from the data (the real wrist sensor's plan fit 1.14 ->
#: 1.24x), both visible in the likelihood (docs/calib_design.md D46).
#: Decision: docs/calib_design.md D46.
MAX_CORRELATION_ROUNDS = 30


def _whitener(S) -> tuple[np.ndarray, np.ndarray] | None:
    """``(T, T_inv)`` that whiten a covariance ``S``: each channel scaled by its standard
    deviation, then the correlation matrix's inverse square root (equivariant to the channels'
    units and order). None when ``S`` is not positive definite."""
    sd = np.sqrt(np.diag(S))
    if not np.all(np.isfinite(S)) or np.any(sd <= 0):
        return None
    R = S / np.outer(sd, sd)
    w, V = np.linalg.eigh(0.5 * (R + R.T))
    if w[0] <= 1e3 * np.finfo(float).eps:
        return None
    return ((V / np.sqrt(w)) @ V.T) / sd[None, :], sd[:, None] * ((V * np.sqrt(w)) @ V.T)


def round_nll(prw: Problem, fit: dict, T) -> float:
    """The Gaussian negative log-likelihood per pose (less its constant) of a fit made in
    channels whitened by ``T``, in the original channels: the readings' covariance the fit
    implies is ``T^-1 diag(v) T^-T``, so ``mean_j e_j^T diag(v)^-1 e_j + sum(log v) - 2
    log|det T|`` with ``e_j`` the pose's whitened residual (scaled by the square root of its
    readings count). Comparable across whitenings of one log (the original readings do not
    change), which the fit's own cost is not (it is in the whitened channels)."""
    E = (prw.Y - fit["M"] @ fit["A"].T - fit["o"]) * np.sqrt(prw.counts)[:, None]
    v = fit["v"]
    return float(np.mean(np.sum(E**2 / v, axis=1)) + np.sum(np.log(v))
                 - 2.0 * np.linalg.slogdet(T)[1])


def fit_correlated(pr: Problem, start_loads: dict | None = None, seed: int = 0,
                   only: dict | None = None):
    """:func:`fit_forward`, then, where :func:`noise_correlation` finds the channels' noise
    correlated, the same fit in whitened channels: the first time from the first fit's loads
    and the same starts, then, in rounds, from the last round's directions, each round
    whitening further by what :func:`shared_noise` still finds (until that is white, at most
    :data:`MAX_CORRELATION_ROUNDS`; the count is ``correlation["rounds"]``). The round returned
    is the one whose model is likeliest (:func:`round_nll`, every round's in
    ``correlation["round_nll"]``, the chosen one ``correlation["chosen_round"]``, from 1).

    Why the likeliest, not the last: the rounds are a fixed-point iteration with no guarantee
    of approaching the data. On simulated gauge-mixed rigs whose rounds settle slowly (the
    fitted directions take up much of the shared noise) the likelihood rises with them and
    the held-out error falls (rig 10,069: 5.7x least squares after one round, 3.98x after 8,
    1.76x at the likeliest, round 21); on the real wrist sensor, whose residual structure is not a
    gauge mixture, the rounds drift: the likelihood falls from the first round on and the
    held-out error rises with it (plan poses 1.04x after one round, 1.14x after 8, 1.24x after
    30). On 360 development gauge-mixed rigs (10,500-10,859): the last of 8 rounds -> the
    likeliest of 30, median 1.27 -> 1.27x least squares, 95th percentile 1.76 -> 1.72x
    (docs/calib.md).

    The rounds whiten by the regression's unshrunk estimate (``gamma_ls``). The James-Stein
    shrinkage decides whether to whiten at all (:func:`noise_correlation`); once whitened, the
    rounds solve the regression's estimating equation ``gamma_ls = 0``. Whitening by the shrunk
    estimate stopped them where what is left is no longer significant, and the fit's
    directions take up much of a shared part (the regression sees 0.3-1 of it:
    :func:`attenuation`), so a shared part of up to about three of its standard errors stayed.
    On 120 development gauge-mixed payload rigs (seeds 10,500-10,619) the fits' held-out error
    over least squares with every load known went median 1.36 -> 1.29x, 95th percentile 2.21
    -> 1.85x, worst 4.00 -> 2.26x (seed 10,501: its rig with 12 fresh noise draws, median
    about 3.5 -> 1.4x), the interval's coverage 86.7 -> 89.2 %. On the payload study's held-out
    rigs: gauge-mixed 1.33 / 1.89 / 2.29 -> 1.25 / 1.58 / 2.47x, coverage 86 -> 85 %; its cost,
    rigs with independent noise taken for correlated chase the regression's noise through the
    rounds (the default case's 95th percentile 1.24 -> 1.30x). Returns
    ``(problem, fit, T, T_inv, correlation)``: the problem and fit in the channels fitted
    (``T`` the identity when not whitened); the calibration in the original channels is
    ``gls_inverse(A, v) @ T``, its offset ``T_inv @ o``. On a one-reading log (no pose
    repeats; not for ``only``) ``correlation["direction_misfit"]`` is
    :func:`direction_misfit` of the first, independent-noise fit (whitening takes up part of a
    misfit: on 5 %-nonlinear rigs 2 of 10 were no longer found in the whitened fit)."""
    fit = fit_forward(pr, start_loads, seed=seed, only=only)
    correlation = noise_correlation(pr, fit)
    if not pr.repeats and only is None:  # (one-reading logs: misfit along the load's direction)
        correlation["direction_misfit"] = direction_misfit(pr, fit, seed=seed)
    T = correlation.pop("T", None)
    T_inv = correlation.pop("T_inv", None)
    if T is None or pr.repeats:  # (a within-pose scatter is per channel: not after mixing)
        correlation["used"] = False
        return pr, fit, np.eye(pr.p), np.eye(pr.p), correlation
    # the rounds run on at most SEARCH_POSES unknown poses (a sweep's evenly strided subset),
    # then the whole log is fitted once more in the channels they settled on
    nu = len(pr.unknown)
    pick = _search_pick(nu) if nu > SEARCH_POSES and only is None else np.arange(nu)
    rows = np.sort(np.r_[pr.known, pr.unknown[pick]])
    q = pr.sub(pr.unknown[pick]) if len(pick) < nu else pr
    first = fit["M"]
    tol = REWEIGHT_TOL / np.sqrt(q.P)
    best = None
    correlation["round_nll"] = []
    for k in range(MAX_CORRELATION_ROUNDS):
        qw = Problem(q.Y @ T.T, q.counts, None, q.known, q.known_M, q.magnitude)
        if only is not None:
            fit = fit_forward(qw, seed=seed, only=only)
        elif k == 0:
            fit = fit_forward(qw, {"independent-noise fit": first[rows], **{
                name: np.asarray(L)[rows] for name, L in (start_loads or {}).items()}},
                seed=seed, v0=np.ones(pr.p))
        else:
            fit = fit_forward(qw, seed=seed, v0=np.ones(pr.p), only={
                "previous round": _directions(fit["M"][q.unknown])})
        correlation["rounds"] = k + 1
        nll = round_nll(qw, fit, T)
        correlation["round_nll"].append(nll)
        if best is None or nll < best[0] or not np.isfinite(best[0]):
            best = (nll, k + 1, qw, fit, T, T_inv)  # (a non-finite value never stays chosen)
        sn = shared_noise(qw, fit)
        # what is left, unshrunk (see the docstring)
        S = _shared_covariance(sn["parts"], sn["gamma_ls"]) if sn is not None else None
        step = _whitener(S) if S is not None else None
        if step is None or k == MAX_CORRELATION_ROUNDS - 1:
            break
        sd = np.sqrt(np.diag(S))
        if np.max(np.abs(S / np.outer(sd, sd) - np.eye(pr.p))) < tol:
            break  # what is left is below a quarter of a correlation's standard error
        T, T_inv = step[0] @ T, T_inv @ step[1]
    _, correlation["chosen_round"], qw, fit, T, T_inv = best
    if q is pr:
        return qw, fit, T, T_inv, correlation
    prw = Problem(pr.Y @ T.T, pr.counts, None, pr.known, pr.known_M, pr.magnitude)
    full = np.array(first, float)
    full[rows] = fit["M"]
    fit = fit_forward(prw, {"correlated rounds": full, "independent-noise fit": first},
                      seed=seed, v0=np.ones(pr.p))
    return prw, fit, T, T_inv, correlation
