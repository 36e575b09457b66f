"""Many logs, or many starts, of one rig solved together: :func:`solve` and
:func:`_feasible_gls` with a leading batch axis, each log stepping through its own
Levenberg-Marquardt and feasible-GLS rounds in lockstep with the others (its own damping, its own
acceptance, its own stopping).

The logs share everything but their readings: the poses, which of them are known and their
loads, the counts and the within-pose scatter. That is what :func:`~.refits._refits` simulates
(logs drawn from a fit's own noise, refitted from the fit's directions), whose serial loop of
small solves spent most of a one-reading joint fit's time in per-call overhead on matrices of a
few dozen rows. Each log takes the same decisions as the serial solver would (the same damping
schedule, the same acceptance and stopping rules); the arithmetic is the same up to the order of
summation in the batched products (results agree to about 1e-12 relative; a step that the serial
solver accepts by less than that can go the other way, which moves the optimum reached by less
than the convergence tolerance). Any failure the serial solver would raise is raised here too:
the caller then repeats the logs serially (:func:`~.refits._refits`). The random starts of
:func:`~.fit.fit_forward` are alternated the same way (:func:`alternate_batch`).
"""

from __future__ import annotations

import copy

import numpy as np

from calib.estimators.forward.problem import Problem, sphere_minimum, tangents
from calib.estimators.forward.variances import (
    MAX_REWEIGHT_ROUNDS,
    REWEIGHT_TOL,
    UNIDENTIFIED_ROUNDS,
    estimate_variances,
)


class Batch:
    """``b`` logs of one rig: ``Y`` (b, P, p), the rest of :class:`Problem` shared (``pr``)."""

    def __init__(self, pr: Problem, Y):
        self.pr = pr
        self.Y = np.asarray(Y, float)
        self.b = len(self.Y)
        self.spread = np.maximum(self.Y.std(axis=1), 1e-300)  # (b, p), as Problem.spread

    def problem(self, i: int) -> Problem:
        """Log ``i`` as a :class:`Problem` of its own (the shared parts not copied)."""
        q = copy.copy(self.pr)
        q.Y, q.spread = self.Y[i], self.spread[i]
        return q

    def loads(self, U, g):
        """Every log's loads (b, P, r): the known ones, ``g U`` at the unknown poses."""
        return _loads(self.pr, U, g)

    def weights(self, v):
        """:meth:`Problem.weights` of each log's variances ``v`` (b, p): (b, P, p)."""
        pr = self.pr
        if pr.repeats:
            return 1.0 / np.sqrt(v[:, None, :] + pr.within[None, None, :] ** 2
                                 / pr.counts[None, :, None])
        return np.sqrt(pr.counts[None, :, None] / v[:, None, :])


def _loads(pr: Problem, U, g):
    """:meth:`Problem.loads` of many directions U (b, nu, r) and magnitudes g (b,)."""
    M = np.zeros((len(U), pr.P, pr.r))
    M[:, pr.known] = pr.known_M
    M[:, pr.unknown] = g[:, None, None] * U
    return M


def _cost(Y, A, o, M, W):
    R = W * (Y - M @ A.transpose(0, 2, 1) - o[:, None, :])
    return np.sum(R**2, axis=(1, 2))


def _normal_equations(bt: Batch, idx, W, A, o, U, g):
    """:func:`~.problem._normal_equations` of the logs ``idx``: R, H, grad, D, gphi, B, T with
    a leading batch axis."""
    pr = bt.pr
    r, p = pr.r, pr.p
    u = pr.unknown
    n, nu, k = len(idx), len(u), r - 1
    nt = p * (r + 1) + (1 if pr.fit_g else 0)
    M = bt.loads(U, g)
    X = np.concatenate([M, np.ones((n, pr.P, 1))], axis=2)  # (n, P, r+1)
    R = W * (bt.Y[idx] - M @ A.transpose(0, 2, 1) - o[:, None, :])
    W2 = W**2
    H = np.zeros((n, nt, nt))
    grad = np.zeros((n, nt))
    WX = W2.transpose(0, 2, 1)[..., None] * X[:, None]  # (n, p, P, r+1)
    Hc = WX.transpose(0, 1, 3, 2) @ X[:, None]  # (n, p, r+1, r+1)
    for c in range(p):
        s = slice(c * (r + 1), (c + 1) * (r + 1))
        H[:, s, s] = Hc[:, c]
    grad[:, : p * (r + 1)] = -((W * R).transpose(0, 2, 1) @ X).reshape(n, -1)
    T = (tangents(U.reshape(n * nu, r)).reshape(n, nu, k, r) if nu
         else np.zeros((n, 0, k, r)))
    Wu = W[:, u]
    TA = (T @ A.transpose(0, 2, 1)[:, None]).transpose(0, 1, 3, 2)  # (n, nu, p, k)
    Jphi = -(Wu * g[:, None, None])[..., None] * TA
    JphiT = Jphi.transpose(0, 1, 3, 2)
    D = JphiT @ Jphi
    gphi = (JphiT @ R[:, u][..., None])[..., 0]
    B = np.zeros((n, nu, nt, k))
    Bc = -(Wu[..., None, None] * X[:, u][:, :, None, :, None]) * Jphi[:, :, :, None, :]
    B[:, :, : p * (r + 1)] = Bc.reshape(n, nu, p * (r + 1), k)
    if pr.fit_g:
        Jg = -Wu * (U @ A.transpose(0, 2, 1))
        H[:, -1, -1] = np.sum(Jg**2, axis=(1, 2))
        hg = ((-Wu * Jg).transpose(0, 2, 1) @ X[:, u]).reshape(n, -1)
        H[:, : p * (r + 1), -1] = hg
        H[:, -1, : p * (r + 1)] = hg
        grad[:, -1] = np.sum(Jg * R[:, u], axis=(1, 2))
        B[:, :, -1] = (Jg[:, :, None, :] @ Jphi)[:, :, 0]
    return R, H, grad, D, gphi, B, T


