"""The forward model ``z = A m + o`` fitted by maximum likelihood, whatever the readings per pose.

Every rig, one statistical model: pose ``j`` is seen as the mean ``y_j`` of its ``n_j``
readings (``n_j = 1`` for one reading per pose, every reading its own pose for a slow
continuous sweep), its load ``m_j`` known (the known loads) or ``g u_j`` with ``u_j`` an unknown
unit direction and ``g`` the load magnitude (held at the known loads' when they are one mass,
or given). Each channel ``c`` has its own noise, so

    y_jc = a_c . m_j + o_c + e_jc,     var(e_jc) = v_c + s_c^2 / n_j,

with ``s_c`` the within-pose scatter (estimated from repeats, 0 when no pose repeats) and
``v_c`` each channel's pose-level variance (model misfit, and the whole reading noise when
poses do not repeat). For fixed variances the negative log-likelihood is the weighted sum of
squares ``sum_jc (y_jc - a_c . m_j - o_c)^2 / var_jc``; the variances are re-estimated from the
residuals, each divided by ``1 - h`` with ``h`` its own leverage (:func:`estimate_variances`),
in rounds of feasible generalised least squares until they settle (at most
:data:`MAX_REWEIGHT_ROUNDS`). Not to an exact fixed point: without repeated readings the
likelihood with a free variance per channel is unbounded (see :data:`REWEIGHT_TOL`).

The weighted least squares is solved by Levenberg-Marquardt on all parameters at once, the
directions eliminated pose by pose through the Schur complement (the bundle-adjustment trick: a
pose's 2 angles touch only its own readings), so a step costs ``O(P p^2 r^2)``: a 100,000-reading
sweep takes about 17 s. Starts (:func:`fit_forward`): the affine map of the known poses extended to
the others by the magnitude constraint, calibrations handed in (the closed-form routes), random
directions, each also *alternated* (the model refitted at the directions, then every unknown pose
moved to the best direction on its sphere, exactly: a global step per pose), and perturbed restarts
of the best; every start's cost under the final weights is reported, the lowest wins.

Everything here is equivariant to the channels' units, order and offsets: the start weights
are each channel's spread, the estimated variances scale with the channel, the model has a free
offset per channel.

The covariance of ``(A, o, g)`` with the directions as nuisance parameters is the inverse of the
Schur complement at the optimum (the Cramer-Rao bound of the model at the estimated variances);
:func:`predict_error` turns it into the held-out load error expected of the calibration.
"""

from __future__ import annotations

import numpy as np

from .result import CalibrationError

#: Points of :func:`grid` (about 5 degrees apart on the sphere).
GRID = 2000
#: Starts with every unknown direction drawn uniformly, alternated; the best distinct ones are
#: refined by LM.
RANDOM_STARTS = 8
#: At most this many unknown poses enter the search over starts; with more (a long sweep, one
#: reading per pose), the starts run on an evenly strided subset and the best is then refined on
#: every pose (same estimator, same optimum basin: the subset only chooses the basin).
SEARCH_POSES = 400
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
REWEIGHT_TOL = 0.25
MAX_REWEIGHT_ROUNDS = 12
#: Where the channels' variances are not identified by the factor-analysis count (Ledermann's
#: bound ``(p - r)^2 < p + r``, e.g. p <= 5 for r = 3, as in :func:`calib.sfm.noise_scale`) the
#: rounds can only settle on noise: a fixed 3 from the neutral start instead (on the study's
#: p = r = 3 sensors, settling rounds moved the 90 degree cap's p95 offset error 1.28 -> 1.59 %).
UNIDENTIFIED_ROUNDS = 3
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
INTERVAL_COVERAGE = 0.95
#: The central share of the fit-to-least-squares ratio's distribution whose upper end (its 95th
#: percentile) the verdict holds to its ceiling (:data:`calib.reliability.PREDICTED_RATIO_MAX`).
RATIO_COVERAGE = 0.90
#: Variances below this fraction of a channel's spread squared are floored (an exactly
#: redundant channel would otherwise get an infinite weight).
VARIANCE_FLOOR = 1e-16


