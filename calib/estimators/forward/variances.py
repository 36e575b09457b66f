"""Each channel's noise variance in the forward fit: leverage-corrected estimates, moderation
towards a shared prior, rounds of feasible generalised least squares, and the start weights.
"""

from __future__ import annotations

import numpy as np

from calib.estimators.forward.problem import Problem, curvature, reinfer, solve

#: Feasible-GLS rounds: until no channel's variance moved, in the last round, by more than
#: :data:`REWEIGHT_TOL` of its own standard error (``sqrt(2 / dof)`` in log terms: further
#: rounds change it by less than its sampling noise), at most :data:`MAX_REWEIGHT_ROUNDS`.
#: Not to an exact fixed point: without repeated readings the likelihood with a free variance
#: per channel is unbounded (the functional errors-in-variables model, Solari 1969): one channel
#: can set every pose's direction alone, its residuals and variance then go to 0 and its weight
#: to infinity. Iterated 45 rounds, the rounds found that degenerate point on a simulated payload
#: rig (one channel's variance 0.36 -> 0.00 of its truth, the others 0.5-1.4). Stopped after a
#: fixed 3 rounds (as before) they had not settled: the quietest channel's variance, started
#: from a weight that cannot favour it (its spread), stayed 2-5x too high on many rigs, the
#: calibration under-used it and the predicted held-out error was too high (the measured error
#: below the 90 % interval on 35 % of 40 simulated 200-pose rigs). The rounds converge
#: geometrically (about 0.6x per round): 4-7 rounds for 30 poses, 5-12 for 200.
#: Decision: docs/calib_design.md D39.
REWEIGHT_TOL = 0.25


#: Decision: docs/calib_design.md D39.
MAX_REWEIGHT_ROUNDS = 12


#: Where the channels' variances are not identified by the factor-analysis count (Ledermann's
#: bound ``(p - r)^2 < p + r``, e.g. p <= 5 for r = 3, as in
#: :func:`calib.estimators.sfm.noise_scale`) the
#: rounds can only settle on noise: a fixed 3 from the neutral start instead (on the study's
#: p = r = 3 sensors, settling rounds moved the 90 degree cap's p95 offset error 1.28 -> 1.59 %).
#: Decision: docs/calib_design.md D40.
UNIDENTIFIED_ROUNDS = 3


#: Variances below this fraction of a channel's spread squared are floored (an exactly
#: redundant channel would otherwise get an infinite weight).
#: Decision: docs/calib_design.md D38.
VARIANCE_FLOOR = 1e-16


#: Leverages are clipped here: a reading that alone sets its pose's direction carries no
#: information on its channel's noise.
#: Decision: docs/calib_design.md D38.
MAX_LEVERAGE = 0.98


