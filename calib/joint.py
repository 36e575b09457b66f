"""Joint estimator: constant-magnitude rows and known (z, m) pairs in one weighted fit.

The centered and paper routes use known pairs only after the fit, to turn and scale a
calibration found from the magnitude constraint alone. On real rigs (a proof mass held in a
dozen static poses, many samples each) the magnitude rows see few distinct directions, and the
known loads carry shape information that such an alignment throws away. :func:`fit_joint`
minimises, over the calibration ``C`` (dof x p), the offset and the load magnitude ``g``,

    sum_i ((|C (z_i - o)| - g) / sigma_mag)^2 + sum_k |(C (z_k - o) - m_k) / sigma_known|^2,

i.e. a maximum-likelihood fit when the magnitude residuals have standard deviation
``sigma_mag`` and each known load component ``sigma_known`` (both in load units). It works in the
data's rank-r principal subspace (``z = mu + V_r y``), so ``C = K V_r^T`` and ``o = mu + V_r c``
with r^2 + r (+1) parameters; the start is the centered route aligned to the known pairs.
``g`` is fitted unless ``magnitude`` is given; the known pairs fix the frame and the scale.

Defaults: ``magnitude_sigma`` is the magnitude residual rms of the start (the readings' own
scatter in load units). ``known_sigma`` defaults to ``magnitude_sigma / sqrt(n / k)``: each of the
k known pairs weighs as much as an equal share of the n motion rows, which is what a known
reading averaged over a static pose's samples is worth when the rig spends about as long in
every pose. State the real accuracies when known (load application error, samples averaged).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from ._validate import check_matrix
from .bias import _finish, _prepare, fit_centered
from .result import CalibrationError, add_uncertainty, channel_span, propagate
from .sfm import principal

#: At most this many (evenly strided) motion rows enter the nonlinear least squares.
JOINT_MAX_ROWS = 50_000


def fit_joint(
    Z,
    known_Z,
    known_M,
    dof: int = 3,
    magnitude: float | None = None,
    known_sigma: float | None = None,
    magnitude_sigma: float | None = None,
    drop_nonfinite: bool = False,
):
    """Fit C, offset (and the load magnitude) to motion rows and known pairs together.

    Parameters
    ----------
    Z : (n, p) readings of a constant-magnitude load over orientations (static poses welcome)
    known_Z, known_M : (k, p), (k, dof) known pairs; k >= 2 (>= 3 to avoid a mirror image)
    magnitude : the load magnitude of the motion rows; None fits it
    known_sigma, magnitude_sigma : accuracies in load units (see the module docstring)

    Returns a Calibration with ``method="joint"``; diagnostics as the centered route's plus
    ``joint`` (sigmas, fitted magnitude, residual rms of both kinds, solver status) and standard
    errors from the weighted Jacobian.
    """
    if known_Z is None or known_M is None:
        raise CalibrationError("method 'joint' needs known loads (--known)")
    dof, r, Z, nbad = _prepare(Z, dof, drop_nonfinite, 0)
    Zk, _ = check_matrix(np.atleast_2d(known_Z), "known readings")
    Mk = np.atleast_2d(np.asarray(known_M, float))
    if len(Zk) != len(Mk):
        raise CalibrationError(f"{len(Zk)} known readings but {len(Mk)} known loads")
    if Zk.shape[1] != Z.shape[1]:
        raise CalibrationError(f"known readings have {Zk.shape[1]} channels, data {Z.shape[1]}")
    if len(Zk) < 2:
        raise CalibrationError(f"method 'joint' needs at least 2 known loads, got {len(Zk)}")
    Mk = Mk[:, :r]
    for name, v in (("known_sigma", known_sigma), ("magnitude_sigma", magnitude_sigma),
                    ("magnitude", magnitude)):
        if v is not None and not (np.isfinite(v) and v > 0):
            raise CalibrationError(f"{name} must be a positive number, got {v!r}")
    start = fit_centered(Z, dof, known_Z=Zk, known_M=Mk, magnitude=magnitude)
    mu = Z.mean(axis=0)
    s, V = principal(Z, center=mu)
    Vr = V[:, :r]
    step = int(np.ceil(len(Z) / JOINT_MAX_ROWS))
    Y = (Z[::step] - mu) @ Vr
    Yk = (Zk - mu) @ Vr
    K0 = start.C @ Vr
    c0 = Vr.T @ (start.offset - mu)
    mags0 = np.linalg.norm((Y - c0) @ K0.T, axis=1)
    g0 = float(magnitude) if magnitude is not None else float(np.mean(mags0))
    if magnitude_sigma is None:
        magnitude_sigma = float(np.sqrt(np.mean((mags0 - g0) ** 2))) or 1e-12 * g0
    if known_sigma is None:
        known_sigma = magnitude_sigma / np.sqrt(max(len(Z) / len(Zk), 1.0))
    fit_g = magnitude is None
    nK = r * r

    def unpack(x):
        K = x[:nK].reshape(r, r)
        c = x[nK : nK + r]
        g = x[nK + r] if fit_g else float(magnitude)
        return K, c, g

    def residuals(x):
        K, c, g = unpack(x)
        m = np.linalg.norm((Y - c) @ K.T, axis=1) - g
        k = ((Yk - c) @ K.T - Mk).ravel()
        return np.r_[m / magnitude_sigma, k / known_sigma]

    def jac(x):
        K, c, g = unpack(x)
        D = Y - c
        U = D @ K.T
        rho = np.maximum(np.linalg.norm(U, axis=1), 1e-300)
        Un = U / rho[:, None]
        n = len(Y)
        J = np.zeros((n + Yk.size, len(x)))
        J[:n, :nK] = (Un[:, :, None] * D[:, None, :]).reshape(n, nK) / magnitude_sigma
        J[:n, nK : nK + r] = -(Un @ K) / magnitude_sigma
        if fit_g:
            J[:n, nK + r] = -1.0 / magnitude_sigma
        Dk = Yk - c
        for j in range(len(Yk)):
            for a in range(r):
                row = n + j * r + a
                J[row, a * r : (a + 1) * r] = Dk[j] / known_sigma
                J[row, nK : nK + r] = -K[a] / known_sigma
        return J

    x0 = np.r_[K0.ravel(), c0, [g0] if fit_g else []]
    sol = least_squares(residuals, x0, jac=jac, method="lm", xtol=1e-14, ftol=1e-14,
                        gtol=1e-14, max_nfev=500)
    K, c, g = unpack(sol.x)
    C = K @ Vr.T
    offset = mu + Vr @ c
    nm = len(Y)
    res = sol.fun
    U = (Z - offset) @ C.T
    extra = {
        "joint": {
            "known_sigma": known_sigma,
            "magnitude_sigma": magnitude_sigma,
            "magnitude": float(g),
            "magnitude_fitted": fit_g,
            "n_known": len(Zk),
            "rows_used": nm,
            "magnitude_residual_rms": float(np.sqrt(np.mean(res[:nm] ** 2)) * magnitude_sigma),
            "known_residual_rms": float(np.sqrt(np.mean(res[nm:] ** 2)) * known_sigma),
            "nfev": int(sol.nfev),
            "converged": bool(sol.status > 0),
            "start": "centered + alignment",
        }
    }
    cal = _finish(Z, C / g, offset, dof, "joint", s, r, nbad, extra, None, None, None,
                  U=U / g)
    cal.C = C
    # Gauss-Newton covariance, scaled by the reduced chi-square (misstated sigmas are absorbed);
    # the motion rows used are len(Y) of n
    J = jac(sol.x)
    chi2 = float(res @ res) / max(len(res) - len(sol.x), 1)
    Jm, Jk = J[:nm] * np.sqrt(len(Z) / nm), J[nm:]
    try:
        cov = np.linalg.inv(Jm.T @ Jm + Jk.T @ Jk) * chi2
    except np.linalg.LinAlgError:
        cov = np.full((len(sol.x), len(sol.x)), np.inf)

    def fn(x):
        K, c, _ = unpack(x)
        return mu + Vr @ c, K @ Vr.T

    off_se, C_se = propagate(fn, sol.x, cov, len(offset))
    add_uncertainty(cal, off_se, C_se, channel_span(Z))
    return cal
