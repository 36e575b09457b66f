"""Least-squares calibration with known loads, paper eqs. (2)-(3): ``C^T = Z^+ M``.

With ``bias=True`` a column of ones is appended, ``[Z 1] [C^T; d^T] = M``, so the fit also absorbs a
constant load offset ``d`` (solved by centring, which keeps C in the data's row space). When p >
dof only ``C z0`` is identifiable from known loads, so the
reported channel offset is the minimum-norm ``z0 = -C^+ d`` (it reproduces the loads exactly).
"""

from __future__ import annotations

import numpy as np

from ._validate import check_dof, check_matrix, check_samples
from .result import Calibration, CalibrationError


def fit_least_squares(Z, M, bias: bool = False, drop_nonfinite: bool = False) -> Calibration:
    """Calibrate from known (z, m) pairs.

    Parameters
    ----------
    Z : array of shape (n, p), raw readings
    M : array of shape (n, dof), the known applied loads, dof in {2, 3, 6}
    bias : also fit a constant offset

    Returns
    -------
    Calibration with ``method="least_squares"``; diagnostics: ``singular_values`` of the design,
    ``condition_number``, ``residual_rms`` (load units), ``n_samples``.
    """
    Z = np.asarray(Z, float)
    M = np.atleast_2d(np.asarray(M, float))
    if M.shape[0] != Z.shape[0]:
        raise CalibrationError(f"Z has {Z.shape[0]} rows but the known loads have {M.shape[0]}")
    both, nbad = check_matrix(np.hstack([Z, M]), "known data", drop_nonfinite)
    Z, M = both[:, : Z.shape[1]], both[:, Z.shape[1] :]
    dof = check_dof(M.shape[1])
    n, p = Z.shape
    need = dof + (1 if bias else 0)
    if n < need:
        raise CalibrationError(
            f"least squares needs at least {need} known loads for dof={dof}, got {n}"
        )
    check_samples(Z, need, "known data", rows_per_channel=False)
    X = np.hstack([Z, np.ones((n, 1))]) if bias else Z
    s = np.linalg.svd(X, compute_uv=False)
    # the loads must span dof dimensions, else C is not determined in the missing directions
    sm = np.linalg.svd(M, compute_uv=False)
    if sm[-1] <= 1e-9 * sm[0]:
        raise CalibrationError(
            f"rank-deficient excitation: the known loads span {int((sm > 1e-9 * sm[0]).sum())} of "
            f"{dof} load dimensions"
        )
    if bias:
        # centring keeps C in the row space of the data (the min-norm [C, d] would not)
        zm, mm = Z.mean(axis=0), M.mean(axis=0)
        Ct, *_ = np.linalg.lstsq(Z - zm, M - mm, rcond=None)
        C = Ct.T
        d = mm - C @ zm
        offset = -np.linalg.pinv(C) @ d
    else:
        Ct, *_ = np.linalg.lstsq(Z, M, rcond=None)
        C = Ct.T
        offset = np.zeros(p)
    res = M - (Z - offset) @ C.T
    diag = {
        "n_samples": n,
        "n_dropped_nonfinite": nbad,
        "singular_values": s,
        "condition_number": float(s[0] / s[-1]) if s[-1] > 0 else float("inf"),
        "residual_rms": float(np.sqrt(np.mean(res**2))),
    }
    return Calibration(C=C, offset=offset, dof=dof, method="least_squares", diagnostics=diag)
