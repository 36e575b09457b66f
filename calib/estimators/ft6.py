"""6-DOF force/torque calibration: shape from motion with a proof mass, plus known loads.

A proof mass at a fixed lever arm r gives loads ``m = [F; r x F] = G F`` with ``G`` (6, 3), so the
rotation data ``Z`` (n, p) has rank 3 (+1 with bias) however many channels there are. Shape from
motion on it yields the offset and the force part of the calibration on the 3-dimensional
subspace W that the proof mass excites, in a unit-magnitude frame of arbitrary orientation:
``u = C_u (z - z0)``.

The full C (6, p) must also map the other directions of the (6-dimensional) measurement space,
which a single proof mass never excites. Writing ``N`` (p, p-3) for an orthonormal basis of the
complement of W, every calibration has the form

    C = H C_u + Y N^T,    H = [s R; [r]x s R]  (6, 3),  Y (6, p-3),

with a rotation R, scale s and lever arm r (7 numbers) and a free 6 x 3 block of Y on the
measured part of the complement. Known pairs (z_k, m_k) give 6 equations each. They are fitted by
variable projection (Y linear, (R, s, r) by ``scipy.optimize.least_squares``), started from the
unstructured linear fit, which needs the known loads to span all 6 load dimensions: hence at least
6 known loads (see docs/calib.md for the counting argument).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calib.data.result import Calibration, CalibrationError
from calib.data.stream import as_source, scan
from calib.data.validate import check_matrix
from calib.estimators.bias import fit_bias
from calib.estimators.sfm import fit_sfm


def skew(v) -> np.ndarray:
    """Cross-product matrix: ``skew(r) @ F == np.cross(r, F)``; shape (3, 3)."""
    x, y, z = np.asarray(v, float)
    return np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])


def _vee(K):
    return 0.5 * np.array([K[2, 1] - K[1, 2], K[0, 2] - K[2, 0], K[1, 0] - K[0, 1]])


def _structured_H(theta, lever_arm=None):
    R = Rotation.from_rotvec(theta[:3]).as_matrix()
    s = np.exp(theta[3])
    r = theta[4:7] if lever_arm is None else lever_arm
    sR = s * R
    return np.vstack([sR, skew(r) @ sR])


def fit_ft6(
    Z,
    known_Z,
    known_M,
    bias: bool = True,
    method: str = "centered",
    lever_arm=None,
    drop_nonfinite: bool = False,
) -> Calibration:
    """Calibrate a 6-DOF sensor from proof-mass rotation data and >= 6 known loads.

    Parameters
    ----------
    Z : array (n, p), p >= 6: a proof mass moved over orientations (constant lever arm); a dask
        array or a :class:`calib.data.stream.ChunkSource` is streamed
    known_Z : array (k, p), readings under known loads (same offset as Z)
    known_M : array (k, 6), the known loads [Fx, Fy, Fz, Tx, Ty, Tz]; must span 6 dimensions
    bias : estimate the offset from Z (shape from motion with bias) or assume none
    method : bias route, "centered" or "paper"
    lever_arm : optional (3,) proof-mass lever arm of the rotation data if known (else estimated)

    Returns
    -------
    Calibration (dof 6, ``method="ft6-sfm"``); diagnostics add ``force_stage`` (the 3-DOF stage's
    diagnostics), ``lever_arm``, ``scale`` and ``known_residual_rms``.
    """
    data = scan(as_source(Z), "Z", drop_nonfinite)  # streamed: the 3-DOF stage makes the passes
    p, nbad = data.p, data.nbad
    if p < 6:
        raise CalibrationError(f"a 6-DOF sensor needs p >= 6 channels, got p={p}")
    Zk, _ = check_matrix(np.atleast_2d(known_Z), "known readings")
    Mk = np.atleast_2d(np.asarray(known_M, float))
    if Mk.shape[1] != 6 or len(Mk) != len(Zk):
        raise CalibrationError(
            f"known loads must be (k, 6) matching known readings (k, {p}), got {Mk.shape}"
        )
    if len(Mk) < 6:
        raise CalibrationError(f"6-DOF calibration needs at least 6 known loads, got {len(Mk)}")
    sm = np.linalg.svd(Mk, compute_uv=False)
    if sm[-1] <= 1e-9 * sm[0]:
        raise CalibrationError(
            f"rank-deficient excitation: the known loads span {int((sm > 1e-9 * sm[0]).sum())} of 6"
            " load dimensions; add loads with different torque/force ratios"
        )
    # unwhitened: the complement N below assumes the minimum-norm C_u, whose rows span the
    # force subspace of the readings (a noise-weighted left inverse's rows do not)
    stage = (fit_bias(data.source, 3, method=method, whiten=False) if bias
             else fit_sfm(data.source, 3))
    C_u, z0 = stage.C, stage.offset
    # orthonormal complement N of the force subspace W = rowspace(C_u)
    Qf, _ = np.linalg.qr(np.column_stack([C_u.T, np.eye(p)]))
    N = Qf[:, 3:p]
    zk = Zk - z0
    Uk = zk @ C_u.T
    Nk = zk @ N
    # the loads excite a 6-dimensional measurement space: W plus 3 more directions, so the
    # complement coordinates of the known readings have rank 3; truncating to it keeps noise (and
    # round-off) in the other p-6 directions from being inverted
    Un, sn, Vnt = np.linalg.svd(Nk, full_matrices=False)
    keep = min(3, int((sn > 1e-12 * max(sn[0], 1e-300)).sum()))
    Nk_pinv = (Vnt[:keep].T / sn[:keep]) @ Un[:, :keep].T
    # unstructured start: Mk = Uk H^T + Nk Y^T
    X = np.hstack([Uk, Nk])
    coef, *_ = np.linalg.lstsq(X, Mk, rcond=None)
    H0 = coef[:3].T
    Uf, sv, Vt = np.linalg.svd(H0[:3])
    R0 = Uf @ Vt
    if np.linalg.det(R0) < 0:  # the unit frame may be mirrored; absorb it into C_u
        C_u = -C_u
        Uk = -Uk
        H0 = -H0
        Uf, sv, Vt = np.linalg.svd(H0[:3])
        R0 = Uf @ Vt
    s0 = float(sv.mean())
    r0 = _vee(H0[3:] @ np.linalg.inv(H0[:3]))
    theta0 = np.concatenate([Rotation.from_matrix(R0).as_rotvec(), [np.log(s0)], r0])
    known_arm = None if lever_arm is None else np.asarray(lever_arm, float)
    if known_arm is not None:
        theta0 = theta0[:4]

    def residuals(theta):
        H = _structured_H(theta, known_arm)
        E = Mk - Uk @ H.T
        Yt = Nk_pinv @ E
        return (E - Nk @ Yt).ravel()

    sol = least_squares(residuals, theta0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    H = _structured_H(sol.x, known_arm)
    Yt = Nk_pinv @ (Mk - Uk @ H.T)
    C = H @ C_u + Yt.T @ N.T
    res = Mk - zk @ C.T
    arm = known_arm if known_arm is not None else sol.x[4:7]
    diag = {
        "force_stage": stage.diagnostics,
        "n_samples": data.n,
        "n_dropped_nonfinite": nbad,
        "n_known": len(Mk),
        "lever_arm": arm,
        "scale": float(np.exp(sol.x[3])),
        "known_residual_rms": float(np.sqrt(np.mean(res**2))),
        "condition_number_C": float(np.linalg.cond(C)),
        "singular_values": stage.diagnostics.get("singular_values"),
        "rank_gap": stage.diagnostics.get("rank_gap"),
        "coverage": stage.diagnostics.get("coverage"),
    }
    return Calibration(C=C, offset=z0, dof=6, method="ft6-sfm", diagnostics=diag)


def random_known_loads(k: int, rng, force: float = 1.0, torque: float = 0.1) -> np.ndarray:
    """k random 6-D loads (k, 6): forces of size ~force, torques ~torque, spanning all 6
    dimensions."""
    rng = np.random.default_rng(rng)
    M = rng.normal(size=(k, 6))
    M[:, :3] *= force
    M[:, 3:] *= torque
    return M
