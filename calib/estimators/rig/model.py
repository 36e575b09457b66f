"""The pose data of a static-pose rig (:class:`PoseData`) and its two models: the affine forward
model with an optional bending term (:class:`ForwardModel`) and the index model, each channel a
polynomial of its own linear signal (:class:`IndexModel`).
"""

from __future__ import annotations

import functools

import numpy as np
from scipy.optimize import least_squares

from calib.estimators.forward.problem import grid
from calib.estimators.forward.problem import tangents as _tangents
from calib.estimators.numdiff import batched_jacobian

# ------------------------------------------------------------------------------- the fit


class PoseData:
    """Pose means, counts and within-pose noise of a labelled log, with the known loads matched."""

    def __init__(self, Z, labels, known_Z, known_M, r, known_samples=None):
        Z = np.asarray(Z, float)
        labels = np.asarray(labels)
        good = labels >= 0
        ids = np.unique(labels[good])
        self.rows = Z[good]
        lab = np.searchsorted(ids, labels[good])
        self.row_pose = lab
        P, p = len(ids), Z.shape[1]
        self.counts = np.bincount(lab, minlength=P).astype(float)
        self.means = np.zeros((P, p))
        np.add.at(self.means, lab, self.rows)
        self.means /= self.counts[:, None]
        resid = self.rows - self.means[lab]
        dof = max(len(self.rows) - P, 1)
        self.sigma = np.maximum(np.sqrt((resid**2).sum(axis=0) / dof),
                                1e-9 * np.maximum(np.ptp(Z, axis=0), 1e-300))
        self.p, self.r = p, r
        # known readings -> poses: the nearest pose mean in noise units when it is clearly the
        # nearest (under a quarter of the distance to the next); else a known-only pose
        Zk = np.atleast_2d(np.asarray(known_Z, float))
        Mk = np.atleast_2d(np.asarray(known_M, float))[:, :r]
        self.known_pose = np.full(len(Zk), -1)
        extra_means, extra_counts = [], []
        n_extra = float(known_samples) if known_samples else float(np.median(self.counts))
        taken = set()
        for k, zk in enumerate(Zk):
            d = np.sqrt(np.mean(((self.means - zk) / self.sigma) ** 2, axis=1))
            order = np.argsort(d)
            j = int(order[0])
            second = d[order[1]] if P > 1 else np.inf
            if j not in taken and d[j] <= 0.25 * second:
                self.known_pose[k] = j
                taken.add(j)
            else:
                self.known_pose[k] = P + len(extra_means)
                extra_means.append(zk)
                extra_counts.append(n_extra)
        if extra_means:
            self.means = np.vstack([self.means, extra_means])
            self.counts = np.r_[self.counts, extra_counts]
        self.P = len(self.means)
        self.known_M = Mk
        self.unknown = np.setdiff1d(np.arange(self.P), self.known_pose)
        self.n_extra = len(extra_means)


@functools.lru_cache(maxsize=4)
def sphere_grid(n: int, r: int) -> np.ndarray:
    """``n`` unit vectors spread evenly over the sphere (r = 3: a Fibonacci lattice) or the
    circle (r = 2) (:func:`calib.estimators.forward.problem.grid`); cached, read-only."""
    out = grid(r, n)
    out.flags.writeable = False
    return out


#: Directions tried per unknown pose by the rig fit's global re-inference (:meth:`ForwardModel.
#: alternate`): about 5 degrees apart on the sphere.
#: Decision: docs/calib_design.md D31.
SPHERE_GRID = 2000


#: Two alternated starts are distinct when some pose's directions differ by more than this.
#: Decision: docs/calib_design.md D31.
DISTINCT_DEG = 10.0


def _wls(X, Y, W):
    """Weighted least squares of every column of Y (P, p) on its own design X (P, k) or (p, P,
    k), weights W (P, p); returns the coefficients (p, k) and the weighted residuals (P, p)."""
    Xc = np.broadcast_to(X, (Y.shape[1],) + X.shape[-2:]) if X.ndim == 2 else X
    coef, resid = _wls_batch(Xc[None], Y, W)
    return coef[0], resid[0]


