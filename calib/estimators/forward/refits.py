"""Refits of the forward model on logs drawn from its own noise: the effective degrees of
freedom of the variance estimates (the reweighting's cost), and their use by the noise tests.
"""

from __future__ import annotations

import numpy as np

from calib.estimators.forward.lockstep import Batch, feasible_gls_batch, solve_batch
from calib.estimators.forward.problem import SEARCH_POSES, Problem, _search_pick, solve
from calib.estimators.forward.variances import _feasible_gls

#: Logs :func:`reweighting_dof` simulates from a fit (each one solve and the feasible-GLS
#: rounds from the fit's own start, in lockstep: 0.37 s of CPU for 40 one-reading poses of 8
#: channels, 2.2 s for 200). With 20 the interval's width moved by up to a fifth between seeds
#: on one rig.
#: Decision: docs/calib_design.md D57.
REWEIGHT_REPS = 40


def reweighting_logs(pr: Problem, fit: dict, reps: int = REWEIGHT_REPS,
                     seed: int = 0) -> np.ndarray | None:
    """The logs of :func:`reweighting_dof`: ``log(v_b / v)`` of each refitted log (rows) and
    channel (columns); None as there. Beyond :data:`SEARCH_POSES` unknown poses the logs are
    simulated on the search's own strided subset (:func:`fit_forward`'s rounds ran there)."""
    out = _refits(pr, fit, reps, seed)
    return None if out is None else out["logs"]


#: Readings (logs x poses x channels) the lockstep refits solve at once (:mod:`.lockstep`): more
#: logs than that are refitted in groups; where fewer than :data:`LOCKSTEP_MIN_LOGS` logs fit
#: in a group, one at a time. The lockstep saves per-call overhead, which small logs are made
#: of; large batches cost memory traffic instead. CPU of 20 refits (median of 3 alternating
#: rounds), serial -> lockstep in groups of this size: 8 channels x 30 poses 0.23 -> 0.08 s,
#: 8 x 100 0.48 -> 0.36 s; 24 x 100 (groups of 4) 0.68 -> 0.68 s, 8 x 400 (groups of 3) 1.75 ->
#: 2.26 s, 24 x 400 in groups of 2 (20,000) 5.95 -> 8.14 s.
#: Decision: docs/calib_design.md D77.
LOCKSTEP_READINGS = 10_000


#: Decision: docs/calib_design.md D77.
LOCKSTEP_MIN_LOGS = 8


def _lag1(e: np.ndarray) -> np.ndarray:
    """Each column's lag-1 autocorrelation (0 where a column is constant)."""
    e = e - e.mean(axis=0)
    g0 = np.sum(e * e, axis=0)
    out = np.zeros(e.shape[1])
    ok = g0 > 0
    out[ok] = np.sum(e[1:, ok] * e[:-1, ok], axis=0) / g0[ok]
    return out


