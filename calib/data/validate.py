"""Input checks shared by every fitting routine; each failure is a one-line CalibrationError."""

from __future__ import annotations

import numpy as np

from calib.data.result import CalibrationError


def check_dof(dof: int) -> int:
    if dof not in (2, 3, 6):
        raise CalibrationError(f"dof must be 2, 3 or 6, got {dof!r}")
    return int(dof)


def force_rank(dof: int) -> int:
    """Rank r of the motion matrix: dimension of the force vector (2 planar, 3 spatial, 3 for
    6-DOF)."""
    return 2 if dof == 2 else 3


def check_matrix(Z, name: str = "Z", drop_nonfinite: bool = False) -> tuple[np.ndarray, int]:
    """Return (float 2-D array, number of rows dropped). NaN/inf rows are an error unless opted
    out."""
    Z = np.asarray(Z, dtype=float)
    if Z.ndim != 2:
        raise CalibrationError(f"{name} must be 2-D (n_samples, n_channels), got shape {Z.shape}")
    bad = ~np.isfinite(Z).all(axis=1)
    nbad = int(bad.sum())
    if nbad:
        if not drop_nonfinite:
            first = int(np.flatnonzero(bad)[0])
            raise CalibrationError(
                f"{name} has {nbad} row(s) with NaN/inf (first at row {first}); "
                "clean the data or opt in to dropping them (--drop-nonfinite)"
            )
        Z = Z[~bad]
    big = float(np.max(np.abs(Z))) if Z.size else 0.0
    if big > 1e150:
        raise CalibrationError(f"{name} has values of magnitude {big:.3g}: beyond what a fit in "
                               "double precision can square; rescale the readings")
    nonzero = np.abs(Z[Z != 0])
    if nonzero.size and float(nonzero.max()) < 1e-150:
        raise CalibrationError(f"{name} has no value above {float(nonzero.max()):.3g} in "
                               "magnitude: too small to fit in double precision; rescale")
    return Z, nbad


def check_samples(n: int, p: int, lo: np.ndarray, hi: np.ndarray, n_params: int,
                  name: str = "Z", rows_per_channel: bool = True) -> None:
    """Too few samples (fewer than ``n_params``, or with ``rows_per_channel`` fewer than
    channels), or constant channels; from the row count and per-channel minima ``lo`` and
    maxima ``hi`` (a streamed scan gives these without the rows)."""
    if rows_per_channel and n < p:
        raise CalibrationError(
            f"{name} has {n} samples for {p} channels: a calibration needs at least as many "
            "samples as channels")
    if n < n_params:
        raise CalibrationError(
            f"{name} has {n} samples, at least {n_params} are needed for this fit"
        )
    spread = hi - lo
    scale = np.maximum(np.maximum(np.abs(hi), np.abs(lo)), 1e-300)
    const = np.flatnonzero(spread <= 1e-12 * scale)
    if len(const):
        raise CalibrationError(
            f"{name} channel(s) {const.tolist()} are constant; a dead or disconnected sense "
            "element cannot be calibrated"
        )


def check_rank(singular_values: np.ndarray, r: int, what: str, rel_tol: float = 1e-9) -> None:
    """Rank-deficient excitation: the r-th singular value must stand clear of zero."""
    s = np.asarray(singular_values)
    if len(s) < r or s[r - 1] <= rel_tol * max(s[0], 1e-300):
        have = int((s > rel_tol * max(s[0], 1e-300)).sum())
        raise CalibrationError(
            f"rank-deficient excitation: {what} has rank {have}, needs {r}; move the load through "
            "more directions"
        )