def _wls_batch(X, Y, W):
    """:func:`_wls` for a batch of designs X (b, p, P, k) (one per channel and batch member):
    coefficients (b, p, k) and weighted residuals (b, P, p)."""
    Xw = X * W.T[None, :, :, None]
    yw = (Y * W).T
    scale = np.maximum(np.sqrt((Xw**2).sum(axis=2)), 1e-300)  # column scaling
    Xs = Xw / scale[:, :, None, :]
    G = np.einsum("bcpk,bcpl->bckl", Xs, Xs)
    h = np.einsum("bcpk,cp->bck", Xs, yw)
    try:
        b = np.linalg.solve(G, h[..., None])[..., 0]
    except np.linalg.LinAlgError:
        b = np.stack([np.stack([np.linalg.lstsq(Xs[i, c], yw[c], rcond=None)[0]
                                for c in range(Xs.shape[1])]) for i in range(len(Xs))])
    coef = b / scale
    resid = yw[None] - np.einsum("bcpk,bck->bcp", Xw, coef)
    return coef, resid.transpose(0, 2, 1)


class ForwardModel:
    """zbar_j = A m_j + o by variable projection over the unknown directions and g; with
    ``bend`` each channel also gets ``b_c (a_c . m)^2``."""

    def __init__(self, pd: PoseData, magnitude=None):
        self.pd = pd
        self.magnitude = magnitude
        self.fit_g = magnitude is None
        # the pose means centred per channel for the solves (the offsets add the centre back):
        # a channel whose offset is a thousand times its spread would otherwise lose three
        # digits to cancellation in every residual, enough to make LM's finite-difference
        # Jacobian noise and stop it short (the rig route's equivariance test found one)
        self.center = pd.means.mean(axis=0)
        self.centered = pd.means - self.center

    def loads(self, x, U0, T):
        """Every pose's load (P, r) at the parameters x: direction steps in the tangent planes T
        of U0, then (when fitted) g."""
        return self.loads_batch(np.asarray(x, float)[None], U0, T)[0]

    def loads_batch(self, xs, U0, T):
        """:meth:`loads` for every row of xs: (b, P, r)."""
        pd = self.pd
        nt = T.shape[1]
        nu = len(pd.unknown)
        Ms = np.zeros((len(xs), pd.P, pd.r))
        Ms[:, pd.known_pose] = pd.known_M
        V = U0 + np.einsum("bma,mad->bmd", xs[:, : nt * nu].reshape(len(xs), nu, nt), T)
        g = xs[:, -1:, None] if self.fit_g else self.magnitude
        Ms[:, pd.unknown] = g * V / np.linalg.norm(V, axis=2, keepdims=True)
        return Ms

    bend = False  # per-channel bending term (a_c . m)^2 in the forward model

    def coefficients(self, M, W):
        """The per-channel model fitted to the pose means at loads M, weights W: a dict with
        ``B`` ((r+1, p): the affine pass), ``resid`` (weighted residuals of the model, (P, p))
        and for ``bend`` ``a`` (p, r), ``S`` and ``bent`` ((p, r+2): affine part and bend
        gain of each channel)."""
        return {k: v[0] for k, v in self.coefficients_batch(np.asarray(M)[None], W).items()}

    def coefficients_batch(self, Ms, W):
        """:meth:`coefficients` for a batch of loads Ms (b, P, r), every entry with a leading
        batch axis (LM's finite-difference Jacobian: one call for all its columns)."""
        pd = self.pd
        X = np.concatenate([Ms, np.ones(Ms.shape[:2] + (1,))], axis=2)
        Xc = np.broadcast_to(X[:, None], (len(Ms), pd.p) + X.shape[1:])
        coef, resid = _wls_batch(Xc, self.centered, W)
        coef[:, :, pd.r] += self.center
        out = {"B": coef.transpose(0, 2, 1), "resid": resid}
        if self.bend:
            a = coef[:, :, : pd.r]
            s2 = np.einsum("bPr,bcr->bPc", Ms, a) ** 2  # (b, P, p)
            S = np.maximum(s2.max(axis=1), 1e-300)
            bendcol = (s2 / S[:, None, :]).transpose(0, 2, 1)[..., None]
            bent, out["resid"] = _wls_batch(np.concatenate([Xc, bendcol], axis=3),
                                            self.centered, W)
            bent[:, :, pd.r] += self.center
            out.update(a=a, S=S, bent=bent)
        return out

    def linear(self, M, W):
        """Weighted least squares per channel of the pose means on [M 1]; (B (r+1, p), resid).
        With ``bend`` the residuals are those of the bent model; B stays the affine part."""
        c = self.coefficients(M, W)
        return c["B"], c["resid"]

    def predict(self, coef, M):
        """The model's pose means (n, p) at loads M (n, r)."""
        if not self.bend:
            return M @ coef["B"][:-1] + coef["B"][-1]
        b = coef["bent"]
        r = self.pd.r
        return M @ b[:, :r].T + b[:, r] + b[:, r + 1] * (M @ coef["a"].T) ** 2 / coef["S"]

    def reinfer(self, M, W, g):
        """Every unknown pose's load moved to the direction on the sphere of radius g (a grid of
        :data:`SPHERE_GRID`) that the model fitted at M explains best: a global step per pose."""
        coef = self.coefficients(M, W)
        grid = g * sphere_grid(SPHERE_GRID, self.pd.r)
        pred = self.predict(coef, grid) - self.center
        out = M.copy()
        u = self.pd.unknown
        # |W_j (zbar_j - pred)|^2 for every pose and grid point, expanded (centred): (nu, grid)
        W2 = W[u] ** 2
        Y = self.centered[u]
        cost = (np.sum(W2 * Y**2, axis=1)[:, None] - 2 * (W2 * Y) @ pred.T + W2 @ (pred**2).T)
        out[u] = grid[np.argmin(cost, axis=1)]
        return out

    def _at(self, U, g):
        """Every pose's load: the known ones, and g U at the unknown poses."""
        M = np.zeros((self.pd.P, self.pd.r))
        M[self.pd.known_pose] = self.pd.known_M
        M[self.pd.unknown] = g * U
        return M

    def cost(self, U, g, W) -> float:
        """The weighted cost with the unknown poses at unit directions U and magnitude g."""
        return float((self.coefficients(self._at(U, g), W)["resid"] ** 2).sum())

    def alternate(self, U, g, W, iters=25):
        """Unit directions of the unknown poses after alternating the model fit and
        :meth:`reinfer` from U (stops when no pose moves)."""
        M = self._at(U, g)
        for _ in range(iters):
            new = self.reinfer(M, W, g)
            if np.array_equal(new, M):
                break
            M = new
        V = M[self.pd.unknown]
        return V / np.linalg.norm(V, axis=1, keepdims=True)

    def solve(self, U0, g0, W, max_nfev=400):
        """LM from unit directions U0 (of the unknown poses) and magnitude g0."""
        T = _tangents(U0)
        x0 = np.zeros(T.shape[1] * len(U0) + (1 if self.fit_g else 0))
        if self.fit_g:
            x0[-1] = g0

        def batch(xs):  # residuals of every row of xs: (b, P * p)
            return self.coefficients_batch(self.loads_batch(xs, U0, T), W)["resid"].reshape(
                len(xs), -1)

        def fun(x):
            return batch(x[None])[0]

        sol = least_squares(fun, x0, jac=batched_jacobian(batch), method="lm", xtol=1e-12,
                            ftol=1e-12, gtol=1e-12, max_nfev=max_nfev * (len(x0) + 1))
        M = self.loads(sol.x, U0, T)
        U = M[self.pd.unknown]
        g = float(sol.x[-1]) if self.fit_g else float(self.magnitude)
        return {"U": U / np.linalg.norm(U, axis=1, keepdims=True), "g": g,
                "cost": float(2 * sol.cost), "converged": bool(sol.status > 0),
                "nfev": int(sol.nfev), "M": M}