def _refits(pr: Problem, fit: dict, reps: int, seed: int, rho=None, n: int = 0,
            spreads: bool = False) -> dict | None:
    """``reps`` logs simulated from the fit and refitted from its directions (the feasible-GLS
    rounds from the same start), on a long log's search subset: ``logs`` (``log(v_b / v)``,
    rows: refits, columns: channels), and (``spreads``) each channel's parameter error in its
    own metric, ``fit_spread`` (the refitted ``(a_c, o_c)``'s deviation from the fit's, squared
    in the inverse of its covariance block, mean over refits, over ``r + 1``) and ``ls_spread`` (the
    same of least squares with every simulated load known, in its information ``X^T W^2 X``),
    ``lag1`` (the refits' residual lag-1 autocorrelation along the log's rows simulated, mean
    over refits; None without ``rho``) and ``rows`` (the poses simulated).

    ``rho`` (per channel, None: independent readings): the noise of the log's first ``n`` rows
    (its own readings, in the order recorded) is an AR(1) with these coefficients along them, of
    the same variance (:func:`serial_correlation`); rows beyond ``n`` (known readings that are not
    rows of the log) get independent noise."""
    from scipy.signal import lfilter

    if reps < 3:
        return None
    orig = np.arange(pr.P)
    nu = len(pr.unknown)
    if nu > SEARCH_POSES:
        pick = _search_pick(nu)
        orig = np.sort(np.r_[pr.known, pr.unknown[pick]])
        pr, fit = pr.sub(pr.unknown[pick]), {**fit, "M": fit["M"][orig], "U": fit["U"][pick]}
    rng = np.random.default_rng([seed, 7919] if rho is None else [seed, 7919, 1])
    A, o, U, g, v = fit["A"], fit["o"], fit["U"], fit["g"], fit["v"]
    r, p = pr.r, pr.p
    v0 = fit.get("v0")
    truth = fit["M"] @ A.T + o
    sd = 1.0 / pr.weights(v)
    cov = _global_cov(fit) if spreads else None
    blocks = None
    if cov is not None:
        try:
            blocks = [np.linalg.inv(cov[c * (r + 1):(c + 1) * (r + 1),
                                        c * (r + 1):(c + 1) * (r + 1)]) for c in range(p)]
        except np.linalg.LinAlgError:
            blocks = None
    if spreads:  # least squares' information per channel
        X = np.column_stack([fit["M"], np.ones(pr.P)])
        W2 = pr.weights(v) ** 2
        H = np.einsum("jc,jd,je->cde", W2, X, X)
    mine = orig < n if rho is not None else np.zeros(pr.P, bool)
    Ys = []
    for _ in range(reps):  # every log drawn first, in the order the serial refits drew them
        z = rng.standard_normal(truth.shape)
        if rho is not None and n > 1:
            e = rng.standard_normal((n, p))
            for c in range(p):
                a = float(np.clip(rho[c], 0.0, 0.999))
                if a > 0:
                    e[:, c] = lfilter([np.sqrt(1 - a * a)], [1.0, -a], e[:, c],
                                      zi=[a * e[0, c]])[0]
            z[mine] = e[orig[mine]]
        Ys.append(truth + z * sd)
    try:
        refitted = _refit_lockstep(pr, np.array(Ys), U, g, A, o, v0)
    except (np.linalg.LinAlgError, ValueError, FloatingPointError):
        refitted = [_refit_one(pr, Y, U, g, A, o, v0) for Y in Ys]  # a log that fails, alone
    logs, spread, spread_ls, lag1 = [], [], [], []
    for Y, out in zip(Ys, refitted, strict=True):
        if out is None:
            continue
        fb, vb = out
        if not (np.all(np.isfinite(vb)) and np.all(vb > 0)):
            continue
        logs.append(np.log(vb / v))
        if mine.sum() > 2:
            lag1.append(_lag1(Y[mine] - fb["M"][mine] @ fb["A"].T - fb["o"]))
        if blocks is not None:
            d = np.column_stack([fb["A"] - A, fb["o"] - o])
            spread.append([d[c] @ blocks[c] @ d[c] for c in range(p)])
        if spreads:
            th = np.linalg.solve(H, np.einsum("jc,jd,jc->cd", W2, X, Y)[..., None])[..., 0]
            dl = th - np.column_stack([A, o])
            spread_ls.append(np.einsum("ca,cab,cb->c", dl, H, dl))
    if len(logs) < 3:
        return None
    return {"logs": np.array(logs),
            "fit_spread": np.mean(spread, axis=0) / (r + 1) if len(spread) >= 3 else None,
            "ls_spread": np.mean(spread_ls, axis=0) / (r + 1) if spread_ls else None,
            "lag1": np.mean(lag1, axis=0) if lag1 else None, "rows": orig}


def _start_weights(q: Problem, v0):
    """The weights the fit's rounds started from: each channel's spread, or ``v0``'s."""
    return (np.broadcast_to(1.0 / q.spread, (q.P, q.p)).copy() if v0 is None
            else q.weights(np.asarray(v0, float)))


def _refit_one(pr: Problem, Y, U, g, A, o, v0):
    """One simulated log ``Y`` refitted as the fit was (:func:`solve` from the fit's own
    point, then the feasible-GLS rounds): ``(fit, v)``, None where the solver fails."""
    q = Problem(Y, pr.counts, pr.within if pr.repeats else None, pr.known, pr.known_M,
                pr.magnitude)
    try:
        f = solve(q, U, g, _start_weights(q, v0), A, o)
        fb, vb, _ = _feasible_gls(q, f, v0)
    except (np.linalg.LinAlgError, ValueError, FloatingPointError):
        return None
    return fb, vb


def _refit_lockstep(pr: Problem, Ys, U, g, A, o, v0) -> list:
    """:func:`_refit_one` of every log ``Ys`` (b, P, p) at once (:mod:`.lockstep`); raises
    where any log's solver would fail (the caller then refits them one by one)."""
    group = LOCKSTEP_READINGS // (pr.P * pr.p)
    if group < LOCKSTEP_MIN_LOGS:  # logs this long gain nothing in lockstep
        return [_refit_one(pr, Y, U, g, A, o, v0) for Y in Ys]
    if len(Ys) > group:  # a long log: groups of logs that keep the batch small
        return [out for i in range(0, len(Ys), group)
                for out in _refit_lockstep(pr, Ys[i:i + group], U, g, A, o, v0)]
    bt = Batch(pr, Ys)
    b = bt.b
    if v0 is None:
        W0 = np.broadcast_to(1.0 / bt.spread[:, None, :], Ys.shape).copy()
    else:
        W0 = np.broadcast_to(pr.weights(np.asarray(v0, float)), Ys.shape).copy()
    rep = np.broadcast_to
    f = solve_batch(bt, rep(U, (b, *U.shape)), np.full(b, float(g)), W0, rep(A, (b, *A.shape)),
                    rep(o, (b, *o.shape)))
    fb, vb, _ = feasible_gls_batch(bt, f, v0)
    return [({"A": fb["A"][i], "o": fb["o"][i], "M": fb["M"][i]}, vb[i]) for i in range(b)]