def tangents(U: np.ndarray) -> np.ndarray:
    """An orthonormal basis of the plane normal to each unit row of U: (m, r-1, r)."""
    if U.shape[1] == 2:
        return np.stack([-U[:, 1], U[:, 0]], axis=1)[:, None, :]
    a = np.eye(3)[np.argmin(np.abs(U), axis=1)]
    t1 = _cross(U, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = _cross(U, t1)
    return np.stack([t1, t2], axis=1)


def _cross(a, b):
    """Row-wise cross products of (m, 3) arrays: ``np.cross``'s arithmetic, in the same order
    (the same bits), without its axis handling, which took a fifth of a one-reading-per-pose
    fit's time."""
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    return np.column_stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def grid(r: int, n: int = GRID) -> np.ndarray:
    """``n`` unit vectors spread evenly over the sphere (a Fibonacci lattice) or circle."""
    i = np.arange(n) + 0.5
    if r == 2:
        a = 2 * np.pi * i / n
        return np.column_stack([np.cos(a), np.sin(a)])
    polar = np.arccos(1 - 2 * i / n)
    azim = np.pi * (1 + 5**0.5) * i
    return np.column_stack([np.cos(azim) * np.sin(polar), np.sin(azim) * np.sin(polar),
                            np.cos(polar)])


class Problem:
    """Pose means, counts, within-pose scatter and the known loads of one rig.

    ``Y`` (P, p) pose means; ``counts`` (P,) readings per pose; ``within`` (p,) within-pose
    standard deviation per channel (None or zeros when no pose repeats); ``known`` indices of
    the poses whose loads ``known_M`` (k, r) are given; ``magnitude`` the load magnitude of the
    unknown poses (None: fitted).
    """

    def __init__(self, Y, counts, within, known, known_M, magnitude=None):
        self.Y = np.asarray(Y, float)
        self.P, self.p = self.Y.shape
        self.counts = np.ones(self.P) if counts is None else np.asarray(counts, float)
        self.repeats = within is not None
        self.within = np.zeros(self.p) if within is None else np.asarray(within, float)
        self.known = np.asarray(known, int)
        self.known_M = np.atleast_2d(np.asarray(known_M, float))
        self.r = self.known_M.shape[1]
        if self.r not in (2, 3):
            raise CalibrationError(f"the forward fit is for 2 or 3 load components, got {self.r}")
        self.unknown = np.setdiff1d(np.arange(self.P), self.known)
        self.magnitude = None if magnitude is None else float(magnitude)
        self.fit_g = magnitude is None
        self.spread = np.maximum(self.Y.std(axis=0), 1e-300)

    def loads(self, U, g):
        """Every pose's load: the known ones, g U at the unknown poses."""
        M = np.zeros((self.P, self.r))
        M[self.known] = self.known_M
        M[self.unknown] = g * U
        return M

    def weights(self, v):
        """Weights 1/sd (P, p) from the pose-level variances v (p,). Without a within-pose
        scatter (no pose repeats) v is the noise of one reading, and a pose that averages
        ``n_j`` readings (a known reading stated as a mean) has ``v / n_j``."""
        if self.repeats:
            return 1.0 / np.sqrt(v[None, :] + self.within[None, :] ** 2 / self.counts[:, None])
        return np.sqrt(self.counts[:, None] / v[None, :])

    def sub(self, keep_unknown):
        """The same rig with only the listed unknown poses (and every known one)."""
        rows = np.sort(np.r_[self.known, keep_unknown])
        q = Problem(self.Y[rows], self.counts[rows], self.within,
                    np.searchsorted(rows, self.known), self.known_M, self.magnitude)
        q.spread = self.spread
        return q


def _search_pick(nu: int) -> np.ndarray:
    """The :data:`SEARCH_POSES` evenly strided unknown poses (indices into ``nu``) a long log's
    search over starts, feasible-GLS rounds and correlation rounds run on."""
    return np.unique(np.linspace(0, nu - 1, SEARCH_POSES).round().astype(int))


def linear_fit(pr: Problem, M, W):
    """Every channel's (a_c, o_c) by weighted least squares at loads M: A (p, r), o (p,)."""
    X = np.column_stack([M, np.ones(pr.P)])
    W2 = W**2
    H = (W2.T[:, None, :] * X.T[None]) @ X  # (p, r+1, r+1)
    b = np.einsum("jc,jc,jd->cd", W2, pr.Y, X)
    H += 1e-13 * np.trace(H, axis1=1, axis2=2)[:, None, None] * np.eye(pr.r + 1)
    th = np.linalg.solve(H, b[..., None])[..., 0]
    return th[:, : pr.r], th[:, pr.r]


def cost(pr: Problem, A, o, M, W) -> float:
    return float(np.sum((W * (pr.Y - M @ A.T - o)) ** 2))


def sphere_minimum(b, Q):
    """The global minimum over unit u of ``-2 b.u + u^T Q u`` for every row: b (m, r), Q (m, r,
    r) symmetric. A trust-region subproblem: ``u = (Q - mu I)^-1 b`` with ``mu`` below Q's
    smallest eigenvalue and ``|u| = 1``, ``mu`` found by bisection in Q's eigenbasis (the norm is
    monotone there). Exact, unlike a grid, and O(m)."""
    lam, V = np.linalg.eigh(Q)
    c = np.einsum("jab,ja->jb", V, b)  # b in the eigenbasis
    nb = np.maximum(np.linalg.norm(b, axis=1), 1e-300)
    lo = lam[:, 0] - nb  # |u(lo)| <= 1
    hi = lam[:, 0] - 1e-15 * np.maximum(np.abs(lam).max(axis=1), nb)
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        n2 = np.sum((c / (lam - mid[:, None])) ** 2, axis=1)
        big = n2 > 1
        hi = np.where(big, mid, hi)
        lo = np.where(big, lo, mid)
    x = c / (lam - lo[:, None])
    # the hard case (b orthogonal to the lowest eigenvector): |x| < 1, the rest along it
    short = np.sqrt(np.clip(1 - np.sum(x**2, axis=1), 0, None))
    x[:, 0] += np.where(x[:, 0] >= 0, 1.0, -1.0) * short
    u = np.einsum("jab,jb->ja", V, x)
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def reinfer(pr: Problem, A, o, g, W, U=None):
    """Every unknown pose moved to the direction on its sphere that the model explains best
    (:func:`sphere_minimum`, exact), kept at ``U`` (when given) where that is as good: the global
    step per pose. Cost per pose: ``-2 b.u + u^T Q u``."""
    u = pr.unknown
    W2 = W[u] ** 2
    b = g * ((W2 * (pr.Y[u] - o)) @ A)  # (nu, r)
    Q = g**2 * np.einsum("jc,ca,cb->jab", W2, A, A)  # (nu, r, r)
    out = sphere_minimum(b, Q)
    if U is not None:
        def per(V):
            return -2 * np.sum(b * V, axis=1) + np.einsum("ja,jab,jb->j", V, Q, V)
        keep = per(U) <= per(out)
        out[keep] = U[keep]
    return out


def alternate(pr: Problem, U, g, W, iters: int = 15, tol: float = 1e-6):
    """Directions after alternating the linear fit and :func:`reinfer` from U: until no pose
    moves or the cost falls by less than ``tol`` (relative: the alternation crawls near an
    optimum, where LM's refinement, which follows, is fast)."""
    last = np.inf
    for _ in range(iters):
        A, o = linear_fit(pr, pr.loads(U, g), W)
        c = cost(pr, A, o, pr.loads(U, g), W)
        if c > last * (1 - tol):
            break
        last = c
        new = reinfer(pr, A, o, g, W, U)
        if np.max(np.abs(new - U)) < 1e-12:
            break
        U = new
    return U


def _normal_equations(pr: Problem, W, A, o, U, g):
    """The linearised weighted least squares at (A, o, U, g): residuals R (P, p), the global
    block H and gradient of (A, o[, g]), every unknown pose's direction block D (nu, k, k) and
    gradient, the cross blocks B (nu, nt, k) and the tangent bases T."""
    r, p = pr.r, pr.p
    u = pr.unknown
    nu, k = len(u), r - 1
    nt = p * (r + 1) + (1 if pr.fit_g else 0)
    M = pr.loads(U, g)
    X = np.column_stack([M, np.ones(pr.P)])
    R = W * (pr.Y - M @ A.T - o)  # weighted residuals; the J entries below are dR/dparam
    W2 = W**2
    H = np.zeros((nt, nt))
    grad = np.zeros(nt)
    Hc = (W2.T[:, None, :] * X.T[None]) @ X  # per channel (a_c, o_c)
    for c in range(p):
        s = slice(c * (r + 1), (c + 1) * (r + 1))
        H[s, s] = Hc[c]
    grad[: p * (r + 1)] = -np.einsum("jc,jc,jd->cd", W, R, X).ravel()
    T = tangents(U) if nu else np.zeros((0, k, r))
    Wu = W[u]
    Jphi = -(Wu * g)[:, :, None] * (T @ A.T).transpose(0, 2, 1)  # dR_jc / dphi_jk
    D = Jphi.transpose(0, 2, 1) @ Jphi
    gphi = np.einsum("jck,jc->jk", Jphi, R[u])
    # cross terms: dR_jc/dtheta_c = -W_jc X_j
    B = np.zeros((nu, nt, k))
    Bc = -(Wu[:, :, None, None] * X[u][:, None, :, None]) * Jphi[:, :, None, :]
    B[:, : p * (r + 1)] = Bc.reshape(nu, p * (r + 1), k)
    if pr.fit_g:
        Jg = -Wu * (U @ A.T)  # dR_jc / dg = -W_jc a_c . u_j
        Jg_full = np.zeros((pr.P, p))
        Jg_full[u] = Jg
        H[-1, -1] = np.sum(Jg**2)
        hg = np.einsum("jc,jc,jd->cd", -W, Jg_full, X).ravel()
        H[: p * (r + 1), -1] = hg
        H[-1, : p * (r + 1)] = hg
        grad[-1] = np.sum(Jg * R[u])
        B[:, -1] = np.einsum("jc,jck->jk", Jg, Jphi)
    return R, H, grad, D, gphi, B, T


def _reduce(H, D, B, lam):
    """The damped Schur complement ``H - sum_j B_j D_j^-1 B_j^T`` and the D_j^-1."""
    nu, nt, k = B.shape
    Dl = D + lam * (np.einsum("jkk->jk", D)[:, :, None] * np.eye(k) + 1e-300 * np.eye(k))
    Hl = H + lam * np.diag(np.diag(H))
    if not nu:
        return Hl, Dl
    Dinv = np.linalg.inv(Dl)
    Lc = np.linalg.cholesky(Dinv)  # Dinv = L L^T
    BL = (B @ Lc).transpose(0, 2, 1).reshape(nu * k, nt)
    return Hl - BL.T @ BL, Dinv


def solve(pr: Problem, U, g, W, A=None, o=None, max_iter: int = 200, tol: float = 1e-12):
    """Levenberg-Marquardt over (A, o, g) and every unknown direction, directions eliminated by
    the Schur complement. Returns a dict: ``A``, ``o``, ``g``, ``U``, ``M``, ``cost``,
    ``converged``, ``iterations`` and the weights ``W`` it used (:func:`curvature` adds the
    covariance and the leverages of a fit, only where they are needed)."""
    r, p = pr.r, pr.p
    nu = len(pr.unknown)
    k = r - 1
    U = np.asarray(U, float).copy()
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    g = float(pr.magnitude if not pr.fit_g else g)
    if A is None:
        A, o = linear_fit(pr, pr.loads(U, g), W)
    A, o = A.copy(), o.copy()
    lam = 1e-3
    cur = cost(pr, A, o, pr.loads(U, g), W)
    converged, it = False, 0
    for it in range(1, max_iter + 1):  # noqa: B007 (the count is returned)
        R, H, grad, D, gphi, B, T = _normal_equations(pr, W, A, o, U, g)
        improved = False
        for _ in range(40):
            S, Dinv = _reduce(H, D, B, lam)
            rhs = -(grad - ((B @ (Dinv @ gphi[:, :, None]))[:, :, 0].sum(axis=0) if nu else 0.0))
            try:
                dth = np.linalg.solve(S, rhs)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            dphi = (-np.einsum("jkl,jl->jk", Dinv, gphi + np.einsum("jak,a->jk", B, dth))
                    if nu else np.zeros((0, k)))
            th = (np.column_stack([A, o]).ravel() + dth[: p * (r + 1)]).reshape(p, r + 1)
            A1, o1 = th[:, :r], th[:, r]
            g1 = g + dth[-1] if pr.fit_g else g
            U1 = U
            if nu:
                U1 = U + np.einsum("jk,jkr->jr", dphi, T)
                U1 = U1 / np.linalg.norm(U1, axis=1, keepdims=True)
            new = cost(pr, A1, o1, pr.loads(U1, g1), W) if (not pr.fit_g or g1 > 0) else np.inf
            if new < cur:
                rel = (cur - new) / max(cur, 1e-300)
                A, o, U, g, cur = A1, o1, U1, g1, new
                lam = max(lam / 5, 1e-12)
                improved = True
                break
            lam *= 5
            if lam > 1e12:
                break
        if not improved:
            converged = True  # no descent direction left at machine precision
            break
        if rel < tol:
            converged = True
            break
    return {"A": A, "o": o, "g": g, "U": U, "M": pr.loads(U, g), "cost": cur,
            "converged": converged, "iterations": it, "W": W}


def curvature(pr: Problem, fit: dict) -> dict:
    """At a fit (:func:`solve`'s dict): ``schur``, the undamped reduced normal matrix (its
    inverse is the covariance of ``(A, o[, g])`` in units of the weights), and ``leverage``
    (:func:`_leverage`)."""
    _, H, _, D, _, B, _ = _normal_equations(pr, fit["W"], fit["A"], fit["o"], fit["U"],
                                            fit["g"])
    S, Dinv = _reduce(H, D, B, 0.0)
    return {"schur": S, "leverage": _leverage(pr, fit["W"], fit["A"], fit["U"], fit["g"], S,
                                              Dinv, B)}


def _leverage(pr: Problem, W, A, U, g, S, Dinv, B) -> np.ndarray:
    """The diagonal of the hat matrix of the linearised weighted fit, one entry per reading
    (P, p): for the row of pose j, channel c, with global Jacobian part ``a`` and direction part
    ``b``, ``h = e^T S^-1 e + b^T D_j^-1 b`` where ``e = a - B_j D_j^-1 b`` (block inversion
    through the Schur complement S). The entries sum to the number of parameters."""
    r, p = pr.r, pr.p
    nt = S.shape[0]
    try:
        Sinv = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        Sinv = np.linalg.pinv(S)
    M = pr.loads(U, g)
    X = np.column_stack([M, np.ones(pr.P)])
    h = np.zeros((pr.P, p))
    u = pr.unknown
    isu = np.zeros(pr.P, bool)
    isu[u] = True
    # a for every row: -W_jc X_j in channel c's block (and -W_jc a_c.u_j for g, unknown poses)
    for c in range(p):
        sl = slice(c * (r + 1), (c + 1) * (r + 1))
        a = np.zeros((pr.P, nt))
        a[:, sl] = -W[:, c : c + 1] * X
        if pr.fit_g:
            a[u, -1] = -W[u, c] * (U @ A[c])
        if len(u):
            T = tangents(U)
            b = -(W[u, c] * g)[:, None] * (T @ A[c])  # (nu, k)
            Db = np.einsum("jkl,jl->jk", Dinv, b)
            a[u] -= (B @ Db[:, :, None])[:, :, 0]
            h[u, c] = np.einsum("jk,jk->j", b, Db)
        h[:, c] += np.sum((a @ Sinv) * a, axis=1)
    return h


#: Leverages are clipped here: a reading that alone sets its pose's direction carries no
#: information on its channel's noise.
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


def _directions(L):
    L = np.asarray(L, float)
    n = np.linalg.norm(L, axis=1)
    if not np.all(np.isfinite(L)) or np.any(n <= 0):
        return None
    return L / n[:, None]


def fit_forward(pr: Problem, start_loads: dict | None = None, seed: int = 0,
                random_starts: int = RANDOM_STARTS, restarts: int = 2,
                only: dict | None = None, v0: np.ndarray | None = None) -> dict:
    """The maximum-likelihood forward fit of a rig (module docstring).

    ``start_loads``: named (P, r) arrays of every pose's load as another route estimates them
    (the closed-form routes' calibrations applied to the pose means); their directions at the
    unknown poses start the search. ``only``: named unit directions (nu, r) that are the *only*
    starts (the oracle: the true directions). ``v0``: channel variances to start the
    feasible-GLS rounds from (default: weights that favour no channel). Returns the final fit
    (:func:`solve`'s dict) plus ``v`` (pose-level variance per channel), ``W``, ``starts``
    (every start: name, cost under the final weights, converged, iterations),
    ``chosen_start``, ``rounds`` (feasible-GLS rounds), ``g0``, ``v0`` (as given: the rounds'
    start, which :func:`reweighting_dof` repeats).
    """
    rng = np.random.default_rng(seed)
    known_mag = np.linalg.norm(pr.known_M, axis=1)
    g0 = pr.magnitude if pr.magnitude is not None else float(np.median(known_mag))
    nu = len(pr.unknown)
    if nu == 0:
        raise CalibrationError("every pose has a known load: use least squares")
    # the search runs on at most SEARCH_POSES unknown poses (evenly strided)
    if nu > SEARCH_POSES:
        pick = _search_pick(nu)
        sp = pr.sub(pr.unknown[pick])
    else:
        pick, sp = np.arange(nu), pr
    # start weights that favour no channel (and are equivariant): each channel's variance left
    # after regressing it on the others (start_variances), else its spread
    psi = start_variances(pr) if v0 is None else None
    W0 = (sp.weights(np.asarray(v0, float)) if v0 is not None
          else np.broadcast_to(1.0 / np.sqrt(psi) if psi is not None else 1.0 / pr.spread,
                               (sp.P, sp.p)).copy())
    named = []
    if only is not None:
        for name, U in only.items():
            named.append((name, np.asarray(U, float)[pick]))
    else:
        # 1. the affine map of the known poses (r + 1 spanning loads), extended by |m| = g
        X = np.column_stack([pr.known_M, np.ones(len(pr.known))])
        if len(X) >= pr.r + 1 and np.linalg.matrix_rank(X) == pr.r + 1:
            Bk = np.linalg.lstsq(X, pr.Y[pr.known], rcond=None)[0]
            A, o = Bk[: pr.r].T, Bk[pr.r]
            Ws = W0[0]
            Aw = A * Ws[:, None]
            got = _directions(((sp.Y[sp.unknown] - o) * Ws) @ np.linalg.pinv(Aw).T)
            if got is not None:
                named.append(("affine map of the known poses", got))
        for name, L in (start_loads or {}).items():
            got = _directions(np.asarray(L, float)[pr.unknown][pick])
            if got is not None:
                named.append((name, got))
    results = []

    def run(name, U, W, alt=True):
        out = []
        try:
            f = solve(sp, U, g0, W)
            out.append({**f, "start": name})
            if alt:
                Ua = alternate(sp, U, g0, W)
                if not np.allclose(Ua, U):
                    f = solve(sp, Ua, g0, W)
                    out.append({**f, "start": f"{name}, alternated"})
        except (np.linalg.LinAlgError, ValueError, FloatingPointError):
            pass
        return out

    for name, U in named:
        results += run(name, U, W0)
    if only is None:
        pool = []
        for i in range(random_starts):
            U = rng.standard_normal((len(sp.unknown), sp.r))
            U /= np.linalg.norm(U, axis=1, keepdims=True)
            try:
                Ua = alternate(sp, U, g0, W0)
            except (np.linalg.LinAlgError, ValueError):
                continue
            A, o = linear_fit(sp, sp.loads(Ua, g0), W0)
            pool.append((cost(sp, A, o, sp.loads(Ua, g0), W0), i, Ua))
        for _, i, Ua in sorted(pool, key=lambda t: t[:2])[:2]:
            results += run(f"random directions {i + 1}, alternated", Ua, W0, alt=False)
    if not results:
        raise CalibrationError("no start of the forward fit gave finite directions")
    best = min(results, key=lambda f: f["cost"])
    if only is None:
        for i in range(restarts):  # every unknown direction turned by about 20 degrees
            U = best["U"] + rng.normal(scale=0.35, size=best["U"].shape)
            results += run(f"perturbed restart {i + 1}", U, W0)
        best = min(results, key=lambda f: f["cost"])
    # feasible GLS on the search subset: rounds from the best start until the variances settle
    # (variances from its residuals, refit); then every start refitted under those final
    # weights and the lowest cost kept: the returned fit is the best of all starts under one
    # objective
    best, v, rounds = _feasible_gls(sp, best, v0)
    Wf = sp.weights(v)
    refit = [best]
    for f in results:
        if f["start"] == best["start"]:
            continue
        try:
            refit.append({**solve(sp, f["U"], f["g"], Wf), "start": f["start"]})
        except (np.linalg.LinAlgError, ValueError):
            continue
    results = refit
    best = min(results, key=lambda f: f["cost"])
    # every pose: the search subset's model placed on the other poses by the global step, then
    # refined together, the variances re-estimated once on every pose (settled on the subset's
    # hundreds of poses; a sweep's tens of thousands would only refine them, at a full solve
    # per round)
    if sp is not pr:
        W = pr.weights(v)
        U = reinfer(pr, best["A"], best["o"], best["g"], W)
        U[pick] = best["U"]
        best = {**solve(pr, U, best["g"], W, best["A"], best["o"]), "start": best["start"]}
        v = estimate_variances(pr, best)
        best = {**solve(pr, best["U"], best["g"], pr.weights(v), best["A"], best["o"]),
                "start": best["start"]}
        rounds += 1
    starts = [{"start": f["start"], "cost": f["cost"], "converged": f["converged"],
               "iterations": f["iterations"]} for f in results]
    return {**best, **curvature(pr, best), "v": v, "starts": starts,
            "chosen_start": best["start"], "rounds": rounds, "g0": g0, "v0": v0}


#: Logs :func:`reweighting_dof` simulates from a fit (each one solve and the feasible-GLS
#: rounds from the fit's own start: 1.3 s for 40 one-reading poses of 8 channels, 2.2 s for
#: 200). With 20 the interval's width moved by up to a fifth between seeds on one rig.
REWEIGHT_REPS = 40


def reweighting_logs(pr: Problem, fit: dict, reps: int = REWEIGHT_REPS,
                     seed: int = 0) -> np.ndarray | None:
    """The logs of :func:`reweighting_dof`: ``log(v_b / v)`` of each refitted log (rows) and
    channel (columns); None as there. Beyond :data:`SEARCH_POSES` unknown poses the logs are
    simulated on the search's own strided subset (:func:`fit_forward`'s rounds ran there)."""
    out = _refits(pr, fit, reps, seed)
    return None if out is None else out["logs"]


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
    logs, spread, spread_ls, lag1 = [], [], [], []
    for _ in range(reps):
        z = rng.standard_normal(truth.shape)
        if rho is not None and n > 1:
            e = rng.standard_normal((n, p))
            for c in range(p):
                a = float(np.clip(rho[c], 0.0, 0.999))
                if a > 0:
                    e[:, c] = lfilter([np.sqrt(1 - a * a)], [1.0, -a], e[:, c],
                                      zi=[a * e[0, c]])[0]
            z[mine] = e[orig[mine]]
        Y = truth + z * sd
        q = Problem(Y, pr.counts, pr.within if pr.repeats else None, pr.known, pr.known_M,
                    pr.magnitude)
        W0 = (np.broadcast_to(1.0 / q.spread, (q.P, q.p)).copy() if v0 is None
              else q.weights(np.asarray(v0, float)))
        try:
            f = solve(q, U, g, W0, A, o)
            fb, vb, _ = _feasible_gls(q, f, v0)
        except (np.linalg.LinAlgError, ValueError, FloatingPointError):
            continue
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


#: Significance level of :func:`noise_correlation`'s test: the conventional 1 %. A false
#: positive is shrunk by its own significance (:func:`shared_noise`), not to nothing, and the F
#: null runs a little hot on fitted residuals (a channel's misestimated variance makes its
#: range and complement parts correlate): at 5 % the payload study's rigs with independent
#: noise were whitened on 8-13 % of fits and the 12-gauge case's 95th percentile rose from 1.21
#: to 1.38x least squares; at 1 %, 0-5 % and unchanged (docs/calib.md).
CORRELATION_ALPHA = 0.01


def _range_and_complement(pr: Problem, fit: dict):
    """A fit's residuals, in channels scaled by its noise (``sd``), as ``A_s eta + N xi``:
    ``eta`` (P, r) in load units along the span of ``A_s = A / sd``, ``xi`` (P, p - r) along an
    orthonormal basis ``N`` of its complement. Returns ``(Bm, eta, xi, sd, G0)`` with ``Bm =
    [A_s N]`` and ``G0 = (A_s^T A_s)^-1`` (the covariance of ``eta`` were the scaled noise
    white)."""
    r = pr.r
    sd = np.sqrt(fit["v"])
    As = fit["A"] / sd[:, None]
    E = (pr.Y - fit["M"] @ fit["A"].T - fit["o"]) * np.sqrt(pr.counts)[:, None] / sd
    Q, _ = np.linalg.qr(As, mode="complete")
    Bm = np.column_stack([As, Q[:, r:]])
    coef = np.linalg.solve(Bm, E.T).T
    return Bm, coef[:, :r], coef[:, r:], sd, np.linalg.inv(As.T @ As)


def _shared_noise(pr: Problem, fit: dict) -> dict | None:
    """How much of the noise along the span of ``A`` the noise outside it predicts, and the
    channels' noise covariance that follows.

    In channels scaled by the fit's noise the residual is ``A_s eta + N xi``
    (:func:`_range_and_complement`). ``xi`` is seen whole at every pose. ``eta`` is not: a
    pose's fitted direction takes up its two tangent components, and what is left is its
    radial part ``u^T eta`` (exactly, to first order, whatever the weights), at a known pose
    all of it. Independent channel noise makes ``eta`` and ``xi`` independent; noise the
    channels share (a wrench mixed from gauges) makes ``eta = Gamma xi + eps``. ``Gamma`` (r, p
    - r) is the least-squares regression of the radial parts on ``u (x) xi`` (a known pose's
    three components on ``I (x) xi``), each row weighted by its variance under independence
    (``u^T G0 u``). Its Wald statistic ``W`` on ``m = r (p - r)`` coefficients tests ``Gamma =
    0`` (``W / m ~ F(m, n - m)``, ``n`` the rows), and ``Gamma`` is shrunk by the positive-part
    James-Stein factor ``1 - (m - 2) (n - m) / ((n - m + 2) W)`` (``m >= 3``; a weak estimate
    is pulled toward independence by as much as it is noise, a strong one is kept). Why not the
    full covariance: its part inside the span is seen one radial component per pose, and a free
    direction per pose makes its likelihood unbounded (docs/calib.md); the calibration needs
    only ``Gamma`` and the covariance of ``xi``, the rest (``eps``'s covariance, taken as the
    radial residuals' variance ``c`` times ``G0``) only weighs the directions. ``c``'s degrees
    of freedom: the rows less the regression's ``m`` and the ``r (r + 1)`` that the fitted ``A``
    and ``o`` take from the range (one more with a fitted magnitude; exact to first order,
    whatever the weights and poses: with ``P / (P - r - 1)``, as for ``xi``, ``c`` came out
    0.77x its truth at 40 poses).

    Returns ``{"p_value", "wald", "m", "shrink", "gamma", "gamma_ls", "gamma_cov", "S",
    "parts", "rows"}`` (``gamma_ls`` the unshrunk estimate, ``gamma_cov`` its covariance
    (row-major ``vec``, at the rows' variance ``c``), ``S`` the covariance in ``pr``'s channels,
    ``rows`` what :func:`_radial_share` needs), None
    when there is nothing to test (``p <= r``, or fewer rows than coefficients)."""
    r, p = pr.r, pr.p
    if p <= r:
        return None
    Bm, eta, xi, sd, G0 = _range_and_complement(pr, fit)
    P = pr.P
    dofc = P / max(P - r - 1, 1)  # (A and o took r + 1 degrees of freedom per channel)
    Cxi = xi.T @ xi / P * dofc
    known = np.zeros(P, bool)
    known[pr.known] = True
    U = _unit(fit["M"])
    iu = ~known
    wu = 1.0 / np.sqrt(np.einsum("ja,ab,jb->j", U[iu], G0, U[iu]))
    X = [np.einsum("ja,jb->jab", U[iu], xi[iu]).reshape(-1, r * (p - r)) * wu[:, None]]
    y = [np.sum(U[iu] * eta[iu], axis=1) * wu]
    As = Bm[:, :r]
    L = np.linalg.cholesky(As.T @ As)  # L^T G0 L = I (G0 = (A_s^T A_s)^-1)
    if known.any():  # every component, rotated to unit variance under independence
        X.append(np.einsum("ab,jc->jbac", L, xi[known]).reshape(-1, r * (p - r)))
        y.append((eta[known] @ L).ravel())
    X, y = np.vstack(X), np.concatenate(y)
    n, m = X.shape
    if n <= m + 2 or not np.all(np.isfinite(X)) or not np.all(np.isfinite(y)):
        return None
    XtX = X.T @ X
    try:
        g = np.linalg.solve(XtX, X.T @ y)
        XtX_inv = np.linalg.inv(XtX)
    except np.linalg.LinAlgError:
        return None
    res = y - X @ g
    s2 = float(res @ res) / (n - m)
    # the range's own variance: the rows' residual degrees of freedom are n - m less the
    # r (r + 1) that the fitted A and o take from the range (its part of every channel's
    # coefficients; the magnitude one more where fitted: exact to first order, whatever the
    # weights and the poses)
    c = float(res @ res) / max(n - m - r * (r + 1) - (1 if pr.fit_g else 0), 1)
    if not s2 > 0:
        return None
    from scipy import stats

    wald = float(g @ XtX @ g) / s2
    shrink = (max(0.0, 1.0 - (m - 2) * (n - m) / ((n - m + 2) * wald)) if m >= 3 and wald > 0
              else 1.0)
    gamma = (shrink * g).reshape(r, p - r)
    parts = (Bm, sd, c, Cxi)
    return {"p_value": float(stats.f.sf(wald / m, m, n - m)), "wald": wald, "m": int(m),
            "shrink": float(shrink), "gamma": gamma, "gamma_ls": g.reshape(r, p - r),
            "gamma_cov": c * XtX_inv, "S": _shared_covariance(parts, gamma), "parts": parts,
            "rows": (U[iu], wu, L if known.any() else None, int(known.sum()), n),
            # the regression's residuals as seen in the range (coordinates where independent
            # noise is white): one component along a_j at each unknown pose, three at a known
            "radial": ((U[iu] @ np.linalg.inv(L).T) * wu[:, None], res[:int((~known).sum())],
                       res[int((~known).sum()):].reshape(-1, r), n,
                       m + r * (r + 1) + (1 if pr.fit_g else 0))}


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


def _shared_covariance(parts, gamma, K=None) -> np.ndarray:
    """The channels' covariance (in the fitted channels) that a shared part ``gamma`` (r, p - r)
    implies, from :func:`shared_noise`'s ``parts = (Bm, sd, c, Cxi)``: ``cov(eta) = c G0 + gamma
    Cxi gamma^T``, ``cov(eta, xi) = gamma Cxi``, ``cov(xi) = Cxi``. In the scaled channels that
    is ``c Qa Qa^T + (A_s gamma + N) Cxi (A_s gamma + N)^T`` (``Qa`` an orthonormal basis of
    ``A_s``'s span: ``A_s G0 A_s^T = Qa Qa^T`` without forming ``G0``, which an ill-conditioned
    ``A_s`` makes lose every digit). ``K``: the range's own covariance in place of ``c I`` (in
    the coordinates where independent noise is white; a draw of :func:`_range_draws`)."""
    Bm, sd, c, Cxi = parts
    r = gamma.shape[0]
    As, N = Bm[:, :r], Bm[:, r:]
    Qa, _ = np.linalg.qr(As)
    if K is None:
        R = c * (Qa @ Qa.T)
    else:  # K in the coordinates eps' = L^T eps (L L^T = A_s^T A_s): A_s L^-T K L^-1 A_s^T
        B = np.linalg.solve(np.linalg.cholesky(As.T @ As), As.T).T  # orthonormal columns
        R = B @ K @ B.T
    Kx = As @ gamma + N
    S = (R + Kx @ Cxi @ Kx.T) * np.outer(sd, sd)
    return 0.5 * (S + S.T)


#: At most this many entries (``(P p)^2``) in :func:`attenuation`'s dense hat matrix (128 MB).
HAT_ENTRIES = 16_000_000


def _radial_share(sn: dict, delta) -> float:
    """The variance a shared part ``delta`` (r, p - r) left unexplained would add to
    :func:`shared_noise`'s regression rows, on average (``delta Cxi delta^T`` read as each
    row reads the range). It cannot exceed the rows' residual variance ``c``: draws of the
    shared part's error are held to it (:func:`predict_error`)."""
    U, wu, L, n_known, n = sn["rows"]
    D = delta @ sn["parts"][3] @ delta.T
    q = np.sum(D * ((U * (wu**2)[:, None]).T @ U))  # sum_j wu_j^2 u_j^T D u_j
    if L is not None:
        q += n_known * np.trace(L.T @ D @ L)
    return float(q / n)


def _projected_blocks(G4, H, F1, F2) -> np.ndarray:
    """Every pose's (p, p) block of ``R (I (x) S) R^T`` (``R = I - G`` the residual projection
    of the linearised fit, ``G4`` its hat matrix as (P, p, P, p), ``H`` the diagonal blocks) for
    a pose covariance ``S = F1 F2^T`` (symmetric)."""
    S = F1 @ F2.T
    HS = H @ S
    GF1 = np.einsum("jaib,bq->jaiq", G4, F1)
    GF2 = np.einsum("jaib,bq->jaiq", G4, F2) if F2 is not F1 else GF1
    return S[None] - HS - HS.transpose(0, 2, 1) + np.einsum("jaiq,jbiq->jab", GF1, GF2)


def _attenuation(pr: Problem, fit: dict, sn: dict | None = None) -> np.ndarray | None:
    """How much of a shared part the regression of :func:`shared_noise` recovers: ``Lambda``
    (m, m) with ``E[gamma_ls] = Lambda vec(delta)`` for residual noise whose shared part is
    ``delta`` (in the fit's scaled channels, to first order about ``delta = 0``).

    The fitted directions and ``A`` take up part of a shared disturbance: a direction fitted
    under per-channel weights leans toward it, and ``A`` with it, the same at every pose, so the
    regression sees less of it than there is (simulated on gauge-mixed wrench rigs: 0.55-0.6 of
    it; 0.95 with the true directions). Exact to first order: the fit's residuals are ``R e``
    with ``R`` the residual projection of its linearised weighted least squares (directions,
    ``A``, ``o`` and ``g`` together), so the regression's expected cross products are linear in
    the noise covariance, ``E[X^T y] = sum_j f_j(R_j S R_j^T)``, and ``Lambda = E[X^T X]^-1
    dE[X^T y] / d delta``. The rounds of :func:`fit_correlated` stop where the estimate is 0,
    so what is left of the shared part has the regression's error divided by ``Lambda``:
    :func:`predict_error` draws it so. Costs a dense hat matrix of the fit (``(P p)^2``
    entries): on at most :data:`SEARCH_POSES` unknown poses and :data:`HAT_ENTRIES` entries (an
    evenly strided subset beyond; fewer poses attenuate more, so the subset errs wide). None
    where there is nothing to test."""
    r, p = pr.r, pr.p
    nu = len(pr.unknown)
    most = max(min(SEARCH_POSES, int(np.sqrt(HAT_ENTRIES) / p) - len(pr.known)), 1)
    if nu > most:
        pick = np.unique(np.linspace(0, nu - 1, most).round().astype(int))
        rows = np.sort(np.r_[pr.known, pr.unknown[pick]])
        q = pr.sub(pr.unknown[pick])
        fit = {**fit, "W": fit["W"][rows], "M": fit["M"][rows], "U": fit["U"][pick]}
        pr, sn = q, None
    sn = sn if sn is not None else shared_noise(pr, fit)
    if sn is None:
        return None
    P = pr.P
    W, A, U, g = fit["W"], fit["A"], fit["U"], fit["g"]
    u = pr.unknown
    k = r - 1
    nt = p * (r + 1) + (1 if pr.fit_g else 0)
    X1 = np.column_stack([pr.loads(U, g), np.ones(P)])
    J = np.zeros((P, p, nt + len(u) * k))
    for c in range(p):
        J[:, c, c * (r + 1):(c + 1) * (r + 1)] = -W[:, c:c + 1] * X1
    Jphi = -(W[u] * g)[:, :, None] * np.einsum("jkr,cr->jck", tangents(U), A)
    for i, j in enumerate(u):
        J[j, :, nt + i * k: nt + (i + 1) * k] = Jphi[i]
    if pr.fit_g:
        J[u, :, nt - 1] = -W[u] * (U @ A.T)
    J = J.reshape(P * p, -1)
    if not np.all(np.isfinite(J)):
        return None
    Q, Rq = np.linalg.qr(J)
    keep = np.abs(np.diag(Rq)) > 1e-10 * np.abs(np.diag(Rq)).max()
    Q = Q[:, keep]
    G4 = (Q @ Q.T).reshape(P, p, P, p)
    H = np.einsum("jajb->jab", G4)
    Bm, _, c, Cxi = sn["parts"]
    As, N = Bm[:, :r], Bm[:, r:]
    Binv = np.linalg.inv(Bm)
    Pa, Pn = Binv[:r], Binv[r:]
    G0 = np.linalg.inv(As.T @ As)
    L = np.linalg.cholesky(np.linalg.inv(G0))
    known = np.zeros(P, bool)
    known[pr.known] = True
    iu = ~known
    Uu = _unit(fit["M"])[iu]
    wu2 = 1.0 / np.einsum("ja,ab,jb->j", Uu, G0, Uu)
    m = r * (p - r)
    # E[X^T X] at delta = 0: the pose covariance c Qa Qa^T + N Cxi N^T
    Qa, _ = np.linalg.qr(As)
    w, V = np.linalg.eigh(Cxi)
    F0 = np.column_stack([np.sqrt(c) * Qa, N @ (V * np.sqrt(np.clip(w, 0, None)))])
    Cr = _projected_blocks(G4, H, F0, F0)
    Cxx = np.einsum("ca,jab,eb->jce", Pn, Cr, Pn)
    EX = np.einsum("j,ja,jb,jce->acbe", wu2, Uu, Uu, Cxx[iu]).reshape(m, m)
    EX += np.einsum("ab,jce->acbe", L @ L.T, Cxx[known]).reshape(m, m)
    # dE[X^T y] / d delta_ab: the pose covariance's derivative A_s e_a (N Cxi e_b)^T + transpose
    NC = N @ Cxi
    D = np.empty((m, m))
    for a in range(r):
        for b in range(p - r):
            F1 = np.column_stack([As[:, a], NC[:, b]])
            F2 = np.column_stack([NC[:, b], As[:, a]])
            Cr = _projected_blocks(G4, H, F1, F2)
            Cxe = np.einsum("ca,jab,eb->jce", Pn, Cr, Pa)
            out = np.einsum("j,ja,jc->ac", wu2, Uu, np.einsum("jce,je->jc", Cxe[iu], Uu))
            out += np.einsum("ab,jce,eb->ac", L, Cxe[known], L)
            D[:, a * (p - r) + b] = out.ravel()
    try:
        lam = np.linalg.solve(EX, D)
    except np.linalg.LinAlgError:
        return None
    return lam if np.all(np.isfinite(lam)) else None


def shared_noise(pr: Problem, fit: dict) -> dict | None:
    """:func:`_shared_noise`, or None where its linear algebra fails (a singular or non-finite
    regression on a degenerate fit): the callers then treat the noise as independent, as they
    do where there is nothing to test, rather than stop."""
    try:
        with np.errstate(all="ignore"):
            sn = _shared_noise(pr, fit)
    except (np.linalg.LinAlgError, ValueError, FloatingPointError):
        return None
    if sn is None or not all(np.all(np.isfinite(sn[k])) for k in ("S", "gamma_cov")):
        return None
    return sn


#: :func:`range_level` needs at least this many degrees of freedom of the radial residuals.
RANGE_LEVEL_MIN_DOF = 5


def range_level(pr: Problem, fit: dict) -> tuple[float, int] | None:
    """Where the channels' variances are not identified (Ledermann's bound, as
    :data:`UNIDENTIFIED_ROUNDS`: p <= 5 channels for 3 load components), the noise level along
    the span of ``A``, where the calibration's error lives, measured on the fit's radial
    residuals: ``(c, dof)``, ``c`` their variance over what the fitted variances predict for
    them (:func:`_shared_noise`'s ``c``, about 1 where they are right) on ``dof`` degrees of
    freedom; None where the variances are identified, or where there is nothing to measure.

    Why: with one complement dimension or two, the rounds settle each channel's variance where
    their start and the directions' give-and-take leave it, 0.4-38x its truth on 4-channel
    payload rigs, and the refits that measure the variances' spread start there too, so they
    do not see it (degrees of freedom up to 2e12). The radial residuals see the noise the
    calibration carries directly: one number per unknown pose, three per known one. On 30
    4-channel payload rigs (seeds 10,000-10,029, stop 65) ``c`` correlated 0.70 in logs with
    the measured error's square over its prediction, and :func:`predict_error` drawing the
    level from it (a scaled inverse chi-square) held the measured error in its 95 % interval
    on 29 of 30 (24 before)."""
    if (pr.p - pr.r) ** 2 >= pr.p + pr.r:
        return None
    sn = shared_noise(pr, fit)
    if sn is None:
        return None
    c = float(sn["parts"][2])
    dof = int(sn["radial"][3] - sn["radial"][4])
    if not (np.isfinite(c) and c > 0) or dof < RANGE_LEVEL_MIN_DOF:
        return None
    return c, dof


def attenuation(pr: Problem, fit: dict, sn: dict | None = None) -> np.ndarray | None:
    """:func:`_attenuation`, or None where its linear algebra fails or gives a non-finite
    ``Lambda`` (:func:`predict_error` then draws the regression's error unattenuated)."""
    try:
        with np.errstate(all="ignore"):
            lam = _attenuation(pr, fit, sn)
    except (np.linalg.LinAlgError, ValueError, FloatingPointError):
        return None
    return lam if lam is not None and np.all(np.isfinite(lam)) else None


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
#: not a regulariser: with the last round returned, a cap of 8 (stops 55-56) stopped rounds that
#: were still improving the fit (payload rig 10,069 written at 3.98x least squares; 1.62x after
#: 30) and 30 let others drift away from the data (the real wrist sensor's plan fit 1.14 ->
#: 1.24x), both visible in the likelihood (docs/calib.md, "The likeliest round").
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


#: Significance level of :func:`direction_misfit`'s test (one-sided, by permutation).
DIRECTION_ALPHA = 0.01
#: Permutations of :func:`direction_misfit`'s null (its p-value's resolution: 1 / 201).
DIRECTION_PERMUTATIONS = 200

#: :func:`outlying_readings`: a reading is outlying where its tail probability is below this
#: over the number of readings (Bonferroni: a log of gaussian readings has none flagged in about
#: 999 of 1,000 fits, whatever its length)
OUTLIER_ALPHA = 1e-3


def outlying_readings(pr: Problem, fit: dict, alpha: float = OUTLIER_ALPHA) -> dict | None:
    """Readings that lie far from the fitted model (a spike, a glitch, a known load stated for
    the wrong reading), from a log of single readings.

    Each reading's residual, every channel scaled by its fitted noise, gives ``d``, its sum of
    squares: chi-square with ``p - (r - 1)`` degrees of freedom at an unknown pose of the stated
    magnitude (its direction takes up ``r - 1``; ``p - r`` where the magnitude is fitted). A
    known reading's is taken as the same: the few known readings pin the fit's rotation, so the
    fit takes up as much of theirs (measured on clean payload rigs, the mean ``d`` at the known
    readings: 6.17 with 8 channels, 8.99 with 12; at the unknown ones 5.86 and 9.73, of 6 and 10
    degrees of freedom; with ``p`` degrees of freedom a known reading's test missed more). A
    spike inflates the fitted noise it is scaled by, so ``d`` is first divided by the unknown
    poses' median of it over the chi-square's median (a robust scale, 1 under the model). A
    reading is flagged where its tail probability is below ``alpha / P``. Units, channel order
    and offsets do not change it. Returns ``{"poses", "p_values", "scale", "min_p_value"}``
    (the flagged poses' indices into ``pr.Y``, their tail probabilities, the robust scale, and
    the smallest tail probability of all), or None with fewer than 10 unknown poses."""
    from scipy.stats import chi2

    un = pr.unknown
    if len(un) < 10:
        return None
    E = ((pr.Y - fit["M"] @ fit["A"].T - fit["o"]) * np.sqrt(pr.counts)[:, None]
         / np.sqrt(fit["v"]))
    if not np.all(np.isfinite(E)):
        return None
    d = np.sum(E**2, axis=1)
    df = float(pr.p - pr.r if pr.fit_g else pr.p - pr.r + 1)
    scale = float(np.median(d[un]) / chi2.median(df))
    if not scale > 0:
        return None
    pv = chi2.sf(d / scale, df)
    out = np.flatnonzero(pv < alpha / pr.P)
    return {"poses": out, "p_values": pv[out], "scale": scale, "min_p_value": float(pv.min())}


def direction_misfit(pr: Problem, fit: dict, permutations: int = DIRECTION_PERMUTATIONS,
                     seed: int = 0) -> dict | None:
    """Whether a fit's residuals are a smooth function of the load's direction (a sensor that
    is not linear in the load: a gauge's nonlinearity, cross-talk) rather than noise, from a log
    of single readings.

    Noise at one reading is independent of the next; a misfit that depends on the load's
    direction is nearly the same at nearby directions. Each unknown pose's residual (every
    channel scaled by its fitted noise) is paired with the pose nearest to it in fitted
    direction, and ``rho``, the sum of the pairs' products over the sum of squares (about the
    misfit's share of the residual variance), is tested against the same statistic with the
    pairs drawn at random (``permutations`` of them; one-sided p-value, ``(1 + #null >= rho) /
    (1 + permutations)``). The fitted directions make neighbouring residuals slightly
    anti-correlated under noise alone, so the permutation null is conservative.

    A log whose readings follow a path has neighbours in direction that are neighbours in time
    too, where noise correlated in time (a slow wander, drift) would read as misfit. So pairs
    closer in the log than ``window`` readings are not paired, ``window`` the first lag at which
    the residuals' autocorrelation (averaged over the channels) falls inside its 95 % band under
    independence, ``2 / sqrt(n)``, and the null's random pairs are drawn as far apart in the log
    as the neighbours are (the neighbours' lags shuffled among the readings): what noise
    correlated in time adds to ``rho`` it adds to the null alike. (With the window alone,
    AR(0.9) sweeps of 1,000 training readings were found nonlinear on 3 of 4; with the matched
    null on none, and an AR(0.99) sweep still on 1 of 4: where the noise is that slow the
    caller does not use the test, :func:`calib.joint.fit_forward_rows`.) Long logs are tested
    on their :data:`SEARCH_POSES` evenly strided unknown poses (in the log's order).

    Measured (stop 64; docs/calib.md, "Gauges that are not linear"): on payload rigs whose
    gauges are 2 % nonlinear p < 0.01 on 8 of 10, at 5 % on 10 of 10; on 40 rigs with linear
    gauges (independent or gauge-mixed noise, 6 or 8 or 12 channels) p >= 0.18; on the real
    wrist sensor (42 fits) p >= 0.10. Units, channel order and offsets do not change it
    (residuals scaled by their channel's noise). Returns ``{"rho", "p_value", "pairs",
    "window", "median_angle_deg"}``, or None with fewer than 10 unknown poses."""
    un = pr.unknown
    if len(un) > SEARCH_POSES:
        un = un[_search_pick(len(un))]
    n = len(un)
    if n < 10:
        return None
    E = ((pr.Y[un] - fit["M"][un] @ fit["A"].T - fit["o"]) * np.sqrt(pr.counts[un])[:, None]
         / np.sqrt(fit["v"]))
    if not np.all(np.isfinite(E)):
        return None
    U = _unit(fit["M"][un])
    # the window: the first lag whose channel-averaged autocorrelation is insignificant
    Ec = E - E.mean(axis=0)
    g0 = np.maximum(np.sum(Ec * Ec, axis=0), 1e-300)
    band = 2.0 / np.sqrt(n)
    window = n // 4
    for lag in range(1, n // 4):
        if float(np.mean(np.sum(Ec[lag:] * Ec[:-lag], axis=0) / g0)) < band:
            window = lag
            break
    G = U @ U.T
    idx = np.arange(n)
    G[np.abs(idx[:, None] - idx[None, :]) < window] = -np.inf  # itself and its time neighbours
    k = np.argmax(G, axis=1)
    ok = np.isfinite(G[idx, k])
    if ok.sum() < 10:
        return None
    i, k = idx[ok], k[ok]
    den = float(np.sum(E[i] ** 2))
    if not den > 0:
        return None
    rho = float(np.sum(E[i] * E[k])) / den
    rng = np.random.default_rng(seed)
    lags = np.abs(k - i)
    hits = 0
    for _ in range(permutations):
        # the null's pairs are as far apart in the log as the neighbours are (their lags
        # shuffled), in a random direction: noise correlated in time weighs on both alike
        lag = rng.permutation(lags)
        up = i + lag
        down = i - lag
        pick_up = (rng.random(len(i)) < 0.5) & (up < n) | (down < 0)
        kk = np.where(pick_up, up, down)
        kk = np.clip(kk, 0, n - 1)
        hits += float(np.sum(E[i] * E[kk])) / den >= rho
    ang = np.degrees(np.arccos(np.clip(np.sum(U[i] * U[k], axis=1), -1.0, 1.0)))
    return {"rho": rho, "p_value": (1.0 + hits) / (1.0 + permutations), "pairs": int(len(i)),
            "window": int(window), "median_angle_deg": float(np.median(ang))}


def gls_inverse(A, v) -> np.ndarray:
    """The calibration of a fitted forward model: ``C = (A^T V^-1 A)^-1 A^T V^-1`` (dof, p), the
    maximum-likelihood load of a new reading ``z`` being ``C (z - o)``."""
    Ai = A / v[:, None]
    return np.linalg.solve(A.T @ Ai, Ai.T)


def _global_cov(fit: dict) -> np.ndarray | None:
    """Covariance of (A, o[, g]) with the directions as nuisance: the inverse Schur complement."""
    S = fit["schur"]
    try:
        cov = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        return None
    cov = 0.5 * (cov + cov.T)
    return cov if np.all(np.isfinite(cov)) and np.all(np.diag(cov) >= 0) else None


#: One-sided significance of a channel's lag-1 residual autocorrelation, in the log's order,
#: before :func:`serial_correlation` takes the log's noise as correlated in time.
SERIAL_ALPHA = 0.01
#: Rounds, and refits in each, that set the simulated noise's AR coefficient in
#: :func:`serial_correlation` (the refits' residual autocorrelation matched to the log's).
SERIAL_ROUNDS = 3
SERIAL_PROBE_REPS = 10


def serial_correlation(pr: Problem, fit: dict, n: int, reps: int = REWEIGHT_REPS,
                       seed: int = 0, alpha: float = SERIAL_ALPHA) -> dict | None:
    """Noise correlated in time in a log of single readings (its first ``n`` poses, in the order
    recorded), and what it does to the fit's uncertainty, measured.

    A sweep read faster than the sensor's noise changes (a filtered output, a slow wander) has
    each reading's noise close to the last one's; the fit's covariance counts every reading as
    independent. On simulated 2,000-reading payload sweeps (1,000 training readings) whose noise
    is an AR(1) along the log, the error measured on a new session lay inside the predicted 95 %
    interval on 4 of 6 rigs at coefficient 0.9 and 0 of 6 at 0.99 (1.8-2.8x the predicted
    median); with this correction on 6 of 6 and 5 of 6 (docs/calib.md, "Noise correlated in
    time").

    Each channel's residuals' lag-1 autocorrelation ``rho`` (in the channels fitted). Where the
    channels together are not significant at ``alpha`` (``n sum rho^2`` against a chi-square
    with ``p`` degrees of freedom) or no channel's exceeds its one-sided ``alpha`` point under
    independence, ``z_alpha / sqrt(n)``, returns None. Otherwise ``reps`` logs are simulated
    from the fit and refitted from its directions (the feasible-GLS rounds, :func:`_refits`)
    twice: with independent noise, and with AR(1) noise along the log on the channels found
    correlated. The residuals' autocorrelation is the noise's attenuated (the fitted directions
    and offsets take up slow noise), so the simulated coefficients are first set, in
    :data:`SERIAL_ROUNDS` rounds of :data:`SERIAL_PROBE_REPS` refits, until the refits'
    residuals reach the log's. Returns

    - ``dof`` (``white_dof``): each channel's variance degrees of freedom from the AR
      (independent) refits (:func:`dof_of_logs`);
    - ``parameter_factor``: per channel, how much wider the refitted ``(a_c, o_c)`` spread
      under the AR noise than under independent noise (in the fit's covariance metric; at least
      1); ``ls_factor`` the same of least squares with every load known (fitted to the same
      correlated readings);
    - ``variance_bias``: per channel found correlated, the AR refits' variance estimates over
      the independent ones' (geometric mean, at most 1; 1 elsewhere): slow noise taken up by
      the fit leaves the variances low;
    - ``rho``, ``correlated`` (the channels found so), ``simulated_rho``.

    :func:`predict_error` takes these (``serial``) for the printed error and interval.

    Why simulated, not a sandwich: a Newey-West covariance of the channels' regression scores
    widened the forward fit's error by too much (measured 0.71-0.89 of its prediction at 0.9;
    the unknown directions carry much of it) and, through the paired ratio, refused 3 of 6 fits
    the oracle makes within 1.5x least squares at 0.99."""
    from scipy.stats import chi2, norm

    n = int(n)
    if n < 8:
        return None
    e = pr.Y[:n] - fit["M"][:n] @ fit["A"].T - fit["o"]
    rho = _lag1(e)
    # the channels together first (Box-Pierce at lag 1: n sum rho^2 against chi-square with a
    # degree of freedom a channel), then each channel one-sided
    if chi2.sf(n * float(np.sum(rho**2)), pr.p) >= alpha:
        return None
    hot = rho > norm.isf(alpha) / np.sqrt(n)
    if not hot.any():
        return None
    white = _refits(pr, fit, reps, seed, spreads=True)
    if white is None:
        return None
    # the residuals' autocorrelation is the noise's attenuated (the fitted directions take up
    # slow noise across the load): the simulated noise's coefficient is set so that the refits'
    # residuals reach the log's, on the rows refitted (a sweep's search subset), in the scale of
    # log(1 - rho)
    rows = white["rows"][white["rows"] < n]
    target = np.minimum(_lag1(e[rows]), 0.9999)
    sim = np.where(hot, np.clip(rho, 0.0, 0.999), 0.0)
    for _ in range(SERIAL_ROUNDS):
        probe = _refits(pr, fit, SERIAL_PROBE_REPS, seed, rho=sim, n=n)
        if probe is None or probe["lag1"] is None:
            return None
        got = np.minimum(probe["lag1"], 0.9999)
        sim = np.where(hot, np.clip(1 - (1 - sim) * (1 - target) / (1 - got), 0.0, 0.999), 0.0)
    red = _refits(pr, fit, reps, seed, rho=sim, n=n, spreads=True)
    if red is None:
        return None
    one = np.ones(pr.p)
    pf = (np.maximum(red["fit_spread"] / np.maximum(white["fit_spread"], 1e-300), 1.0)
          if red["fit_spread"] is not None and white["fit_spread"] is not None else one)
    pl = np.maximum(red["ls_spread"] / np.maximum(white["ls_spread"], 1e-300), 1.0)
    # slow noise is taken up by the fitted directions and offsets beyond what the leverage
    # correction allows for independent noise: the variances come out low, by as much on the
    # refits (their mean log ratio under the AR noise over that under independent noise)
    bias = np.where(hot, np.minimum(np.exp(red["logs"].mean(axis=0)
                                           - white["logs"].mean(axis=0)), 1.0), 1.0)
    return {"rho": rho, "correlated": hot, "simulated_rho": sim, "dof": dof_of_logs(red["logs"]),
            "white_dof": dof_of_logs(white["logs"]),
            "variance_bias": bias,
            "parameter_factor": pf, "ls_factor": pl}


#: At most this many test readings in :func:`predict_error`'s Monte Carlo (evenly strided poses
#: of larger rigs: the interval is then that of a 2,000-reading test set, a little wider than a
#: larger one's).
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


def _unit(M) -> np.ndarray:
    """Rows of ``M`` scaled to unit length (zero rows stay zero)."""
    n = np.linalg.norm(M, axis=1, keepdims=True)
    return M / np.where(n > 0, n, 1.0)


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
    noise: what :func:`calib.reliability.assess` holds to its ceiling; the two parameter
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
        sv = np.sqrt(v)
        try:  # the range's own covariance: its posterior given the rows (not one number)
            Kd = _range_draws(sn, rng, draws)
        except (np.linalg.LinAlgError, ValueError):
            Kd = None
    for i in range(draws):
        s = rng.chisquare(dof) / dof * bias
        vi = v / s  # the variance an estimate of v could have come from
        # the fit's error scales with the true noise: each channel's block by sqrt(vi / v)
        d = (L @ rng.standard_normal(nth)).reshape(p, r + 1) * (grow / np.sqrt(s))[:, None]
        dl = np.einsum("cab,cb->ca", Lls, rng.standard_normal((p, r + 1))) * grow_ls[:, None]
        if sn is None:
            # least squares' error scales with the true noise as the fit's does (both are
            # fitted to the same readings)
            dl = dl * np.sqrt(1.0 / s)[:, None]
            if level is not None:  # the noise along the load's span, as its radial parts say
                t = level[0] * level[1] / rng.chisquare(level[1])
                vi, d, dl = vi * t, d * np.sqrt(t), dl * np.sqrt(t)
            Z = truth + rng.standard_normal((P, p)) * np.sqrt(vi + pr.within**2)  # one reading
            Cw = None
        else:  # the shared part's error: correlated noise, errors mixed across channels
            dg = (Lg @ rng.standard_normal(len(Lg))).reshape(r, p - r)
            q = _radial_share(sn, dg)
            if q > sn["parts"][2]:  # more than the radial residuals hold: to their variance
                dg = dg * np.sqrt(sn["parts"][2] / q)
            Si = _shared_covariance(sn["parts"], dg, None if Kd is None else Kd[i]) / np.sqrt(
                np.outer(s, s))
            w, V = np.linalg.eigh(Si)
            half = (V * np.sqrt(np.clip(w, 0, None))) @ V.T
            mix = half / sv[None, :]
            # (d's per-channel 1 / sqrt(s) undone first: Si carries the variances' draw)
            d, dl = mix @ (d * np.sqrt(s)[:, None]), mix @ dl
            Z = truth + rng.standard_normal((P, p)) @ half
            Cw = np.linalg.pinv(Si)  # least squares with every load known weighs by the truth
        if sd > 0:  # the fits' share of the stated loads' error; the test loads' own
            d = d + (L_lab @ rng_lab.standard_normal(nth)).reshape(p, r + 1)
            dl = dl + (L_lab_ls @ rng_lab.standard_normal(nth)).reshape(p, r + 1)
            Z = Z - _label_error(rng_lab, M, sd, tangent) @ A.T  # the applied, not the stated
        Ah, oh = A + d[:, :r], o + d[:, r]
        Ch = gls_inverse(Ah, v)  # the calibration weighs by the estimate, the truth is vi
        err[i] = np.sqrt(np.mean(np.sum(((Z - oh) @ Ch.T - M) ** 2, axis=1)))
        Al, ol = A + dl[:, :r], o + dl[:, r]
        Cl = (gls_inverse(Al, v) if Cw is None
              else np.linalg.solve(Al.T @ Cw @ Al, Al.T @ Cw))
        err_ls[i] = np.sqrt(np.mean(np.sum(((Z - ol) @ Cl.T - M) ** 2, axis=1)))
    lo, hi = np.quantile(err, [(1 - coverage) / 2, (1 + coverage) / 2])
    med, med_ls = float(np.median(err)), float(np.median(err_ls))
    return {"rms": med, "interval": [float(lo), float(hi)], "coverage": coverage,
            "ls_rms": med_ls, "ratio": med / med_ls if med_ls > 0 else float("inf"),
            "upper_ratio": float(np.quantile(err / np.maximum(err_ls, 1e-300),
                                             (1 + ratio_coverage) / 2)),
            "ratio_coverage": ratio_coverage,
            "interval_ratio": float(hi) / med_ls if med_ls > 0 else float("inf"),
            "upper_bounded": True,  # (calib.joint.one_sided: not where the sensor reads nonlinear)
            "test_readings": int(P),
            "range_level": None if level is None else {"c": level[0], "dof": level[1]}}