def estimate_variances(pr: Problem, fit: dict) -> np.ndarray:
    """Pose-level variance per channel from a fit's residuals, each scaled by its own leverage:
    ``v_c`` solving ``mean_j res_jc^2 / ((1 - h_jc) (v_c + s_c^2 / n_j)) = 1`` with ``h_jc`` the
    reading's leverage (:func:`_leverage`: the hat matrix's diagonal, directions and
    coefficients together).

    Why each reading's own leverage and not a channel total: without repeated readings a
    channel can take a pose's direction to itself (its residuals shrink, its variance estimate
    falls, its weight grows: the Heywood case of factor analysis). A total degrees-of-freedom
    correction was biased low (0.79x the true variance, median over 40 simulated rigs) and,
    iterated, let one channel drift from 2.7x to 0.23x; each residual divided by its own
    ``1 - h`` gives 0.99-1.07x. Iterated to a fixed point even this collapses a channel on some
    rigs (the likelihood is unbounded), hence the bounded rounds (:data:`REWEIGHT_TOL`).

    Where poses repeat, each channel's mean square is first moderated across the channels
    (:func:`moderate_variances`, on the scale of the channel's sensitivity ``|a_c|^2``), then
    split into the pose-level ``v_c`` and the sampling part as above."""
    raw = pr.Y - fit["M"] @ fit["A"].T - fit["o"]
    lev = fit["leverage"] if "leverage" in fit else curvature(pr, fit)["leverage"]
    h = np.minimum(lev, MAX_LEVERAGE)
    floor = VARIANCE_FLOOR * pr.spread**2
    s2n = pr.within[None, :] ** 2 / pr.counts[:, None]
    e2 = raw**2 / (1 - h)
    if not pr.repeats:  # one reading's variance: a pose mean of n_j readings has v / n_j
        v = np.maximum((e2 * pr.counts[:, None]).mean(axis=0), floor)
        return _held_out_variances(pr, fit, lev, v, floor)
    # poses repeat: the pose-level scatter is misfit, moderated across the channels on the scale
    # of each channel's own signal (moderate_variances)
    u = e2.mean(axis=0)
    d = np.maximum(pr.P - np.asarray(lev).sum(axis=0), 1.0)
    ref = np.sum(np.asarray(fit["A"], float) ** 2, axis=1)
    ok = (u > 0) & (ref > 0) & np.isfinite(u) & np.isfinite(ref)
    if ok.sum() >= 3:
        um, _ = moderate_variances(u[ok], d[ok], ref[ok])
        e2 = e2.copy()
        e2[:, ok] *= um / u[ok]
    v = np.empty(pr.p)
    for c in range(pr.p):
        if not np.any(s2n[:, c] > 0):
            v[c] = max(e2[:, c].mean(), floor[c])
            continue

        def f(x, c=c):
            return np.mean(e2[:, c] / (x + s2n[:, c])) - 1.0

        if f(floor[c]) <= 0:  # sampling noise explains the whole scatter
            v[c] = floor[c]
            continue
        lo, hi = floor[c], max(e2[:, c].mean(), floor[c]) * 2 + floor[c]
        while f(hi) > 0:
            hi *= 4
        for _ in range(200):  # bisection in log space: f is decreasing in x
            mid = np.sqrt(lo * hi)
            lo, hi = (mid, hi) if f(mid) > 0 else (lo, mid)
            if hi / lo < 1 + 1e-12:
                break
        v[c] = np.sqrt(lo * hi)
    return v


def moderate_variances(u, d, ref) -> tuple[np.ndarray, float]:
    """Variance estimates ``u`` (k,) on ``d`` (k,) degrees of freedom moderated towards a prior
    common to the channels on each channel's own scale ``ref`` (k,): the empirical Bayes of
    Smyth (2004, "Linear models and empirical Bayes methods for assessing differential
    expression in microarray experiments", Stat. Appl. Genet. Mol. Biol. 3(1), section 6).

    The true variances are taken as ``1 / sigma_c^2 ~ chi2_d0 / (d0 ref_c s0^2)`` (a scaled
    inverse chi-square prior); ``d0`` and ``s0^2`` are estimated from the ``log(u_c / ref_c)``
    by the moments of the log chi-square (digamma, trigamma), and each channel's posterior is
    ``(d0 ref_c s0^2 + d_c u_c) / (d0 + d_c)``. Where the channels' ratios scatter no more than
    their sampling noise explains, ``d0`` is infinite (every channel at ``ref_c s0^2``); where
    they differ far more, ``d0`` is small and each channel keeps its own estimate. Nothing to
    tune: the data set how far each estimate moves. Equivariant: a channel's unit scales its
    ``u_c`` and ``ref_c`` alike.

    Used for the pose-level variances of static-pose rigs (:func:`estimate_variances`), which
    are model misfit (the noise is the within-pose scatter, measured apart) estimated from
    the residuals of a dozen poses: 5-8 degrees of freedom a channel, sampling error a factor
    of about 1.8, so feasible GLS weighs the channels by noise. ``ref_c = |a_c|^2``, the
    channel's sensitivity squared: what the misfit at a pose scales with when it is a load off
    its nominal (a misaligned mount, a mass error) or a fraction of the channel's own signal
    (nonlinearity, creep). Measured on 150 simulated rigs (50 each of the rig study's
    all-imperfections, outlier and creep cases, paired with the unmoderated variances): held-out
    error -0.3 +- 0.4 %, -0.5 +- 0.4 % and -2.5 +- 1.0 % (docs/calib.md). Returns the
    moderated variances and ``d0``."""
    from scipy.special import digamma, polygamma

    u, d, ref = (np.asarray(x, float) for x in (u, d, ref))
    z = np.log(u / ref) - digamma(d / 2) + np.log(d / 2)
    zbar = float(z.mean())
    excess = float(z.var(ddof=1) - np.mean(polygamma(1, d / 2)))
    if not excess > 0:
        return np.exp(zbar) * ref, float("inf")
    d0 = 2.0 * _trigamma_inverse(excess)
    s0 = np.exp(zbar + digamma(d0 / 2) - np.log(d0 / 2))
    return (d0 * s0 * ref + d * u) / (d0 + d), float(d0)


