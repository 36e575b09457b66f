"""Plan a static-pose rig before weighing masses: which poses get the known loads, and how
accurate the calibration can be (``calib plan``).

The accuracy is the Cramer-Rao bound of the pose-level model of :mod:`calib.estimators.rig`: pose
means ``zbar_j = A m_j + o`` with Gaussian noise of standard deviation ``noise / sqrt(samples)`` per
channel, the k known poses' loads given and the others' directions unknown (two angles each,
nuisance parameters), the magnitude tied by the known loads. The load error of a calibration on
a test load m is ``-C (dA m + do)`` to first order; its rms over 300 test loads spread over the
sphere is evaluated under the bound's covariance and under that of least squares with every
load known. Their ratio does not depend on the noise level or the sensor's gain; it depends on
the rig's geometry and (weakly) on the sensor's shape, taken isotropic here (``A = s Q``, Q with
orthonormal columns) unless a shape is given. With ``noise`` and ``sensitivity`` (counts per
load unit) the absolute bound is printed too. No estimator can beat the bound; the rig fit
reaches it on linear sensors (docs/calib.md).
"""

from __future__ import annotations

import numpy as np

from calib.data.result import CalibrationError
from calib.routes.joint import choose_known_poses
from calib.simulation.simulate import sample_directions


def _unit(th, ph):
    return np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])


def _load_error_ms(A, cov, test):
    """Mean over test loads and components of the squared first-order load error."""
    C = np.linalg.pinv(A)
    p = A.shape[0]
    total = 0.0
    for m in test:
        G = np.zeros((3, 4 * p))
        for a in range(p):
            G[:, a * 3:(a + 1) * 3] = -np.outer(C[:, a], m)
            G[:, 3 * p + a] = -C[:, a]
        total += np.trace(G @ cov @ G.T)
    return total / len(test) / 3


def bounds(directions, known, A=None, magnitude: float = 1.0, samples: int = 100,
           noise: float = 1.0, test=None) -> tuple[float, float]:
    """RMS load error (vector length, over the test loads) under the Cramer-Rao bound with the
    ``known`` poses' loads given, and with every load given: (bound, all-known bound).

    ``directions`` (P, 3) pose directions; ``A`` (p, 3) the sensor's response (default an
    isotropic 8-channel sensor of unit gain); ``noise`` per-reading standard deviation per
    channel; ``test`` (t, 3) test loads (default 300 spread over the sphere of ``magnitude``).
    """
    U = np.asarray(directions, float)
    U = U / np.linalg.norm(U, axis=1, keepdims=True)
    P = len(U)
    if A is None:
        A, _ = np.linalg.qr(np.random.default_rng(0).normal(size=(8, 3)))
    A = np.asarray(A, float)
    p = A.shape[0]
    F = magnitude * U
    known = [int(i) for i in known]
    unknown = [j for j in range(P) if j not in known]
    s2 = noise**2 / samples
    J = np.zeros((P * p, 4 * p + 2 * len(unknown)))
    eps = 1e-7
    for j in range(P):
        for a in range(p):
            J[p * j + a, a * 3:(a + 1) * 3] = F[j]
            J[p * j + a, 3 * p + a] = 1.0
        if j in unknown:
            t = 4 * p + 2 * unknown.index(j)
            u = U[j]
            th, ph = np.arccos(np.clip(u[2], -1, 1)), np.arctan2(u[1], u[0])
            J[p * j:p * (j + 1), t] = A @ ((_unit(th + eps, ph) - _unit(th - eps, ph))
                                           / (2 * eps)) * magnitude
            J[p * j:p * (j + 1), t + 1] = A @ ((_unit(th, ph + eps) - _unit(th, ph - eps))
                                               / (2 * eps)) * magnitude
    cov = np.linalg.pinv(J.T @ J / s2)[:4 * p, :4 * p]
    Jl = J[:, :4 * p]
    cov_all = np.linalg.pinv(Jl.T @ Jl / s2)
    if test is None:
        test = magnitude * sample_directions(300, 3, np.random.default_rng(12345))
    return (float(np.sqrt(3 * _load_error_ms(A, cov, test))),
            float(np.sqrt(3 * _load_error_ms(A, cov_all, test))))


def plan(directions, k: int = 4, magnitude: float = 1.0, samples: int = 100,
         noise: float | None = None, sensitivity: float | None = None) -> dict:
    """The recommended known poses for a budget of ``k`` known loads and the predicted error.

    Returns ``known`` (indices, :func:`calib.routes.joint.choose_known_poses`), ``ratio`` (bound
    over the all-known bound), ``ratio_first`` (the same for the first k poses, a naive choice),
    ``ratio_reading`` / ``ratio_reading_first`` (the same for the error on a new single
    reading, whose own noise adds to both: what a rig with one reading per pose sees) and,
    with ``noise`` and ``sensitivity``, ``bound`` and ``bound_all_known`` in load units.
    """
    U = np.asarray(directions, float)
    if U.ndim != 2 or U.shape[1] != 3 or not np.all(np.isfinite(U)):
        raise CalibrationError(f"pose directions must be an (n, 3) finite array, got {U.shape}")
    norms = np.linalg.norm(U, axis=1)
    if np.any(norms <= 0):
        raise CalibrationError("a pose direction is zero")
    if not 2 <= k < len(U):
        raise CalibrationError(f"the known-load budget must be 2..{len(U) - 1} for {len(U)} "
                               f"poses, got {k}")
    if len(U) > 200:
        raise CalibrationError(f"at most 200 candidate poses, got {len(U)}")
    known = choose_known_poses(U, k)
    b, b_all = bounds(U, known, magnitude=magnitude, samples=samples)
    f, f_all = bounds(U, range(k), magnitude=magnitude, samples=samples)
    # a new single reading adds its own noise through C (isotropic unit-gain sensor, unit
    # noise as in bounds): what a held-out reading's error is, and the ratio one-reading-per-
    # pose rigs see (their parameter errors are small beside it)
    A, _ = np.linalg.qr(np.random.default_rng(0).normal(size=(8, 3)))
    n2 = float(np.sum(np.linalg.pinv(A) ** 2))
    out = {"known": known, "ratio": b / b_all, "ratio_first": f / f_all, "k": k,
           "poses": len(U), "samples": samples,
           "ratio_reading": float(np.sqrt((b**2 + n2) / (b_all**2 + n2))),
           "ratio_reading_first": float(np.sqrt((f**2 + n2) / (f_all**2 + n2)))}
    if noise is not None and sensitivity is not None:
        A, _ = np.linalg.qr(np.random.default_rng(0).normal(size=(8, 3)))
        b, b_all = bounds(U, known, A=A * sensitivity, magnitude=magnitude, samples=samples,
                          noise=noise)
        out.update({"bound": b, "bound_all_known": b_all})
    return out
