"""Bootstrap percentile intervals for the offset and C of any fitting route.

Rows are resampled with replacement (seeded), the same fit is run on every resample, and the
2.5th / 97.5th percentiles (for ``level=0.95``) of each offset entry and each entry of C are
reported. Without known pairs C lives in a canonical frame that a resample may turn (the
principal axes move), so each replicate's C is first rotated onto the original by orthogonal
Procrustes (``align=True``); with known pairs the frame is part of the estimate and is left alone.
"""

from __future__ import annotations

import warnings

import numpy as np

from calib.data.result import Calibration, CalibrationError, CalibrationWarning


def _rotate_onto(C: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """R C with R in O(r) minimising |R C - ref| (scipy's orthogonal Procrustes on the
    transposes: C^T R^T ~ ref^T)."""
    from scipy.linalg import orthogonal_procrustes

    Rt, _ = orthogonal_procrustes(C.T, ref.T)
    return Rt.T @ C


def bootstrap_intervals(
    fit,
    Z: np.ndarray,
    cal: Calibration,
    n_boot: int,
    seed: int = 0,
    level: float = 0.95,
    align: bool = True,
    progress=None,
) -> dict:
    """Percentile intervals from ``n_boot`` refits ``fit(Z[idx])`` on resampled rows.

    Parameters
    ----------
    fit : callable taking an (n, p) array and returning a Calibration
    Z : the (n, p) data ``cal`` was fitted to
    cal : the point estimate (its C is the reference frame when ``align``)
    n_boot : number of resamples (>= 2)
    progress : optional object with ``update()`` called once per resample

    Returns a dict for ``diagnostics["bootstrap"]``: ``n_boot``, ``seed``, ``level``,
    ``offset_low``/``offset_high`` (p,), ``C_low``/``C_high`` (dof, p), ``n_failed`` (resamples
    whose fit raised CalibrationError; they are left out).
    """
    if int(n_boot) < 2:
        raise CalibrationError(f"bootstrap needs at least 2 resamples, got {n_boot}")
    if not 0 < level < 1:
        raise CalibrationError(f"level must be in (0, 1), got {level}")
    Z = np.asarray(Z, float)
    rng = np.random.default_rng(seed)
    n = len(Z)
    offs, Cs = [], []
    failed = 0
    for _ in range(int(n_boot)):
        idx = rng.integers(0, n, n)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", CalibrationWarning)
                b = fit(Z[idx])
        except CalibrationError:
            failed += 1
        else:
            offs.append(b.offset)
            Cs.append(_rotate_onto(b.C, cal.C) if align else b.C)
        if progress is not None:
            progress.update()
    if len(offs) < 2:
        raise CalibrationError(f"bootstrap: {failed} of {n_boot} resamples could not be fitted")
    q = [50 * (1 - level), 50 * (1 + level)]
    lo_o, hi_o = np.percentile(np.asarray(offs), q, axis=0)
    lo_C, hi_C = np.percentile(np.asarray(Cs), q, axis=0)
    return {
        "n_boot": int(n_boot),
        "seed": int(seed),
        "level": float(level),
        "offset_low": lo_o,
        "offset_high": hi_o,
        "C_low": lo_C,
        "C_high": hi_C,
        "n_failed": failed,
    }
