"""Shape from motion with sensor bias: ``Z = [M 1] [S; z0^T]`` (paper eqs. 15-18).

Two routes, both returning a :class:`calib.data.result.Calibration` with the offset filled in:

``method="paper"`` (section 7.1): rank r+1 SVD of the raw data, ``M^ = U* Sigma*^1/2``. The last
column of ``A^-1`` satisfies the plane ``m^T a4 = 1`` (linear least squares); the first r columns
``B^T`` the cylinder ``m^T B^T B m = 1`` (18). Start: the linear quadric ``m^T Q m = 1`` (19). On
the
plane that fit is not unique (``Q + lam a4 a4^T``, rescaled, fits the same points), so the
free ``lam`` is fixed where Q becomes singular: by the matrix determinant lemma
``lam = -1 / (a4^T Q^-1 a4)``. Zeroing the smallest singular value of that Q gives B. Refinement:
``scipy.optimize.least_squares`` on the residuals ``|B m_i| - 1`` and ``m_i^T a4 - 1``, or plain
gradient descent on their mean square, as in the paper (``refine="gd"``). Needs p >= r+1.

``method="centered"``: subtract the mean, rank-r PCA, fit an ellipsoid to the r-dimensional
coordinates (:mod:`calib.estimators.ellipsoid`, approximate maximum likelihood); its centre c gives
the offset
``z0 = mean + V_r c`` and its shape the calibration. Works for p = r (3-axis magnetometers).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from calib.data.result import (
    Calibration,
    CalibrationError,
    add_uncertainty,
    channel_span,
    coverage_diagnostics,
    excitation_is_poor,
    propagate,
    warn,
)
from calib.data.stream import (
    ChunkSource,
    MappedSource,
    Scan,
    as_source,
    check_scan_samples,
    is_streamed,
    scan,
)
from calib.data.validate import check_dof, check_rank, force_rank
from calib.estimators.ellipsoid import fit_ellipsoid, fit_normalised, subsample_steps
from calib.estimators.sfm import (
    coverage_step,
    finish_frame,
    fit_unit_quadric,
    magnitude_pass,
    principal,
    rank_gap,
    unit_quadric_and_plane,
)

#: Decision: docs/calib_design.md D12.
METHODS = ("centered", "paper")
#: The paper route's refinement uses at most this many (evenly strided) rows.
#: Decision: docs/calib_design.md D13.
PAPER_REFINE_MAX_ROWS = 50_000


def fit_bias(
    Z,
    dof: int = 3,
    method: str = "centered",
    known_Z=None,
    known_M=None,
    magnitude: float | None = None,
    drop_nonfinite: bool = False,
    whiten: bool = True,
    **kwargs,
) -> Calibration:
    """Shape from motion with bias; dispatches to :func:`fit_centered` or :func:`fit_paper`.

    Parameters
    ----------
    Z : array of shape (n, p); or a ``dask.array.Array`` or :class:`calib.data.stream.ChunkSource`,
        streamed block by block and never held whole in memory (:mod:`calib.data.stream`; the same
        result as the in-memory fit up to rounding)
    dof : 2 or 3 (6-DOF: :func:`calib.estimators.ft6.fit_ft6`)
    method : "centered" (default) or "paper"
    known_Z, known_M : optional known pairs (k, p), (k, dof) fixing rotation and scale
    magnitude : load magnitude used as scale when no known pairs are given
    whiten : divide every channel by its noise level (:func:`calib.estimators.sfm.noise_scale`,
    factor
        analysis of the readings' covariance) before the route's SVD, and scale the result back:
        the calibrated loads then do not depend on the channels' units. The centered
        route is also independent of the channels' offsets (it subtracts the mean); the paper
        route is not, with noise (its SVD of the uncentred readings weighs the offset). False
        runs the route on the raw readings, as the paper does (the paper's trials use it); the
        isotropy prior of the centered route then speaks of the raw channels (on the paper's
        own near-isotropic sensor, Trial 3 at a 60 degree cap, 20 seeds: offset error median
        7.4 counts raw, 17.1 whitened; at 90 degrees 1.6 and 2.4; full sphere equal).

    A channel that is an exact affine copy of another (logged twice) is left out of the fit
    and given a column of zeros in C (:mod:`calib.data.copies`).
    """
    if method not in METHODS:
        raise CalibrationError(f"method must be one of {METHODS}, got {method!r}")
    from calib.data.copies import fit_without_copies

    # a channel logged twice (an exact affine copy): fitted without it (calib.data.copies)
    out = fit_without_copies(Z, known_Z, lambda Zs, Zk: fit_bias(
        Zs, dof, method, Zk, known_M, magnitude, drop_nonfinite, whiten, **kwargs), dof)
    if out is not None:
        return out
    route = fit_centered if method == "centered" else fit_paper
    if not whiten:
        return route(Z, dof, known_Z, known_M, magnitude, drop_nonfinite, **kwargs)
    _, r, data = _prepare_source(Z, dof, drop_nonfinite, int(method == "paper"))
    from calib.estimators.sfm import gram, noise_scale

    cov = gram(data.source, center=data.mean) / max(data.n - 1, 1)
    s, how = noise_scale(cov, r)
    s = s / np.exp(np.mean(np.log(s)))  # one common factor: geometric mean 1
    # scaled only, not moved: the paper route's rank-(r+1) SVD of the uncentred readings depends
    # on where the origin is (with noise), and no canonical origin does well on every sensor:
    # the paper's Trial 3 at a 90 degree cap measured offset errors of 4.8 counts (median, 20
    # seeds) at its own origin, 2.3 / 40 / 514 with the data's mean moved to 0.5 / 1 / 3 rms radii
    if is_streamed(Z):
        src = as_source(Z)
        Zw = MappedSource(src, lambda b, s=s: b / s, p=src.p)
    else:
        Zw = np.asarray(Z, float) / s
    kw = None if known_Z is None else np.atleast_2d(np.asarray(known_Z, float)) / s
    cal = route(Zw, dof, kw, known_M, magnitude, drop_nonfinite, **kwargs)
    rows = data.source.strided(max(1, int(np.ceil(data.n / SCALE_BOOTSTRAP_ROWS))))
    return _unwhiten(cal, s, how, _log_scale_cov(rows, r))


#: The uncertainty of the channel scales (:func:`_log_scale_cov`): bootstrap resamples, on at
#: most this many (evenly strided) rows.
#: Decision: docs/calib_design.md D17.
SCALE_BOOTSTRAP = 20
#: Decision: docs/calib_design.md D17.
SCALE_BOOTSTRAP_ROWS = 20_000


def _log_scale_cov(rows: np.ndarray, r: int, seed: int = 0) -> np.ndarray | None:
    """Covariance of the log channel scales of :func:`calib.estimators.sfm.noise_scale` over
    bootstrap
    resamples of the rows (deterministic: seeded; the resamples' factor analyses run as one
    stack). The scales choose which left inverse of the
    shape C is (its part that the loads of noise-free readings never see), so their sampling
    error is part of C's standard error."""
    from calib.estimators.sfm import noise_scale

    rows = rows[np.all(np.isfinite(rows), axis=1)]
    n = len(rows)
    if n < 3:
        return None
    rng = np.random.default_rng(seed)
    covs = np.array([np.cov(rows[rng.integers(0, n, n)], rowvar=False)
                     for _ in range(SCALE_BOOTSTRAP)])
    sb, _ = noise_scale(covs, r)
    logs = np.log(sb)
    return np.cov(logs - logs.mean(axis=1, keepdims=True), rowvar=False)


def _unwhiten(cal: Calibration, s: np.ndarray, how: str,
              log_cov: np.ndarray | None = None) -> Calibration:
    """A calibration of the readings ``z / s`` as one of the readings ``z``.
    ``log_cov``: the covariance of ``log s`` (:func:`_log_scale_cov`), added to C's standard
    error by the delta method on ``C(s) = (A^T D A)^-1 A^T D``, ``D = diag(s^-2)``, at the fitted
    shape ``A`` (C's left-inverse part that the scales choose)."""
    d = dict(cal.diagnostics)
    C = cal.C / s[None, :]
    for key in ("offset_stderr", "span"):
        if key in d:
            d[key] = np.asarray(d[key]) * s
    if "C_stderr" in d:
        C_se = np.asarray(d["C_stderr"]) / s[None, :]
        # p == dof: C is the shape's only inverse, the weights choose nothing
        if (log_cov is not None and np.all(np.isfinite(log_cov))
                and C.shape[1] > C.shape[0]):
            Dinv = s**2
            try:
                A = (Dinv[:, None] * C.T) @ np.linalg.inv((C * Dinv[None, :]) @ C.T)

                def fn(t, A=A, off=cal.offset):
                    w = np.exp(-2.0 * t)
                    Aw = A * w[:, None]
                    return off, np.linalg.solve(A.T @ Aw, Aw.T)

                _, C_se_w = propagate(fn, np.log(s), log_cov, len(s))
            except np.linalg.LinAlgError:  # C of lower rank than its rows: nothing to say
                C_se_w = np.full(C.shape, np.inf)
            C_se = np.sqrt(C_se**2 + C_se_w**2)
        d["C_stderr"] = C_se
    d["channel_scale"] = {"scale": s, "method": how,
                          "note": "singular values are of the readings divided by scale"}
    return Calibration(C=C, offset=cal.offset * s,
                       dof=cal.dof, method=cal.method, diagnostics=d)


def _prepare_source(Z, dof, drop_nonfinite, extra_rank) -> tuple[int, int, Scan]:
    """:func:`_prepare` for any input (array, dask array, chunk source) in one pass: returns
    (dof, r, scan) with the checked source and its column statistics."""
    dof = check_dof(dof)
    if dof == 6:
        raise CalibrationError("6-DOF calibration needs known loads: use "
                               "calib.estimators.ft6.fit_ft6")
    r = force_rank(dof)
    data = scan(as_source(Z), "Z", drop_nonfinite)
    p = data.p
    if p < r + extra_rank:
        if extra_rank:
            raise CalibrationError(
                f"method 'paper' needs p >= r+1 = {r + 1} channels for dof={dof}, got p={p}; "
                "use --method centered"
            )
        raise CalibrationError(f"need at least {r} channels for dof={dof}, got p={p}")
    check_scan_samples(data, r + r * (r + 1) // 2 + 1)
    return dof, r, data


def _finish(
    Z,
    C_unit,
    offset,
    dof,
    method,
    s,
    r,
    nbad,
    extra,
    known_Z,
    known_M,
    magnitude,
    offset_stderr=None,
    U=None,
    uncertainty=None,
    loads=None,
):
    """Diagnostics, frame and uncertainty of a fit. Z is the data (an array, with U its unit
    loads or None) or a :class:`calib.data.stream.Scan` (then one more pass over its source, with
    ``loads(block)`` the unit loads of a block, ``(block - offset) @ C_unit.T`` by default)."""
    if isinstance(Z, Scan):
        n = Z.n
        if loads is None:
            def loads(b, offset=offset, C_unit=C_unit):
                return (b - offset) @ C_unit.T
        mstats = magnitude_pass(Z.source, loads)
        cov = coverage_diagnostics(loads(Z.source.strided(coverage_step(n))))
    else:
        n = len(Z)
        if U is None:
            U = (Z - offset) @ C_unit.T
        mags = np.linalg.norm(U, axis=1)
        cov = coverage_diagnostics(U)
        mstats = {"residual_magnitude_rms": float(np.sqrt(np.mean((mags - 1) ** 2))),
                  "magnitude_mean": float(mags.mean())}
    diag = {
        "n_samples": n,
        "n_dropped_nonfinite": nbad,
        "singular_values": s,
        # the paper route factors the raw data (offset included): its rank is r + 1
        "rank": r + (method == "paper"),
        "rank_gap": rank_gap(s, r + (method == "paper")),
        "coverage": cov,
        "condition_number_C": float(np.linalg.cond(C_unit)),
        "residual_magnitude_rms": mstats["residual_magnitude_rms"],
        "magnitude_mean": mstats["magnitude_mean"],
    }
    diag.update(extra)
    poor = excitation_is_poor(cov)
    diag["excitation_poor"] = bool(poor)
    if poor:
        # the paper route's standard errors leave the poor excitation out (its verdict refuses
        # such a fit, calib.verdict.reliability); the centered route's carry it (covered 91-93 % of
        # true offsets at 60-90 degree caps, nominal 95 %), so its warning says where to look
        warn(
            f"poor excitation (isotropy {cov['isotropy']:.2f}, directions within "
            f"{cov['cap_half_angle_deg']:.0f} deg of their mean): "
            + ("the offset is unreliable" if method == "paper" else
               "the offset is extrapolated from these directions; its standard errors "
               "(offset_stderr) say how far it holds")
        )
    cal = Calibration(C=C_unit, offset=offset, dof=dof, method=method, diagnostics=diag)
    cal = finish_frame(cal, known_Z, known_M, magnitude)
    if uncertainty is not None:
        # C = A C_unit: the frame (known pairs or magnitude) is held fixed
        A = cal.C @ np.linalg.pinv(C_unit)
        x, cov, fn = uncertainty
        off_se, C_se = propagate(lambda t: fn(t, A), x, cov, len(offset))
        if offset_stderr is not None:  # extra variance the parameter covariance leaves out
            off_se = np.sqrt(off_se**2 + offset_stderr**2)
        add_uncertainty(cal, off_se, C_se, Z.span if isinstance(Z, Scan) else channel_span(Z))
    return cal


# --------------------------------------------------------------------------------- centered


def fit_centered(
    Z,
    dof: int = 3,
    known_Z=None,
    known_M=None,
    magnitude: float | None = None,
    drop_nonfinite: bool = False,
    refine: bool = True,
    isotropy_prior: float | str | None = "auto",
) -> Calibration:
    """Mean removal, rank-r PCA, ellipsoid fit; see the module docstring. Works for p >= r.

    ``refine`` runs the approximate maximum-likelihood refinement; ``isotropy_prior`` is the prior
    spread of the shape around a sphere (see :func:`calib.estimators.ellipsoid.fit_ellipsoid`):
    negligible with good coverage, it keeps the offset bounded under partial coverage.

    Returns a Calibration with ``method="centered"``; extra diagnostics: ``ellipsoid`` (fit info),
    ``offset_stderr`` (p,) from the refinement's Jacobian.
    """
    dof, r, data = _prepare_source(Z, dof, drop_nonfinite, 0)
    src, n = data.source, data.n
    mu = data.mean
    # the strided subsamples (algebraic start, refinement, prior choice, coverage) are gathered
    # during the Gram pass
    src.want(*subsample_steps(n, refine), coverage_step(n))
    s, V = principal(src, center=mu)
    check_rank(s, r, "the centred data")
    Vr = V[:, :r]
    muV = mu @ Vr
    # Y = (Z - mu) @ Vr per block, never n x p (nor n x r) in memory; its mean is zero and its
    # mean square sum(s_r^2) / n, so the ellipsoid fit normalises it without another pass
    scale = float(np.sqrt(np.sum(s[:r] ** 2) / max(n, 1))) or 1.0
    Yn = MappedSource(src, lambda b: (b @ Vr - muV) / scale, p=r)
    fit = fit_normalised(Yn, np.zeros(r), scale, refine=refine, isotropy_prior=isotropy_prior)
    offset = mu + Vr @ fit.centre
    C_unit = fit.W @ Vr.T
    # the mean's own error in the p - r directions the ellipsoid does not see (s^2 / n is the
    # variance there, / n again for the mean)
    perp = (V[:, r:] ** 2) @ (s[r:] ** 2 / max(n * (n - 1), 1))
    stderr = np.sqrt(perp)
    idx = [(j, k) for j in range(r) for k in range(j, r)]

    def fn(theta, A, mu=mu, Vr=Vr, idx=idx, r=r):
        W = np.zeros((r, r))
        for a, (j, k) in enumerate(idx):
            W[j, k] = W[k, j] = theta[r + a]
        return mu + Vr @ theta[:r], A @ W @ Vr.T

    theta = np.r_[fit.centre, [fit.W[j, k] for j, k in idx]]

    # C_unit only sees the span of Vr: the unit loads from the projection
    def loads(b, Vr=Vr, muV=muV, c=fit.centre, W=fit.W):
        return ((b @ Vr - muV) - c) @ W.T

    return _finish(
        data,
        C_unit,
        offset,
        dof,
        "centered",
        s,
        r,
        data.nbad,
        {"ellipsoid": fit.info},
        known_Z,
        known_M,
        magnitude,
        offset_stderr=stderr,
        uncertainty=(theta, fit.cov, fn),
        loads=loads,
    )


# ------------------------------------------------------------------------------------ paper


def cylinder_start(
    Mhat, a4: np.ndarray, resolve: bool = True, Q0: np.ndarray | None = None
) -> tuple[np.ndarray, dict]:
    """Paper's start for B (r, r+1): linear quadric, freedom resolved, smallest singular value
    zeroed.

    ``resolve=False`` is the literal paper recipe (least-squares Q as it comes out, smallest
    eigenvalue zeroed), kept to show how far from the cylinder it can start.

    Returns (B, info) with ``info["lambda"]`` the resolved ``Q + lam a4 a4^T`` parameter and
    ``info["ok"]`` False if the quadric could not be made a cylinder (then the caller falls back).
    ``Q0``: the linear quadric of Mhat if already computed (Mhat may then be a chunk source).
    """
    q = len(a4)
    r = q - 1
    if Q0 is None:
        Q0 = fit_unit_quadric(Mhat)
    info = {"ok": False, "resolved": bool(resolve)}
    try:
        t = float(a4 @ np.linalg.solve(Q0, a4)) if resolve else np.inf
    except np.linalg.LinAlgError:
        t = np.inf
    if np.isfinite(t) and abs(t) > 1e-300:
        lam = -1.0 / t
        Q = (Q0 + lam * np.outer(a4, a4)) / (1.0 + lam)
        info["lambda"] = lam
    else:  # Q0 already singular: it is the cylinder
        Q = Q0
        info["lambda"] = 0.0
    w, V = np.linalg.eigh((Q + Q.T) / 2)
    order = np.argsort(np.abs(w))[::-1]
    w, V = w[order], V[:, order]
    info["eigenvalues"] = w.tolist()
    if np.all(w[:r] > 0):
        info["ok"] = True
    B = np.sqrt(np.abs(w[:r]))[:, None] * V[:, :r].T
    return B, info


def _plane_start(Mhat, a4):
    """Fallback start: ellipsoid fit in plane coordinates, B = W (P^T - c a4^T)."""
    q = len(a4)
    # orthonormal basis P (q, r) of a4's orthogonal complement
    Qf, _ = np.linalg.qr(np.column_stack([a4, np.eye(q)]))
    P = Qf[:, 1:q]
    Y = MappedSource(Mhat, lambda m: m @ P, p=q - 1) if isinstance(Mhat, ChunkSource) else Mhat @ P
    fit = fit_ellipsoid(Y, refine=False)
    return fit.W @ (P.T - np.outer(fit.centre, a4))


def _residuals(x, Mhat, r):
    q = r + 1
    B = x[: r * q].reshape(r, q)
    a4 = x[r * q :]
    return np.concatenate([np.linalg.norm(Mhat @ B.T, axis=1) - 1.0, Mhat @ a4 - 1.0])


def _jacobian(x, Mhat, r):
    q = r + 1
    n = len(Mhat)
    B = x[: r * q].reshape(r, q)
    V = Mhat @ B.T  # (n, r)
    rho = np.maximum(np.linalg.norm(V, axis=1), 1e-300)
    J = np.zeros((2 * n, r * q + q))
    # d|Bm|/dB_jk = (Bm)_j m_k / |Bm|
    J[:n, : r * q] = ((V / rho[:, None])[:, :, None] * Mhat[:, None, :]).reshape(n, r * q)
    J[n:, r * q :] = Mhat
    return J


def refine_gradient_descent(x0, Mhat, r, max_iter: int = 20000, tol: float = 1e-12):
    """Plain gradient descent on the mean squared residual, fixed step 1 / (2 lambda_max(m m^T)).

    Returns (x, info) with ``iterations``, ``converged``, ``cost``.
    """
    n = len(Mhat)
    H = Mhat.T @ Mhat / n
    step = 0.5 / np.linalg.eigvalsh(H)[-1]
    x = x0.copy()
    prev = np.inf
    it = 0
    converged = False
    for it in range(1, max_iter + 1):  # noqa: B007 (the count is returned after the loop)
        res = _residuals(x, Mhat, r)
        cost = float(res @ res / n)
        grad = 2.0 * (_jacobian(x, Mhat, r).T @ res) / n
        x = x - step * grad
        if abs(prev - cost) <= tol * max(cost, 1e-300):
            converged = True
            break
        prev = cost
    res = _residuals(x, Mhat, r)
    return x, {"iterations": it, "converged": converged, "cost": float(np.mean(res**2))}


def fit_paper(
    Z,
    dof: int = 3,
    known_Z=None,
    known_M=None,
    magnitude: float | None = None,
    drop_nonfinite: bool = False,
    refine: str | None = "lsq",
    gd_max_iter: int = 20000,
    start: str = "resolved",
) -> Calibration:
    """The paper's rank-(r+1) plane + cylinder method; see the module docstring.

    Parameters
    ----------
    refine : "lsq" (scipy least_squares, default), "gd" (plain gradient descent), or None
    start : "resolved" (quadric freedom fixed by the determinant lemma, default) or "naive"
    """
    dof, r, data = _prepare_source(Z, dof, drop_nonfinite, 1)
    src, n = data.source, data.n
    q = r + 1
    fit_step = int(np.ceil(n / PAPER_REFINE_MAX_ROWS))
    src.want(fit_step, coverage_step(n))  # gathered during the Gram pass
    s, V = principal(src)
    check_rank(s, q, "Z (with offset)")
    Vq, sq = V[:, :q], s[:q]
    Mhat = MappedSource(src, lambda b: (b @ Vq) / np.sqrt(sq), p=q)
    if start not in ("resolved", "naive"):
        raise CalibrationError(f"start must be 'resolved' or 'naive', got {start!r}")
    # one pass: the plane m^T a4 = 1 and the linear quadric, both least squares over all rows
    Q0, a4 = unit_quadric_and_plane(Mhat)
    B, start = cylinder_start(Mhat, a4, resolve=(start == "resolved"), Q0=Q0)
    if not start["ok"]:
        warn(
            "the quadric start is not a cylinder (poor excitation?); starting from a plane-"
            "coordinate ellipsoid fit instead"
        )
        B = _plane_start(Mhat, a4)
    x0 = np.concatenate([B.ravel(), a4])
    # the dense (2n x 16) Jacobian is too big for millions of rows: refine on a strided subsample
    Mfit = Mhat.strided(fit_step)
    cost0 = float(np.mean(_residuals(x0, Mfit, r) ** 2))
    extra = {"paper_start": start, "start_cost": cost0, "refine_rows": len(Mfit)}
    if refine == "lsq":
        sol = least_squares(
            _residuals,
            x0,
            jac=_jacobian,
            args=(Mfit, r),
            method="lm",
            xtol=1e-14,
            ftol=1e-14,
            gtol=1e-14,
            max_nfev=2000,
        )
        x = sol.x
        extra["refinement"] = {
            "solver": "scipy least_squares (lm)",
            "nfev": int(sol.nfev),
            "converged": bool(sol.status > 0),
            "cost": float(np.mean(sol.fun**2)),
        }
    elif refine == "gd":
        x, info = refine_gradient_descent(x0, Mfit, r, max_iter=gd_max_iter)
        extra["refinement"] = {"solver": "gradient descent", **info}
    elif refine is None:
        x = x0
    else:
        raise CalibrationError(f"refine must be 'lsq', 'gd' or None, got {refine!r}")
    B = x[: r * q].reshape(r, q)
    a4 = x[r * q :]
    Ainv = np.column_stack([B.T, a4])
    cond_A = float(np.linalg.cond(Ainv))
    if not np.isfinite(cond_A) or cond_A > 1e12:
        raise CalibrationError(
            "the plane and cylinder are degenerate (A^-1 singular); "
            "excitation is too poor for the paper method"
        )
    S_hat = np.sqrt(sq)[:, None] * Vq.T

    def fn(x, A=None, S_hat=S_hat, r=r, q=q):
        Ainv = np.column_stack([x[: r * q].reshape(r, q).T, x[r * q :]])
        S_aug = np.linalg.solve(Ainv, S_hat)
        C_unit = np.linalg.pinv(S_aug[:r].T)
        return S_aug[r], C_unit if A is None else A @ C_unit

    offset, C_unit = fn(x)
    extra["condition_number_Ainv"] = cond_A
    # Gauss-Newton covariance of (B, a4); B's rotation gauge (B -> R B) leaves the residuals
    # unchanged, hence the pseudo-inverse. The refinement saw len(Mfit) of n rows.
    res = _residuals(x, Mfit, r)
    J = _jacobian(x, Mfit, r)
    dof_res = max(len(res) - (len(x) - r * (r - 1) // 2), 1)
    cov = np.linalg.pinv(J.T @ J) * float(res @ res) / dof_res * len(Mfit) / n
    return _finish(data, C_unit, offset, dof, "paper", s, r, data.nbad, extra, known_Z, known_M,
                   magnitude, uncertainty=(x, cov, fn))
