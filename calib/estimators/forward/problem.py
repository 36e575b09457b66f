"""The forward problem ``z = A m + o`` (:class:`Problem`) and its weighted least-squares solver.

Levenberg-Marquardt on all parameters at once, the unknown directions eliminated pose by pose
(Schur complement); the exact best direction of one pose on its sphere (:func:`reinfer`), and
the alternation of model and directions (:func:`alternate`). See :mod:`calib.estimators.forward`.
"""

from __future__ import annotations

import numpy as np

from calib.data.result import CalibrationError

#: Points of :func:`grid` (about 5 degrees apart on the sphere).
#: Decision: docs/calib_design.md D36.
GRID = 2000


#: At most this many unknown poses enter the search over starts; with more (a long sweep, one
#: reading per pose), the starts run on an evenly strided subset and the best is then refined on
#: every pose (same estimator, same optimum basin: the subset only chooses the basin).
#: Decision: docs/calib_design.md D36.
SEARCH_POSES = 400


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
    smallest eigenvalue ``l_0`` and ``|u| = 1``. In Q's eigenbasis (``c`` the coefficients of b,
    ``d_i = l_i - l_0``, ``t = l_0 - mu > 0``) that is the root of ``1 / n(t) = 1`` with
    ``n(t)^2 = sum_i c_i^2 / (d_i + t)^2``; ``1 / n`` is concave and increasing in ``t`` (Moré
    and Sorensen 1983, "Computing a trust region step"), so Newton's method from a ``t`` left of
    the root, ``t = |c_0|`` (there ``n >= 1``), climbs to it without overshooting, each row until
    its step no longer moves it (quadratic convergence: a few steps where bisection takes about
    64). Exact, unlike a grid, and O(m). The hard case (b orthogonal to the lowest
    eigenvector: ``n < 1`` at the smallest ``t``): the rest of the unit length along it."""
    lam, V = np.linalg.eigh(Q)
    c = np.einsum("jab,ja->jb", V, b)  # b in the eigenbasis
    c2 = c**2
    nb = np.maximum(np.linalg.norm(b, axis=1), 1e-300)
    d = lam - lam[:, :1]
    tmin = 1e-15 * np.maximum(np.abs(lam).max(axis=1), nb)
    # (b's component along the lowest eigenvector exactly 0: the hard case, from the smallest t)
    t = np.where(c[:, 0] != 0, np.abs(c[:, 0]), tmin)
    a = np.arange(len(t))
    for _ in range(100):
        e = d[a] + t[a, None]
        n2 = np.sum(c2[a] / e**2, axis=1)
        left = n2 > 1  # still left of the root
        if not left.any():
            break
        a, e, n2 = a[left], e[left], n2[left]
        n = np.sqrt(n2)
        # Newton on 1 / n(t) - 1: d(1 / n) / dt = sum_i c_i^2 / (d_i + t)^3 / n^3
        step = (1.0 - 1.0 / n) * n2 * n / np.sum(c2[a] / e**3, axis=1)
        t1 = t[a] + step
        moved = t1 > t[a]
        t[a[moved]] = t1[moved]
        a = a[moved]
        if not len(a):
            break
    x = c / (d + t[:, None])
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
    T = tangents(U) if len(u) else None
    # a for every row: -W_jc X_j in channel c's block (and -W_jc a_c.u_j for g, unknown poses)
    for c in range(p):
        sl = slice(c * (r + 1), (c + 1) * (r + 1))
        a = np.zeros((pr.P, nt))
        a[:, sl] = -W[:, c : c + 1] * X
        if pr.fit_g:
            a[u, -1] = -W[u, c] * (U @ A[c])
        if len(u):
            b = -(W[u, c] * g)[:, None] * (T @ A[c])  # (nu, k)
            Db = np.einsum("jkl,jl->jk", Dinv, b)
            a[u] -= (B @ Db[:, :, None])[:, :, 0]
            h[u, c] = np.einsum("jk,jk->j", b, Db)
        h[:, c] += np.sum((a @ Sinv) * a, axis=1)
    return h


def _unit(M) -> np.ndarray:
    """Rows of ``M`` scaled to unit length (zero rows stay zero)."""
    n = np.linalg.norm(M, axis=1, keepdims=True)
    return M / np.where(n > 0, n, 1.0)
