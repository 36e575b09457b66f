"""Real 3-axis data (p = r = 3): magnetometer and accelerometer calibration with the centered route.

The paper's rank r+1 method cannot handle p = r, so these use
:func:`calib.estimators.bias.fit_centered` (ellipsoid fit, approximate maximum likelihood). Two
physical checks need no ground truth:

- the calibrated magnitude is constant (coefficient of variation, :func:`magnitude_cv`);
- for a rigid device carrying both sensors, the angle between the calibrated magnetic and gravity
  vectors (the magnetic dip) is the same in every shot (:func:`dip_analysis`). Each calibration is
  known only up to a rotation (the symmetric, rotation-free factor is returned), so the two
  calibrated frames are first aligned: the rotation R and dip delta minimising
  ``sum_i (g_i . R m_i - cos delta)^2`` over unit vectors (4 parameters, ``least_squares``).
"""

from __future__ import annotations

import json
import warnings

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calib.data.result import Calibration, CalibrationError, CalibrationWarning
from calib.estimators.bias import fit_centered


def load_furbrain(path) -> tuple[np.ndarray, np.ndarray]:
    """``shots.mag`` and ``shots.grav`` of a furbrain cal_data JSON file as (n, 3) arrays.

    The files hold flat float lists padded with NaN (and not a multiple of 3 long); the leading
    finite triples are the shots, same device orientation per index.
    """
    from calib.data.io import open_regular

    with open_regular(path, encoding="utf-8") as f:
        d = json.load(f)
    try:
        shots = d["shots"]
        mag, grav = (np.asarray(shots[k], float) for k in ("mag", "grav"))
    except (KeyError, TypeError):
        raise CalibrationError(f"{path}: no shots.mag / shots.grav lists") from None
    out = []
    for v in (mag, grav):
        v = v.ravel()
        v = v[: 3 * (len(v) // 3)].reshape(-1, 3)
        out.append(v)
    ok = np.isfinite(out[0]).all(axis=1) & np.isfinite(out[1]).all(axis=1)
    return out[0][ok], out[1][ok]


def load_xyz(path) -> np.ndarray:
    """Whitespace-separated ``x y z`` rows (bazhin/mag_out.txt) as (n, 3)."""
    from calib.data.io import open_regular

    with open_regular(path, encoding="utf-8") as f:
        return np.loadtxt(f, ndmin=2)[:, :3]


def calibrate_vector_sensor(V: np.ndarray, quiet: bool = True) -> Calibration:
    """Offset + 3 x 3 calibration of a constant-magnitude 3-axis sensor, V of shape (n, 3).

    The result maps to unit magnitude in a rotation-free (symmetric) frame.
    """
    with warnings.catch_warnings():
        if quiet:
            warnings.simplefilter("ignore", CalibrationWarning)
        return fit_centered(V, dof=3)


def magnitude_cv(V: np.ndarray, cal: Calibration | None = None) -> float:
    """Coefficient of variation (std / mean) of |v| (raw) or |C (v - offset)| (calibrated)."""
    X = V if cal is None else cal.apply(V)
    m = np.linalg.norm(X, axis=1)
    return float(m.std() / m.mean())


def _angles_deg(a, b):
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1, 1)))


def align_frames(m_unit: np.ndarray, g_unit: np.ndarray) -> tuple[np.ndarray, float]:
    """Rotation R (3, 3) and dip (deg) with ``g_i . R m_i ~= cos(dip)`` for unit rows (n, 3)."""
    c0 = float(np.mean(np.sum(m_unit * g_unit, axis=1)))

    def res(x):
        R = Rotation.from_rotvec(x[:3]).as_matrix()
        return np.sum(g_unit * (m_unit @ R.T), axis=1) - x[3]

    sol = least_squares(res, np.array([0.0, 0.0, 0.0, c0]), method="lm")
    R = Rotation.from_rotvec(sol.x[:3]).as_matrix()
    return R, float(np.degrees(np.arccos(np.clip(sol.x[3], -1, 1))))


def dip_analysis(mag: np.ndarray, grav: np.ndarray) -> dict:
    """Calibrate both sensors, align their frames, and report magnitude CVs and dip statistics.

    Parameters
    ----------
    mag, grav : arrays (n, 3) of raw readings, same device orientation per row

    Returns
    -------
    dict with ``raw_cv_mag``, ``raw_cv_grav``, ``cv_mag``, ``cv_grav`` (calibrated),
    ``dip_std_unaligned_deg`` (identity between the two rotation-free frames),
    ``dip_std_deg`` and ``dip_deg`` (after alignment), ``alignment_angle_deg``, ``n``.
    """
    cm = calibrate_vector_sensor(mag)
    cg = calibrate_vector_sensor(grav)
    mu, gu = cm.apply(mag), cg.apply(grav)
    mu = mu / np.linalg.norm(mu, axis=1, keepdims=True)
    gu = gu / np.linalg.norm(gu, axis=1, keepdims=True)
    R, dip = align_frames(mu, gu)
    aligned = _angles_deg(mu @ R.T, gu)
    return {
        "n": len(mag),
        "raw_cv_mag": magnitude_cv(mag),
        "raw_cv_grav": magnitude_cv(grav),
        "cv_mag": magnitude_cv(mag, cm),
        "cv_grav": magnitude_cv(grav, cg),
        "dip_std_unaligned_deg": float(np.std(_angles_deg(mu, gu))),
        "dip_std_deg": float(np.std(aligned)),
        "dip_deg": dip,
        "alignment_angle_deg": float(np.degrees(Rotation.from_matrix(R).magnitude())),
        "mag_excitation_poor": cm.diagnostics["excitation_poor"],
        "grav_excitation_poor": cg.diagnostics["excitation_poor"],
    }


def leave_one_out_cv(V: np.ndarray) -> float:
    """Magnitude CV of held-out shots: each row calibrated by a fit to all the other rows.

    An honest (out-of-sample) counterpart of :func:`magnitude_cv`, which with 24 shots and 9
    parameters is optimistic.
    """
    mags = []
    for i in range(len(V)):
        cal = calibrate_vector_sensor(np.delete(V, i, axis=0))
        mags.append(np.linalg.norm(cal.apply(V[i])))
    mags = np.asarray(mags)
    return float(mags.std() / mags.mean())