def _reduce(H, D, B, lam):
    """:func:`~.problem._reduce` with a leading batch axis, ``lam`` one damping a log."""
    n, nu, nt, k = B.shape
    eye = np.eye(k)
    Dl = D + lam[:, None, None, None] * (np.diagonal(D, axis1=2, axis2=3)[..., None] * eye
                                         + 1e-300 * eye)
    Hl = H + lam[:, None, None] * (np.diagonal(H, axis1=1, axis2=2)[:, :, None] * np.eye(nt))
    if not nu:
        return Hl, Dl
    Dinv = np.linalg.inv(Dl)
    Lc = np.linalg.cholesky(Dinv)
    BL = (B @ Lc).transpose(0, 1, 3, 2).reshape(n, nu * k, nt)
    return Hl - BL.transpose(0, 2, 1) @ BL, Dinv


def _solve_each(S, rhs):
    """``solve(S, rhs)`` per log; None where a log's S is singular (the serial solver's
    LinAlgError)."""
    try:
        return np.linalg.solve(S, rhs[..., None])[..., 0], np.ones(len(S), bool)
    except np.linalg.LinAlgError:
        out, ok = np.zeros_like(rhs), np.ones(len(S), bool)
        for i in range(len(S)):
            try:
                out[i] = np.linalg.solve(S[i], rhs[i])
            except np.linalg.LinAlgError:
                ok[i] = False
        return out, ok