class IndexModel:
    """A forward model in which every channel is a polynomial of its own linear signal,

        zbar_jc = o_c + u_jc + sum_{k=2..d+1} b_ck s_c (u_jc / s_c)^k,    u_jc = a_c . m_j / g,

    (a Wiener model: a printed flexure, a gap or a gauge that stiffens or softens along the one
    load direction it senses; ``s_c`` the channel's spread over the poses, for scaling). Unlike
    the bending term of :class:`ForwardModel`, whose direction is frozen at the affine fit's,
    ``a_c`` is fitted with the curvature and the loads. Fitted by LM over the unknown poses'
    directions and every channel's (a_c, o_c, b_c) together, at a held magnitude ``g``. With
    ``free`` every pose's direction is unknown (the known loads ignored): the consistency check.
    On a real printed 8-channel sensor (docs/calib.md) it took the pose loads of the worst load
    set from 5.9x to 1.8x least squares with every load known."""

    def __init__(self, pd: PoseData, g: float, M0: np.ndarray, free: bool = False):
        self.pd, self.g = pd, float(g)
        self.free = free
        self.unknown = np.arange(pd.P) if free else pd.unknown
        U0 = M0[self.unknown]
        self.U0 = U0 / np.linalg.norm(U0, axis=1, keepdims=True)
        self.T = _tangents(self.U0)
        self.ng = self.T.shape[1] * len(self.unknown)
        self.scale = np.maximum(pd.means.std(axis=0), 1e-300)
        # fitted to the pose means centred per channel (the offsets in theta are from the
        # centre), for the reason :class:`ForwardModel` gives
        self.Y = pd.means - pd.means.mean(axis=0)

    def loads_batch(self, xs):
        """The loads (b, P, r) of direction steps xs[:, :ng]."""
        pd = self.pd
        nt = self.T.shape[1]
        Ms = np.zeros((len(xs), pd.P, pd.r))
        if not self.free:
            Ms[:, pd.known_pose] = pd.known_M
        V = self.U0 + np.einsum("bma,mad->bmd",
                                xs[:, : self.ng].reshape(len(xs), len(self.unknown), nt), self.T)
        Ms[:, self.unknown] = self.g * V / np.linalg.norm(V, axis=2, keepdims=True)
        return Ms

    def predict(self, Ms, theta, deg):
        """Pose means (b, P, p) at loads Ms (b, P, r), channel parameters theta (b, p, r+1+deg)."""
        r = self.pd.r
        u = np.einsum("bPr,bcr->bPc", Ms / self.g, theta[:, :, :r])
        pred = u + theta[:, None, :, r]
        for k in range(deg):
            pred = pred + theta[:, None, :, r + 1 + k] * self.scale * (u / self.scale) ** (k + 2)
        return pred

    def start(self, deg):
        """Parameters at the start directions: the affine fit per channel, no curvature."""
        pd = self.pd
        X = np.column_stack([self.loads_batch(np.zeros((1, self.ng)))[0] / self.g,
                             np.ones(pd.P)])
        B = np.linalg.lstsq(X, self.Y, rcond=None)[0]
        return np.r_[np.zeros(self.ng), np.column_stack([B.T, np.zeros((pd.p, deg))]).ravel()]

    def grow(self, x, deg):
        """Parameters of degree ``deg`` as a start of degree ``deg + 1`` (zero new term)."""
        th = x[self.ng:].reshape(self.pd.p, -1)
        return np.r_[x[: self.ng], np.column_stack([th, np.zeros(self.pd.p)]).ravel()]

    def solve(self, deg, W, x0=None, max_nfev=20):
        """LM from x0 (default :meth:`start`), at most ``max_nfev`` evaluations per parameter
        (converged fits take under 2; known loads that contradict the readings can crawl for
        200); a dict as :meth:`ForwardModel.solve`'s plus ``x``, ``deg`` and the weighted
        residuals ``resid`` (P, p)."""
        pd = self.pd
        x0 = self.start(deg) if x0 is None else x0
        k = pd.r + 1 + deg

        def batch(xs):
            Ms = self.loads_batch(xs)
            th = xs[:, self.ng:].reshape(len(xs), pd.p, k)
            return ((self.Y - self.predict(Ms, th, deg)) * W).reshape(len(xs), -1)

        sol = least_squares(lambda x: batch(x[None])[0], x0, jac=batched_jacobian(batch),
                            method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-12,
                            max_nfev=max_nfev * (len(x0) + 1))
        M = self.loads_batch(sol.x[None])[0]
        U = M[pd.unknown]
        return {"U": U / np.linalg.norm(U, axis=1, keepdims=True), "g": self.g,
                "cost": float(2 * sol.cost), "converged": bool(sol.status > 0),
                "nfev": int(sol.nfev), "M": M, "x": sol.x, "deg": deg,
                "resid": sol.fun.reshape(pd.P, pd.p)}

    def holdout(self, fit, W) -> float:
        """Leave-one-pose-out error of a fit: for every pose, the model refitted without it (from
        ``fit``), then its readings predicted (an unknown pose at the direction on its sphere,
        of :data:`SPHERE_GRID` then LM, that explains them best); the sum over poses of the
        weighted squared reading residuals. The held-out side of the degree choice: a degree
        that fits the poses it was given but not the next one is overfitted."""
        pd, deg = self.pd, fit["deg"]
        k = pd.r + 1 + deg
        grid = sphere_grid(SPHERE_GRID, pd.r)
        unknown = set(self.unknown.tolist())
        total = 0.0
        for j in range(pd.P):
            Wj = np.array(W, float)
            Wj[j] = 0.0
            f = self.solve(deg, Wj, fit["x"])
            th = f["x"][self.ng:].reshape(1, pd.p, k)

            def misfit(V, th=th, j=j):  # weighted residuals of pose j at directions V (n, r)
                U = V / np.linalg.norm(V, axis=1, keepdims=True)
                return (self.Y[j] - self.predict(U[None] * self.g, th, deg)[0]) * W[j]

            if j not in unknown:
                total += float(np.sum(misfit(f["M"][j][None]) ** 2))
                continue
            u_fit = f["M"][j] / self.g
            u_grid = grid[np.argmin(np.sum(misfit(grid) ** 2, axis=1))]
            # the grid's best is a second start only when it is not the fitted direction's basin
            starts = [u_fit] if u_fit @ u_grid > np.cos(np.radians(DISTINCT_DEG)) else [
                u_fit, u_grid]
            best = np.inf
            for u in starts:
                T = _tangents(u[None])[0]
                sol = least_squares(lambda a, u=u, T=T: misfit((u + a @ T)[None])[0],
                                    np.zeros(len(T)), method="lm")
                best = min(best, float(2 * sol.cost))
            total += best
        return total

    def reweighted(self, fit):
        """Feasible GLS weights (P, p) from a fit's own residuals: each channel's pose-level
        residual variance (over the residual degrees of freedom) plus each pose mean's sampling
        variance."""
        pd = self.pd
        raw = fit["resid"] / fit["W"]
        n_par = pd.r + 1 + fit["deg"] + self.ng / pd.p
        v = (raw**2).sum(axis=0) / max(pd.P - n_par, 1.0)
        return 1.0 / np.sqrt(v[None, :] + (pd.sigma**2)[None, :] / pd.counts[:, None])