def reweighting_dof(pr: Problem, fit: dict, reps: int = REWEIGHT_REPS,
                    seed: int = 0) -> np.ndarray | None:
    """Each channel's degrees of freedom of its variance estimate as the feasible-GLS rounds
    produce it, measured: ``reps`` logs simulated from the fitted model (the fit's loads, A and
    o, noise of the fit's variances ``v``), each refitted from the fit's directions by the same
    rounds from the same start (:func:`_feasible_gls`), the degrees of freedom a scaled
    chi-square needs to spread as they do, ``2 / var(log(v_b / v))`` per channel, the
    variance capped by the undershoots' (:func:`dof_of_logs`).

    Why not the linear count ``P - sum(leverage)``: the rounds feed back. A channel estimated
    quiet gets more weight, the directions lean on it and absorb more of its noise, its residual
    shrinks further; a channel estimated loud is let go. With the rounds' variances frozen at
    the true ones the estimate follows the linear count's chi-square (60 simulated 8-gauge
    payload rigs: 3.3 % of 480 channels below its 5 % point, 5.0 % above its 95 %), as the
    rounds run it does not (6.9 / 9.6 %; on the channels with the highest signal-to-noise
    ratio, which carry the calibration, 9.1 / 14.0 %). Linear theory cannot see it.

    Where the search ran on a subset (more than :data:`SEARCH_POSES` unknown poses: a sweep),
    the logs are simulated on that subset, and its degrees of freedom are the fit's: the rounds
    settle the variances there and the one re-estimate on every pose inherits their spread,
    not the hundreds of degrees of freedom the linear count gives it. Measured on 20
    development sweeps of 1,000 training readings (8 gauges, 160 channels): the fits' log
    variance ratios to the truth over their standard deviation ``sqrt(2 / dof)`` spread with
    sd 1.69 by the linear count, 1.08 by the subset's measured degrees of freedom (the subset
    count scaled up by the poses' ratio: the interval's coverage on 60 sweeps 80 -> 85 % only).

    None with fewer than 3 ``reps`` or where fewer than 3 simulated logs could be refitted."""
    logs = reweighting_logs(pr, fit, reps, seed)
    return None if logs is None else dof_of_logs(logs)


def dof_of_logs(logs) -> np.ndarray:
    """The degrees of freedom of a scaled chi-square spread as ``logs`` (rows: estimates'
    ``log(v_hat / v)``, columns: channels): ``2 / var``, the variance taken no larger than
    twice the mean square of the estimates below the truth, ``2 mean(min(log, 0)^2)``; at
    least 1.

    Why the cap: in :func:`predict_error` the chi-square's lower tail stands for estimates
    below the truth (the true noise larger than the fit thinks), which is what widens the
    error's upper end. Where the estimates spread symmetrically about the truth the two
    measures agree (a normal centred on 0: the same); where they spread because the rounds
    let a channel go (its weight falls, the directions stop absorbing its noise, its estimate
    rises far above the truth: simulated refits with mean log ratio +2.1 and variance 3.2 on
    a payload rig's channel with 2 linear degrees of freedom), the variance measures the
    overshoot, and a chi-square with its degrees of freedom (here 1) puts the truth up to 250
    times above the estimate that its undershoots (at most a factor 2.9 in 40 refits) never
    came near."""
    logs = np.atleast_2d(np.asarray(logs, float))
    spread = np.minimum(np.var(logs, axis=0, ddof=1),
                        2.0 * np.mean(np.minimum(logs, 0.0) ** 2, axis=0))
    return np.maximum(2.0 / np.maximum(spread, 1e-12), 1.0)


def _global_cov(fit: dict) -> np.ndarray | None:
    """Covariance of (A, o[, g]) with the directions as nuisance: the inverse Schur complement."""
    S = fit["schur"]
    try:
        cov = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        return None
    cov = 0.5 * (cov + cov.T)
    return cov if np.all(np.isfinite(cov)) and np.all(np.diag(cov) >= 0) else None