def solve_batch(bt: Batch, U, g, W, A, o, max_iter: int = 200, tol: float = 1e-12) -> dict:
    """:func:`~.problem.solve` of every log from its own start (U (b, nu, r), g (b,), A (b, p,
    r), o (b, p)) under its own weights W (b, P, p). Returns a dict of batched ``A``, ``o``,
    ``g``, ``U``, ``M``, ``cost``, ``converged``, ``iterations`` and ``W``."""
    pr = bt.pr
    r, p = pr.r, pr.p
    nu, k, b = len(pr.unknown), r - 1, bt.b
    U = np.array(U, float)
    U /= np.linalg.norm(U, axis=2, keepdims=True)
    g = (np.full(b, float(pr.magnitude)) if not pr.fit_g else np.array(g, float).reshape(b))
    A, o, W = np.array(A, float), np.array(o, float), np.asarray(W, float)
    lam = np.full(b, 1e-3)
    cur = _cost(bt.Y, A, o, bt.loads(U, g), W)
    converged = np.zeros(b, bool)
    done = np.zeros(b, bool)
    it = np.zeros(b, int)
    trial = np.zeros(b, int)
    need = np.ones(b, bool)  # a new iteration: the normal equations at the current point
    nt = p * (r + 1) + (1 if pr.fit_g else 0)
    H, grad = np.zeros((b, nt, nt)), np.zeros((b, nt))
    D, gphi = np.zeros((b, nu, k, k)), np.zeros((b, nu, k))
    B, T = np.zeros((b, nu, nt, k)), np.zeros((b, nu, k, r))
    while not done.all():
        new_it = np.flatnonzero(need & ~done)
        if len(new_it):
            it[new_it] += 1
            trial[new_it] = 0
            _, H[new_it], grad[new_it], D[new_it], gphi[new_it], B[new_it], T[new_it] = (
                _normal_equations(bt, new_it, W[new_it], A[new_it], o[new_it], U[new_it],
                                  g[new_it]))
            need[new_it] = False
        a = np.flatnonzero(~done)
        S, Dinv = _reduce(H[a], D[a], B[a], lam[a])
        Ba, ga = B[a], gphi[a]
        rhs = -(grad[a] - ((Ba @ (Dinv @ ga[..., None]))[..., 0].sum(axis=1) if nu else 0.0))
        dth, ok = _solve_each(S, rhs)
        trial[a] += 1
        bad = a[~ok]  # serial: lam *= 10, the next trial (no ceiling test)
        lam[bad] *= 10
        a, dth, Dinv, Ba, ga = a[ok], dth[ok], Dinv[ok], Ba[ok], ga[ok]
        if len(a):
            dphi = (-(Dinv @ (ga + (dth[:, None, None, :] @ Ba)[:, :, 0])[..., None])[..., 0]
                    if nu else np.zeros((len(a), 0, k)))
            th = (np.concatenate([A[a], o[a][:, :, None]], axis=2).reshape(len(a), -1)
                  + dth[:, : p * (r + 1)]).reshape(len(a), p, r + 1)
            A1, o1 = th[:, :, :r], th[:, :, r]
            g1 = g[a] + dth[:, -1] if pr.fit_g else g[a]
            U1 = U[a]
            if nu:
                U1 = U1 + (dphi[:, :, None, :] @ T[a])[:, :, 0]
                U1 = U1 / np.linalg.norm(U1, axis=2, keepdims=True)
            new = _cost(bt.Y[a], A1, o1, bt.loads(U1, g1), W[a])
            if pr.fit_g:
                new = np.where(g1 > 0, new, np.inf)
            acc = new < cur[a]
            ia = a[acc]
            rel = (cur[ia] - new[acc]) / np.maximum(cur[ia], 1e-300)
            A[ia], o[ia], U[ia], g[ia], cur[ia] = A1[acc], o1[acc], U1[acc], g1[acc], new[acc]
            lam[ia] = np.maximum(lam[ia] / 5, 1e-12)
            small = rel < tol
            converged[ia[small]] = True
            done[ia[small]] = True
            last = ia[~small][it[ia[~small]] >= max_iter]  # the iterations ran out
            done[last] = True
            need[ia] = True
            ir = a[~acc]
            lam[ir] *= 5
            gave_up = ir[lam[ir] > 1e12]  # serial: the trials stop, no descent left
            converged[gave_up] = True
            done[gave_up] = True
        out = np.flatnonzero(~done & ~need & (trial >= 40))  # 40 trials, none improved
        converged[out] = True
        done[out] = True
    return {"A": A, "o": o, "g": g, "U": U, "M": bt.loads(U, g), "cost": cur,
            "converged": converged, "iterations": it, "W": W}


def leverage_batch(bt: Batch, fit: dict):
    """:func:`~.problem.curvature`'s ``leverage`` of every log at its fit: (b, P, p)."""
    pr = bt.pr
    r, p = pr.r, pr.p
    u = pr.unknown
    b = bt.b
    idx = np.arange(b)
    W, A, U, g = fit["W"], fit["A"], fit["U"], fit["g"]
    _, H, _, D, _, B, T = _normal_equations(bt, idx, W, A, fit["o"], U, g)
    S, Dinv = _reduce(H, D, B, np.zeros(b))
    try:
        Sinv = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        Sinv = np.empty_like(S)
        for i in range(b):
            try:
                Sinv[i] = np.linalg.inv(S[i])
            except np.linalg.LinAlgError:
                Sinv[i] = np.linalg.pinv(S[i])
    nt = S.shape[1]
    M = fit["M"]
    X = np.concatenate([M, np.ones((b, pr.P, 1))], axis=2)
    h = np.zeros((b, pr.P, p))
    for c in range(p):
        sl = slice(c * (r + 1), (c + 1) * (r + 1))
        a = np.zeros((b, pr.P, nt))
        a[:, :, sl] = -W[:, :, c:c + 1] * X
        if pr.fit_g:
            a[:, u, -1] = -W[:, u, c] * (U @ A[:, c, :, None])[..., 0]
        if len(u):
            bb = -(W[:, u, c] * g[:, None])[..., None] * (T @ A[:, c, None, :, None])[..., 0]
            Db = (Dinv @ bb[..., None])[..., 0]
            a[:, u] -= (B @ Db[..., None])[..., 0]
            h[:, u, c] = np.sum(bb * Db, axis=2)
        h[:, :, c] += np.sum((a @ Sinv) * a, axis=2)
    return h


def _take(fit: dict, idx) -> dict:
    return {k: v[idx] for k, v in fit.items()}


