"""Ellipse / ellipsoid fitting in r dimensions: ``(y - c)^T W^T W (y - c) = 1``, W symmetric PD.

1. Algebraic start: the general quadric ``y^T A y + b^T y + d = 0`` with unit-norm coefficients
   (smallest eigenvector of the design's Gram matrix, on normalised data). If A is not definite
   (a hyperboloid, typical for partial coverage) a CalibrationWarning is raised and the start
   becomes the constrained fit: a sphere (A = I, linear), which the refinement can only deform
   into ellipsoids.
2. Refinement (approximate maximum likelihood): Levenberg-Marquardt on the first-order geometric
   (Sampson) distance ``d_i = (rho_i - 1) rho_i / |W^T v_i|`` with ``v_i = W (y_i - c)``,
   ``rho_i = |v_i|``; the weights are refreshed every iteration (IRLS). Parametrising W as a
   symmetric matrix removes the rotation gauge, and steps that leave the PD cone are rejected, so
   the result is always an ellipsoid. Normal equations are accumulated in row chunks, so memory
   stays O(chunk).

Why a Levenberg-Marquardt loop of its own and not ``scipy.optimize.least_squares``: that needs the
whole residual vector (and its Jacobian, n x parameters) in memory at every evaluation, while this
fit streams logs larger than memory (``--chunk-rows``, dask arrays): each iteration is one pass
that accumulates the normal equations and costs the batched trial steps, block by block. It also
keeps the prior weight frozen within an iteration and rejects steps that leave the PD cone, which
``least_squares`` has no hook for.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from calib.data.result import warn
from calib.data.stream import CHUNK_ROWS as CHUNK_ROWS  # re-exported: rows per block of a pass
from calib.data.stream import QR, ChunkSource, blocks_of, rows_of, strided_of

#: Above this many points the refinement converges on a strided subsample of this size first.
#: Decision: docs/calib_design.md D14.
SUBSAMPLE_ROWS = 50_000
#: Full-data Gauss-Newton (LM) steps after the subsample has converged.
#: Decision: docs/calib_design.md D14.
FULL_DATA_STEPS = 1


@dataclass
class EllipsoidFit:
    """Result of :func:`fit_ellipsoid`.

    centre : (r,)  c
    W : (r, r)     symmetric PD map from the ellipsoid to the unit sphere: u = W (y - c)
    centre_stderr : (r,) standard errors of c from the final Jacobian (noise estimated from
        residuals)
    cov : (r + r(r+1)/2, r + r(r+1)/2) covariance of (c, upper triangle of W row by row), the
        Gauss-Newton ``sigma^2 (J^T J)^-1`` (prior included when it is used)
    info : dict    start kind, iterations, convergence, residual rms, condition number
    """

    centre: np.ndarray
    W: np.ndarray
    centre_stderr: np.ndarray
    cov: np.ndarray | None = None
    info: dict = field(default_factory=dict)


def _sym_index(r):
    return [(j, k) for j in range(r) for k in range(j, r)]


def _ncols(Y) -> int:
    return Y.p if isinstance(Y, ChunkSource) else Y.shape[1]


def _algebraic(Y):
    """General quadric fit on (already normalised) Y; returns (centre, E) or None if not an
    ellipsoid."""
    r = _ncols(Y)
    idx = _sym_index(r)
    nq = len(idx)
    npar = nq + r + 1
    G = np.zeros((npar, npar))
    for y in blocks_of(Y):
        D = np.empty((len(y), npar))
        for c, (j, k) in enumerate(idx):
            D[:, c] = y[:, j] * y[:, k] * (1.0 if j == k else 2.0)
        D[:, nq : nq + r] = y
        D[:, -1] = 1.0
        G += D.T @ D
    w, V = np.linalg.eigh(G)
    theta = V[:, 0]
    A = np.zeros((r, r))
    for c, (j, k) in enumerate(idx):
        A[j, k] = A[k, j] = theta[c]
    b = theta[nq : nq + r]
    d = theta[-1]
    ev = np.linalg.eigvalsh(A)
    if ev[0] < 0 < ev[-1] or np.all(ev == 0):
        return None, float(w[1] / max(w[0], 1e-300))
    if ev[0] < 0:
        A, b, d = -A, -b, -d
    c = -0.5 * np.linalg.solve(A, b)
    k = c @ A @ c - d
    if k <= 0:
        return None, float(w[1] / max(w[0], 1e-300))
    return (c, A / k), float(w[1] / max(w[0], 1e-300))


def _sphere(Y):
    """Linear sphere fit |y|^2 + b^T y + d = 0; returns (centre, E = I / R^2)."""
    r = _ncols(Y)
    if isinstance(Y, ChunkSource):  # one pass, streaming QR
        qr = QR()
        for y in blocks_of(Y):
            qr.add(np.column_stack([y, np.ones(len(y)), -np.sum(y**2, axis=1)]))
        t = qr.lstsq(r + 1)[:, 0]
    else:
        X = np.column_stack([Y, np.ones(len(Y))])
        t, *_ = np.linalg.lstsq(X, -np.sum(Y**2, axis=1), rcond=None)
    c = -0.5 * t[:r]
    R2 = max(c @ c - t[r], 1e-12)
    return c, np.eye(r) / R2


def _sqrt_sym(E):
    w, V = np.linalg.eigh((E + E.T) / 2)
    return (V * np.sqrt(np.clip(w, 1e-300, None))) @ V.T


def _prior(W, idx, weight):
    """Isotropy prior residuals ``weight * (W - mean(diag W) I)`` (upper triangle) and Jacobian."""
    r = W.shape[0]
    wbar = np.trace(W) / r
    res = np.array([W[j, k] - (wbar if j == k else 0.0) for j, k in idx]) * weight
    J = np.zeros((len(idx), r + len(idx)))
    for a, (j, k) in enumerate(idx):
        J[a, r + a] = weight
        if j == k:
            for b, (jj, kk) in enumerate(idx):
                if jj == kk:
                    J[a, r + b] -= weight / r
    return res, J


def _normal_equations(Y, c, W, idx, prior_weight=0.0):
    """J^T J and J^T e of the Sampson residuals plus the prior, and the data cost e^T e, at
    (c, W)."""
    r = _ncols(Y)
    npar = r + len(idx)
    JTJ = np.zeros((npar, npar))
    JTe = np.zeros(npar)
    ee = 0.0
    if prior_weight > 0:
        pr, PJ = _prior(W, idx, prior_weight)
        JTJ += PJ.T @ PJ
        JTe += PJ.T @ pr
    for y in blocks_of(Y):
        dlt = y - c
        v = dlt @ W  # W symmetric
        rho = np.sqrt(np.einsum("ij,ij->i", v, v))
        g = v @ W
        gn = np.sqrt(np.einsum("ij,ij->i", g, g))
        wgt = rho / np.maximum(gn, 1e-300)  # 1 / |grad rho|
        e = wgt * (rho - 1.0)
        J = np.empty((len(dlt), npar))
        inv_rho = 1.0 / np.maximum(rho, 1e-300)
        J[:, :r] = -(g * inv_rho[:, None])
        for col, (j, k) in enumerate(idx):
            if j == k:
                J[:, r + col] = v[:, j] * dlt[:, j] * inv_rho
            else:
                J[:, r + col] = (v[:, j] * dlt[:, k] + v[:, k] * dlt[:, j]) * inv_rho
        J *= wgt[:, None]
        JTJ += J.T @ J
        JTe += J.T @ e
        ee += float(e @ e)
    return JTJ, JTe, ee


def _cost(Y, c, W, idx=None, prior_weight=0.0):
    ee = 0.0
    if prior_weight > 0:
        pr, _ = _prior(W, idx, prior_weight)
        ee += float(pr @ pr)
    for y in blocks_of(Y):
        v = (y - c) @ W
        rho = np.sqrt(np.einsum("ij,ij->i", v, v))
        g = v @ W
        gn = np.sqrt(np.einsum("ij,ij->i", g, g))
        e = rho / np.maximum(gn, 1e-300) * (rho - 1.0)
        ee += float(e @ e)
    return ee


def _trial_steps(JTJ, JTe, lam, c, W, idx, r, tries: int = 20):
    """The LM trial steps for damping lam, 10 lam, 100 lam, ... (``tries`` of them), lazily:
    (lambda, delta, c_new, W_new) for each that is solvable and keeps W positive definite."""
    for _ in range(tries):
        try:
            delta = -np.linalg.solve(JTJ + lam * np.diag(np.diag(JTJ) + 1e-12), JTe)
        except np.linalg.LinAlgError:
            lam *= 10
            continue
        c_new = c + delta[:r]
        W_new = W.copy()
        for col, (j, k) in enumerate(idx):
            W_new[j, k] += delta[r + col]
            if j != k:
                W_new[k, j] += delta[r + col]
        if np.linalg.eigvalsh(W_new)[0] > 0:
            yield lam, delta, c_new, W_new
        lam *= 10


def _costs(Y, params) -> list[float]:
    """:func:`_cost` (data part) of several (c, W) in one pass over Y; each sum is taken as
    :func:`_cost` takes it, so the values are the same."""
    ee = [0.0] * len(params)
    for y in blocks_of(Y):
        for a, (c, W) in enumerate(params):
            v = (y - c) @ W
            rho = np.sqrt(np.einsum("ij,ij->i", v, v))
            g = v @ W
            gn = np.sqrt(np.einsum("ij,ij->i", g, g))
            e = rho / np.maximum(gn, 1e-300) * (rho - 1.0)
            ee[a] += float(e @ e)
    return ee


def _doubling_batches(items):
    """Lists of 1, 2, 4, ... consecutive items of the iterator ``items`` (lazily; the last
    may be shorter, none is empty)."""
    size = 1
    while batch := list(itertools.islice(items, size)):
        yield batch
        size *= 2


def _lm(Yn, c, W, idx, npar, tau, max_iter, tol, sigma2=None):
    """Levenberg-Marquardt iterations.

    Returns (c, W, prior_weight, iterations, converged, JTJ, data_cost); JTJ is the last normal
    matrix evaluated (at the final or the previous iterate) and data_cost the final data cost.
    """
    n, r = rows_of(Yn), _ncols(Yn)
    lam = 1e-3
    pw = 0.0
    converged = False
    it = 0
    data_cost = None
    for it in range(1, max_iter + 1):  # noqa: B007 (the count is returned after the loop)
        if data_cost is not None:
            sigma2 = data_cost / max(n - npar, 1)
        elif sigma2 is None:  # first pass: the prior weight needs sigma before the normal eqs.
            sigma2 = _cost(Yn, c, W) / max(n - npar, 1)
        # prior weight sigma / (tau * wbar), frozen within an iteration
        pw = float(np.sqrt(sigma2) / (tau * np.trace(W) / r)) if tau else 0.0
        pr, _ = _prior(W, idx, pw) if pw > 0 else (np.zeros(0), None)
        JTJ, JTe, data_cost = _normal_equations(Yn, c, W, idx, pw)
        cost = data_cost + float(pr @ pr)
        step_ok = False
        rel = 0.0
        delta = None
        # the trial steps (lambda x 10 after every failure) in order; on streamed data they
        # are scored in batches of 1, 2, 4, ... trials, one pass each (a failed first trial
        # then costs one pass over 2 trials, not one over all the others): the same step is
        # taken as when they are scored one by one
        trials = _trial_steps(JTJ, JTe, lam, c, W, idx, r)
        if isinstance(Yn, ChunkSource):
            scored = itertools.chain.from_iterable(
                zip(b, _costs(Yn, [(t[2], t[3]) for t in b]), strict=True)
                for b in _doubling_batches(trials))
        else:
            scored = ((t, _cost(Yn, t[2], t[3])) for t in trials)
        for (lam_t, delta_t, c_new, W_new), new_data in scored:
            prn, _ = _prior(W_new, idx, pw) if pw > 0 else (np.zeros(0), None)
            new_cost = new_data + float(prn @ prn)
            if new_cost <= cost:
                step_ok = True
                rel = (cost - new_cost) / max(cost, 1e-300)
                c, W, data_cost, delta = c_new, W_new, new_data, delta_t
                lam = max(lam_t / 10, 1e-12)
                break
        if not step_ok or rel < tol or np.max(np.abs(delta)) < 1e-13:
            converged = True
            break
    return c, W, pw, it, converged, JTJ, data_cost


#: Folds of the cross-validation that decides whether the isotropy prior is used.
#: Decision: docs/calib_design.md D15.
CV_FOLDS = 5
#: The cross-validation runs on an evenly strided subsample of at most this many points.
#: Decision: docs/calib_design.md D15.
CV_MAX_ROWS = 20_000
#: The prior is kept only if its held-out cost is below this fraction of the cost without it.
#: Decision: docs/calib_design.md D15.
CV_MARGIN = 1.0
#: The prior spread tried by ``isotropy_prior="auto"``.
#: Decision: docs/calib_design.md D15.
AUTO_TAU = 0.1


def _refine(Yn, c, W, idx, npar, tau, max_iter, tol):
    """LM on Yn (subsample first for large n, then full-data steps); see :func:`fit_ellipsoid`."""
    n = rows_of(Yn)
    if n > SUBSAMPLE_ROWS:
        # converge on an evenly strided subsample, then polish with full-data Gauss-Newton
        # steps: one Newton step from a root-n consistent start is already efficient
        sub = strided_of(Yn, int(np.ceil(n / SUBSAMPLE_ROWS)))
        c, W, pw, it, converged, _, sub_cost = _lm(sub, c, W, idx, npar, tau, max_iter, tol)
        c, W, pw, it2, _, JTJ, data_cost = _lm(
            Yn, c, W, idx, npar, tau, FULL_DATA_STEPS, 0.0,
            sigma2=sub_cost / max(len(sub) - npar, 1),
        )
        return c, W, pw, it + it2, converged, JTJ, data_cost
    return _lm(Yn, c, W, idx, npar, tau, max_iter, tol)


def cross_validate_prior(Yn, c, W, tau, folds=CV_FOLDS, max_iter=200, tol=1e-12):
    """Held-out Sampson cost with and without the isotropy prior (spread ``tau``).

    ``folds`` strided folds (point i in fold ``i % folds``) of at most :data:`CV_MAX_ROWS`
    evenly strided points; each fold is fitted from the start (c, W) on the other folds and
    scored by the plain data cost (no prior) of its held-out points.

    Returns {"prior": cost, "none": cost, "folds": folds, "rows": m}.
    """
    n, r = rows_of(Yn), _ncols(Yn)
    idx = _sym_index(r)
    npar = r + len(idx)
    X = strided_of(Yn, int(np.ceil(n / CV_MAX_ROWS)) if n > CV_MAX_ROWS else 1)
    m = len(X)
    fold = np.arange(m) % folds
    out = {"folds": folds, "rows": m}
    for key, t in (("prior", tau), ("none", None)):
        total = 0.0
        for k in range(folds):
            train, test = X[fold != k], X[fold == k]
            if len(train) <= npar or len(test) == 0:
                total = float("nan")
                break
            ck, Wk, *_ = _lm(train, c, W, idx, npar, t, max_iter, tol)
            total += _cost(test, ck, Wk)
        out[key] = total
    return out


#: Prior-data conflict: the prior-free shape is this many prior spreads from isotropy ...
#: Decision: docs/calib_design.md D16.
CONFLICT_SPREADS = 3.0
#: ... and known to better than this fraction of that distance.
#: Decision: docs/calib_design.md D16.
CONFLICT_PRECISION = 1.0 / 3.0
#: The prior-free shape's anisotropy is known to better than this fraction of the prior spread:
#: the prior cannot add information, no cross-validation needed.
#: Decision: docs/calib_design.md D16.
DATA_DOMINATED = 0.1


def prior_conflict(W, JTJ, sigma2, tau) -> dict:
    """Does the data's own (prior-free) shape contradict the isotropy prior?

    The prior says each entry of ``W - wbar I`` (upper triangle, m entries) is about
    ``tau * wbar``, so the relative anisotropy ``d = |W - wbar I| / wbar`` of a sensor the prior
    fits is about ``tau sqrt(m)``. If the prior-free fit puts d beyond
    :data:`CONFLICT_SPREADS` times that, and its standard error (delta method on the
    Gauss-Newton covariance ``sigma^2 (J^T J)^-1``) is below :data:`CONFLICT_PRECISION` of d, the
    data determine an anisotropic shape the prior cannot describe: a prior-data conflict (Evans
    and Moshonov 2006), and the prior can only bias the fit. (This is the case cross-validation
    gets wrong on nearly flat, fully covered ellipsoids: the prior-free fold fits stop in poor
    local minima and the prior seems to predict better.)

    Also ``data_dominated``: the data pin the shape down to well within the prior's spread
    (``se < DATA_DOMINATED * tau``), so the prior would carry about ``(se / tau)^2`` < 1 % of the
    information: it cannot help, and the fit skips the cross-validation (full-sphere logs).

    Returns {"anisotropy": d, "anisotropy_stderr": se, "conflict": bool, "data_dominated": bool}.
    """
    r = W.shape[0]
    idx = _sym_index(r)
    m = len(idx)
    wbar = np.trace(W) / r
    e, J = _prior(W, idx, 1.0)
    norm = float(np.linalg.norm(e))
    d = norm / wbar
    # gradient of d over the parameters (c, upper triangle of W); c does not enter
    grad = np.zeros(r + m)
    if norm > 0:
        grad += J.T @ e / (norm * wbar)
    for a, (j, k) in enumerate(idx):
        if j == k:
            grad[r + a] -= norm / wbar**2 / r
    try:
        var = float(grad @ np.linalg.solve(JTJ, grad)) * sigma2
    except np.linalg.LinAlgError:
        var = float("inf")
    se = float(np.sqrt(max(var, 0.0)))
    conflict = bool(d > CONFLICT_SPREADS * tau * np.sqrt(m) and se < CONFLICT_PRECISION * d)
    return {"anisotropy": float(d), "anisotropy_stderr": se, "conflict": conflict,
            "data_dominated": bool(se < DATA_DOMINATED * tau)}


def fit_ellipsoid(
    Y: np.ndarray,
    refine: bool = True,
    max_iter: int = 200,
    tol: float = 1e-12,
    isotropy_prior: float | str | None = "auto",
) -> EllipsoidFit:
    """Fit an ellipse (r=2) or ellipsoid (r=3) to points Y of shape (n, r).

    ``isotropy_prior`` is the prior spread tau of W around a multiple of the identity, relative to
    its mean diagonal: the refinement minimises ``sum d_i^2 + (sigma / tau)^2 |W - wbar I|^2 /
    wbar^2`` with sigma the current residual rms (a maximum a posteriori fit). With good coverage
    the data outweigh it by ~n; with partial coverage it keeps the ill-determined shape, and so
    the offset, bounded, but only if the sensor really is near isotropic: on an anisotropic
    sensor it pulls the shape, and the offset with it, the wrong way. None disables it; a number
    always uses it.

    ``"auto"`` (default) lets the data decide: the fit is cross-validated with the prior
    (tau = :data:`AUTO_TAU`) and without it (:func:`cross_validate_prior`, 5 strided folds,
    held-out Sampson cost) and the prior is kept only where it predicts held-out points better.
    A prior that is wrong for the sensor biases the shape, which shows as a larger held-out
    residual; where the data cannot pin down the shape (partial coverage of a near-isotropic
    sensor), the unregularised fit over-fits the folds and the prior wins. The choice and both
    costs are in ``info["prior_selection"]``.

    Returns an :class:`EllipsoidFit`; ``info["start"]`` is ``"algebraic"`` or
    ``"sphere (hyperboloid rejected)"``.

    Y may be a :class:`calib.data.stream.ChunkSource` (rows computed per block, never all in
    memory).
    """
    if isinstance(Y, ChunkSource):  # two passes: mean, then mean squared distance from it
        n, r = Y.count(), Y.p
        mu = sum(y.sum(axis=0) for y in blocks_of(Y)) / max(n, 1)
        ss = sum(float(np.sum((y - mu) ** 2)) for y in blocks_of(Y))
        scale = float(np.sqrt(ss / max(n, 1))) or 1.0
        Yn = normalised(Y, mu, scale)
    else:
        Y = np.asarray(Y, float)
        n, r = Y.shape
        mu = Y.mean(axis=0)
        scale = float(np.sqrt(np.mean(np.sum((Y - mu) ** 2, axis=1)))) or 1.0
        Yn = (Y - mu) / scale
    return fit_normalised(Yn, mu, scale, refine, max_iter, tol, isotropy_prior)


def normalised(Y: ChunkSource, mu, scale) -> ChunkSource:
    """``(Y - mu) / scale`` computed per block."""
    from calib.data.stream import MappedSource

    return MappedSource(Y, lambda y: (y - mu) / scale, p=Y.p)


def subsample_steps(n: int, refine: bool = True) -> list[int]:
    """Strides of the subsamples :func:`fit_normalised` takes of n rows (the algebraic start and
    the refinement; the cross-validation of the prior), so a streamed fit can gather them in an
    earlier pass."""
    steps = [int(np.ceil(n / SUBSAMPLE_ROWS)) if refine and n > SUBSAMPLE_ROWS else 1]
    if refine:
        steps.append(int(np.ceil(n / CV_MAX_ROWS)) if n > CV_MAX_ROWS else 1)
    return steps


def fit_normalised(
    Yn,
    mu: np.ndarray,
    scale: float,
    refine: bool = True,
    max_iter: int = 200,
    tol: float = 1e-12,
    isotropy_prior: float | str | None = "auto",
) -> EllipsoidFit:
    """:func:`fit_ellipsoid` on ``Yn = (Y - mu) / scale`` (an array or a
    :class:`calib.data.stream.ChunkSource`, streamed: full passes only for the full-data steps);
    the result is in Y's units."""
    n, r = rows_of(Yn), _ncols(Yn)
    if isinstance(Yn, ChunkSource) and n <= SUBSAMPLE_ROWS:
        Yn = Yn.to_array()  # small: the in-memory code as it is
    if isinstance(Yn, ChunkSource):
        Yn.want(*subsample_steps(n, refine))
    # the algebraic fit is only a start: for large n an evenly strided subsample is enough
    step = int(np.ceil(n / SUBSAMPLE_ROWS)) if refine and n > SUBSAMPLE_ROWS else 1
    start, gap = _algebraic(strided_of(Yn, step) if step > 1 else Yn)
    info = {"algebraic_eigen_gap": min(gap, 1e300)}
    if start is None:
        warn(
            "the unconstrained quadric fit is a hyperboloid (partial coverage?); using a "
            "constrained ellipsoid fit, the offset is unreliable"
        )
        c, E = _sphere(Yn)
        info["start"] = "sphere (hyperboloid rejected)"
    else:
        c, E = start
        info["start"] = "algebraic"
    W = _sqrt_sym(E)
    idx = _sym_index(r)
    npar = r + len(idx)
    tau = isotropy_prior
    if isinstance(tau, str):
        if tau != "auto":
            raise ValueError(f"isotropy_prior must be a number, None or 'auto', got {tau!r}")
        tau = None
        if refine:
            free = _refine(Yn, c, W, idx, npar, None, max_iter, tol)
            conflict = prior_conflict(free[1], free[5], free[6] / max(n - npar, 1), AUTO_TAU)
            if conflict["conflict"] or conflict["data_dominated"]:
                use = False
                why = "prior-data conflict" if conflict["conflict"] else "data dominate the prior"
                info["prior_selection"] = {"criterion": why, "prior_used": False, **conflict}
            else:
                cv = cross_validate_prior(Yn, c, W, AUTO_TAU, max_iter=max_iter, tol=tol)
                use = bool(np.isfinite(cv["prior"]) and cv["prior"] < CV_MARGIN * cv["none"])
                info["prior_selection"] = {
                    "criterion": f"{cv['folds']}-fold held-out Sampson cost",
                    "rows": cv["rows"],
                    "cost_with_prior": cv["prior"],
                    "cost_without_prior": cv["none"],
                    "prior_used": use,
                    **conflict,
                }
            tau = AUTO_TAU if use else None
    if refine and isotropy_prior == "auto" and tau is None:
        c, W, pw, it, converged, JTJ, data_cost = free  # the prior-free fit is the answer
    elif refine:
        c, W, pw, it, converged, JTJ, data_cost = _refine(Yn, c, W, idx, npar, tau, max_iter, tol)
    else:
        it, converged, pw = 0, True, 0.0
        data_cost = _cost(Yn, c, W)
        JTJ, _, _ = _normal_equations(Yn, c, W, idx, pw)
    info["residual_rms"] = float(np.sqrt(data_cost / n)) * scale
    info["isotropy_prior"] = tau
    info["prior_weight"] = pw
    sigma2 = data_cost / max(n - npar, 1)
    # covariance of (c, upper triangle of W) in the caller's units: c = mu + scale c_n,
    # W = W_n / scale
    units = np.r_[np.full(r, scale), np.full(len(idx), 1.0 / scale)]
    try:
        cov = np.linalg.inv(JTJ) * sigma2 * np.outer(units, units)
        cond = float(np.linalg.cond(JTJ))
    except np.linalg.LinAlgError:
        cov = np.full((npar, npar), np.inf)
        cond = float("inf")
    stderr = np.sqrt(np.clip(np.diag(cov)[:r], 0, None))
    info.update({"iterations": it, "converged": bool(converged), "condition_number_JTJ": cond})
    return EllipsoidFit(centre=mu + scale * c, W=W / scale, centre_stderr=stderr, cov=cov,
                        info=info)