def _trigamma_inverse(x: float) -> float:
    """``y`` with ``trigamma(y) = x`` (x > 0), by Smyth's (2004) Newton iteration, which
    converges monotonically from ``0.5 + 1 / x``."""
    from scipy.special import polygamma

    if x > 1e7:
        return 1.0 / np.sqrt(x)
    if x < 1e-6:
        return 1.0 / x
    y = 0.5 + 1.0 / x
    for _ in range(50):
        tri = float(polygamma(1, y))
        step = tri * (1 - tri / x) / float(polygamma(2, y))
        y += step
        if -step / y < 1e-8:
            break
    return y


def _held_out_variances(pr: Problem, fit: dict, lev, v, floor) -> np.ndarray:
    """``v`` with every channel whose residuals keep less than one degree of freedom (its
    leverages sum to more than ``P - 1``: the fit takes the poses' directions from it, its
    residuals vanish, the Heywood case :func:`estimate_variances` describes) estimated instead
    from the directions the *other* channels set: each unknown pose moved to where the model
    explains them best with that channel's weight zero (:func:`reinfer`), the channel's own
    residuals there (degrees of freedom: ``P - r - 1``, its coefficients). Measured on a
    simulated gauge-mixed wrench rig (payload study seed 15) whose Fz channel's variance had
    fallen to the floor (1.5e-15 against 1.4e-2): 3.64x least squares, now 1.43x. Not
    where ``p = r``: the other channels cannot set a direction without this one (in the study's
    p = r = 3 sensors at a 90 degree cap the estimate moved the joint route's p95 offset error
    1.28 -> 1.40 % of span)."""
    dof = pr.P - np.asarray(lev).sum(axis=0)
    low = np.flatnonzero(dof < 1)
    if not len(low) or not len(pr.unknown) or "W" not in fit or pr.p - 1 < pr.r:
        return v  # (p = r: the other channels cannot set a direction without this one)
    v = v.copy()
    for c in low:
        W = np.array(fit["W"], float)
        W[:, c] = 0.0
        try:
            U = reinfer(pr, fit["A"], fit["o"], fit["g"], W)
        except (np.linalg.LinAlgError, ValueError, FloatingPointError):
            continue
        res = pr.Y[:, c] - pr.loads(U, fit["g"]) @ fit["A"][c] - fit["o"][c]
        est = np.sum(res**2 * pr.counts) / max(pr.P - pr.r - 1, 1)
        if np.isfinite(est):
            v[c] = max(v[c], est, floor[c])
    return v


def _reweight_step(pr: Problem, fit: dict, v_old) -> tuple[np.ndarray, bool]:
    """One feasible-GLS round's variances (:func:`estimate_variances`) and whether they have
    settled: no channel's log-variance moved by more than :data:`REWEIGHT_TOL` of its standard
    error ``sqrt(2 / dof)`` since ``v_old`` (None: the first round, never settled)."""
    fit = {**fit, **curvature(pr, fit)} if "leverage" not in fit else fit
    v = estimate_variances(pr, fit)
    if v_old is None:
        return v, False
    dof = np.maximum(pr.P - fit["leverage"].sum(axis=0), 1.0)
    step = np.abs(np.log(v / v_old)) / np.sqrt(2.0 / dof)
    return v, bool(np.max(step) <= REWEIGHT_TOL)