def feasible_gls_batch(bt: Batch, fit: dict, v0=None) -> tuple[dict, np.ndarray, np.ndarray]:
    """:func:`~.variances._feasible_gls` of every log from its fit (:func:`solve_batch`'s
    dict): each log's rounds until its own variances settle. Returns ``(fit, v, rounds)``,
    batched."""
    pr = bt.pr
    b = bt.b
    identified = (pr.p - pr.r) ** 2 >= pr.p + pr.r
    cap = MAX_REWEIGHT_ROUNDS if identified else UNIDENTIFIED_ROUNDS
    v = None if v0 is None else np.broadcast_to(np.asarray(v0, float), (b, pr.p)).copy()
    rounds = np.zeros(b, int)
    fit = {k: np.array(val) for k, val in fit.items()}
    active = np.arange(b)
    while len(active):
        rounds[active] += 1
        sub = Batch(pr, bt.Y[active])
        sub.spread = bt.spread[active]
        f = _take(fit, active)
        lev = leverage_batch(sub, f)
        vn = np.empty((len(active), pr.p))
        for i in range(len(active)):
            q = sub.problem(i)
            vn[i] = estimate_variances(q, {"M": f["M"][i], "A": f["A"][i], "o": f["o"][i],
                                           "g": f["g"][i], "W": f["W"][i],
                                           "leverage": lev[i]})
        if v is None:  # the first round from no stated variances: never settled
            settled = np.zeros(len(active), bool)
            v = np.zeros((b, pr.p))
        else:
            dof = np.maximum(pr.P - lev.sum(axis=1), 1.0)
            step = np.abs(np.log(vn / v[active])) / np.sqrt(2.0 / dof)
            settled = np.max(step, axis=1) <= REWEIGHT_TOL
        v[active] = vn
        new = solve_batch(sub, f["U"], f["g"], sub.weights(vn), f["A"], f["o"])
        for key, val in new.items():
            fit[key][active] = val
        stop = (settled & identified) | (rounds[active] >= cap)
        active = active[~stop]
    return fit, v, rounds


def alternate_batch(pr: Problem, U, g, W, iters: int = 15, tol: float = 1e-6) -> np.ndarray:
    """:func:`~.problem.alternate` of many starts of one rig at once (U (s, nu, r), the same
    readings and weights W (P, p)): each start's linear fit and global step per pose
    (:func:`~.problem.sphere_minimum` on every start's poses in one call), each start stopping
    by the serial rule. Returns the directions (s, nu, r)."""
    U = np.array(U, float)
    s, r = len(U), pr.r
    u = pr.unknown
    W2 = W**2
    WY = (W2 * pr.Y).T  # (p, P)
    WX0 = W2.T[None, :, :, None]
    last = np.full(s, np.inf)
    act = np.arange(s)
    gv = np.full(s, float(g))
    for _ in range(iters):
        M = _loads(pr, U[act], gv[act])
        X = np.concatenate([M, np.ones((len(act), pr.P, 1))], axis=2)
        H = (WX0 * X[:, None]).transpose(0, 1, 3, 2) @ X[:, None]  # (s, p, r+1, r+1)
        H += 1e-13 * np.trace(H, axis1=2, axis2=3)[..., None, None] * np.eye(r + 1)
        th = np.linalg.solve(H, (WY[None] @ X)[..., None])[..., 0]
        A, o = th[..., :r], th[..., r]
        c = np.sum((W * (pr.Y - M @ A.transpose(0, 2, 1) - o[:, None, :])) ** 2, axis=(1, 2))
        go = ~(c > last[act] * (1 - tol))
        act, A, o = act[go], A[go], o[go]
        last[act] = c[go]
        if not len(act):
            break
        n = len(act)
        b = g * ((W2[u][None] * (pr.Y[u][None] - o[:, None, :])) @ A)  # (n, nu, r)
        AA = (A[:, :, :, None] * A[:, :, None, :]).reshape(n, pr.p, r * r)
        Q = (g**2 * (W2[u][None] @ AA)).reshape(n, len(u), r, r)
        new = sphere_minimum(b.reshape(-1, r), Q.reshape(-1, r, r)).reshape(n, len(u), r)

        def per(V, b=b, Q=Q):
            return (-2 * np.sum(b * V, axis=2)
                    + (V[..., None, :] @ Q @ V[..., :, None])[..., 0, 0])

        old = U[act]
        keep = per(old) <= per(new)
        new[keep] = old[keep]
        moved = np.max(np.abs(new - old), axis=(1, 2)) >= 1e-12
        act = act[moved]
        U[act] = new[moved]
        if not len(act):
            break
    return U