def _feasible_gls(pr: Problem, fit: dict, v0=None) -> tuple[dict, np.ndarray, int]:
    """Feasible-GLS rounds from ``fit`` (a :func:`solve` dict under its start weights): the
    variances from its residuals (:func:`estimate_variances`), refit, until they settle
    (:data:`REWEIGHT_TOL`; a fixed :data:`UNIDENTIFIED_ROUNDS` where the variances are not
    identified). ``v0``: the variances the first round's step is measured from (None: the
    first round never settles). Returns ``(fit, v, rounds)``."""
    identified = (pr.p - pr.r) ** 2 >= pr.p + pr.r
    v, rounds = (None if v0 is None else np.asarray(v0, float)), 0
    while rounds < (MAX_REWEIGHT_ROUNDS if identified else UNIDENTIFIED_ROUNDS):
        rounds += 1
        v, settled = _reweight_step(pr, fit, v)
        fit = {**solve(pr, fit["U"], fit["g"], pr.weights(v), fit["A"], fit["o"]),
               "start": fit.get("start")}
        if settled and identified:
            break
    return fit, v, rounds


def start_variances(pr: Problem):
    """Each channel's variance left after regressing it on the other channels over the poses
    (``1 / (S^-1)_cc``, ``S`` the readings' covariance): the classic starting uniquenesses of
    factor analysis (Joreskog 1967), for the start weights of :func:`fit_forward`; or left
    after regressing it on all but one of them (below). A channel the others predict (one that
    reads the load the others read) gets about its noise; a channel that reads no load keeps
    its whole variance. None where there are no more poses than channels, or channels repeat
    one another exactly (below).

    Why not each channel's spread: weights of one spread each make a channel of noise alone
    count as much as a channel of signal, and its noise is then the largest residual the
    directions can take up. On a simulated one-reading payload rig with such a channel added
    (8 gauges, seed 10,005) the first solve from the true directions measured 6.3 N on a
    8.5 N load (106x least squares), the channel given a full signal.

    A channel that another repeats (one gauge read twice, a channel logged again through a
    second amplifier) is predicted by its repeat to the repeat's own noise, far below its real
    noise, and both then take almost all the weight (the Heywood case of factor analysis): the
    directions take up that channel's noise. So each channel's variance is also taken with any
    one other channel left out of the regression, and the largest of these kept, where
    ``p >= r + 3`` (the others left then still carry the load with one to spare). On the
    payload study's default case with channel 1 repeated at 1e-4 of its span (seeds
    10,000-10,005) the fits measured 1.10-3.55x least squares with every load known, the worst
    written outside its interval; with the channel left out 1.10-1.51x (without the repeat
    0.85-1.10x: the repeat still counts that channel's noise twice). A channel repeated twice
    or more is not covered. Regressions on channels that repeat one another exactly (a
    correlation matrix with a condition number above 1e12) are skipped, and where every one
    is, the spread is used."""
    Y = pr.Y
    if len(Y) - 1 <= pr.p:
        return None
    sd = Y.std(axis=0)
    if not np.all(sd > 0):
        return None
    R = np.corrcoef(Y.T)
    if not np.all(np.isfinite(R)):
        return None

    def left(o):  # each of channels o's variance left after regressing it on the others of o
        Ro = R[np.ix_(o, o)]
        return None if np.linalg.cond(Ro) > 1e12 else 1.0 / np.diag(np.linalg.inv(Ro))

    every = np.arange(pr.p)
    psi = left(every)
    psi = np.zeros(pr.p) if psi is None else psi
    seen = np.full(pr.p, bool(np.any(psi > 0)))
    if pr.p >= pr.r + 3:  # with any one other channel left out
        for d in range(pr.p):
            o = every[every != d]
            v = left(o)
            if v is not None:
                psi[o] = np.maximum(psi[o], v)
                seen[o] = True
    if not seen.all():
        return None
    return np.maximum(np.minimum(psi, 1.0) * sd**2, VARIANCE_FLOOR * pr.spread**2)
