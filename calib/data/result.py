"""The calibration result, its warning and error types, and the diagnostics every fit reports.

A calibration maps raw sense-element readings ``z`` (p channels) to loads ``m`` (dof components):
``m = C (z - offset)``, i.e. for a batch ``M = (Z - offset) @ C.T``.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field

import numpy as np


class CalibrationError(ValueError):
    """Bad input to a calibration routine; the message is one line and names the bad value."""


class CalibrationWarning(UserWarning):
    """The fit succeeded but its result is unreliable (poor excitation, hyperboloid, mirror
    ambiguity)."""


def warn(message: str) -> None:
    """Emit a :class:`CalibrationWarning` attributed to the caller of the public function."""
    warnings.warn(message, CalibrationWarning, stacklevel=3)


@dataclass
class Calibration:
    """A fitted calibration.

    Attributes
    ----------
    C : ndarray of shape (dof, p)
        Calibration matrix, eq. (1) of the paper: ``m = C z``.
    offset : ndarray of shape (p,)
        Sensor bias ``z0`` subtracted from every raw sample before applying ``C``.
    dof : int
        Number of load components (2, 3 or 6).
    method : str
        Which estimator produced it (``"least_squares"``, ``"sfm"``, ``"paper"``, ``"centered"``,
        ...).
    diagnostics : dict
        JSON-serialisable numbers: singular values, rank gap, excitation coverage, condition
        numbers,
        residuals. See :func:`coverage_diagnostics` and the fitting functions for the keys.
    """

    C: np.ndarray
    offset: np.ndarray
    dof: int
    method: str = "unknown"
    diagnostics: dict = field(default_factory=dict)
    #: Optional quadratic channel terms (``--model quadratic``): Q (dof, p), and the centre and
    #: scale (p,) of the channels they square: ``m = C (z - offset) + Q ((z - centre) / scale)^2``.
    quadratic: np.ndarray | None = None
    quadratic_center: np.ndarray | None = None
    quadratic_scale: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.C = np.atleast_2d(np.asarray(self.C, dtype=float))
        self.offset = np.asarray(self.offset, dtype=float).reshape(-1)
        if self.C.shape[1] != self.offset.shape[0]:
            raise CalibrationError(
                f"C has {self.C.shape[1]} columns but offset has {self.offset.shape[0]} entries"
            )
        self.dof = int(self.dof)
        if self.quadratic is not None:
            self.quadratic = np.atleast_2d(np.asarray(self.quadratic, dtype=float))
            self.quadratic_center = np.asarray(self.quadratic_center, float).reshape(-1)
            self.quadratic_scale = np.asarray(self.quadratic_scale, float).reshape(-1)
            p = self.C.shape[1]
            if (self.quadratic.shape != self.C.shape or self.quadratic_center.shape != (p,)
                    or self.quadratic_scale.shape != (p,) or np.any(self.quadratic_scale <= 0)):
                raise CalibrationError(
                    f"quadratic terms must be a {self.C.shape} matrix with {p} centres and "
                    f"{p} positive scales")

    @property
    def n_channels(self) -> int:
        """Number of raw sense elements p."""
        return self.C.shape[1]

    def apply(self, Z: np.ndarray) -> np.ndarray:
        """Loads from raw readings.

        Parameters
        ----------
        Z : ndarray of shape (n_samples, p) or (p,)

        Returns
        -------
        ndarray of shape (n_samples, dof) or (dof,)
        """
        Z = np.asarray(Z, dtype=float)
        if Z.shape[-1] != self.n_channels:
            raise CalibrationError(
                f"data has {Z.shape[-1]} channels, calibration expects {self.n_channels}"
            )
        out = (Z - self.offset) @ self.C.T
        if self.quadratic is not None:
            out = out + ((Z - self.quadratic_center) / self.quadratic_scale) ** 2 @ (
                self.quadratic.T)
        return out

    def to_dict(self) -> dict:
        d = {
            "C": self.C.tolist(),
            "offset": self.offset.tolist(),
            "dof": self.dof,
            "method": self.method,
        }
        if self.quadratic is not None:
            d.update(quadratic=self.quadratic.tolist(),
                     quadratic_center=self.quadratic_center.tolist(),
                     quadratic_scale=self.quadratic_scale.tolist())
        d["diagnostics"] = _jsonable(self.diagnostics)
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_dict(cls, d: dict) -> Calibration:
        """A calibration from its JSON form, validated: ``dof`` 2, 3 or 6; ``C`` a finite
        (dof, p) matrix; ``offset`` p finite numbers; ``diagnostics`` an object. Anything else is
        a one-line :class:`CalibrationError` (a CAL.json is data from elsewhere: check it)."""
        if not isinstance(d, dict):
            raise CalibrationError("a calibration must be a JSON object")
        missing = [k for k in ("C", "offset", "dof") if k not in d]
        if missing:
            raise CalibrationError(f"calibration file lacks key(s) {missing}")
        dof = d["dof"]
        if isinstance(dof, bool) or not isinstance(dof, int) or dof not in (2, 3, 6):
            raise CalibrationError(f"dof must be 2, 3 or 6, got {dof!r}")
        C = _finite_array(d["C"], "C", ndim=2)
        offset = _finite_array(d["offset"], "offset", ndim=1)
        if C.shape[0] != dof:
            raise CalibrationError(f"C has {C.shape[0]} rows but dof is {dof}")
        diagnostics = d.get("diagnostics", {})
        if not isinstance(diagnostics, dict):
            raise CalibrationError("diagnostics must be a JSON object")
        quad = {}
        keys = ("quadratic", "quadratic_center", "quadratic_scale")
        if any(k in d for k in keys):
            if not all(k in d for k in keys):
                raise CalibrationError(f"quadratic terms need all of {list(keys)}")
            quad = {"quadratic": _finite_array(d["quadratic"], "quadratic", ndim=2),
                    "quadratic_center": _finite_array(d["quadratic_center"], "quadratic_center",
                                                      ndim=1),
                    "quadratic_scale": _finite_array(d["quadratic_scale"], "quadratic_scale",
                                                     ndim=1)}
        return cls(C=C, offset=offset, dof=dof, method=str(d.get("method", "unknown")),
                   diagnostics=dict(diagnostics), **quad)


def _finite_array(value, name: str, ndim: int) -> np.ndarray:
    """``value`` as a finite float array of ``ndim`` dimensions, or a one-line error."""
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise CalibrationError(f"{name} must be {'a matrix' if ndim == 2 else 'a list'} of "
                               "numbers") from None
    if a.ndim != ndim or a.size == 0:
        raise CalibrationError(f"{name} must be a {ndim}-D array of numbers, got shape "
                               f"{a.shape}")
    if not np.all(np.isfinite(a)):
        raise CalibrationError(f"{name} contains NaN, infinite or missing values")
    return a


def _jsonable(x):
    """Recursively convert numpy scalars/arrays to plain Python for json.dumps."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.bool_,)):
        return bool(x)
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, (float, np.floating)):
        v = float(x)
        return v if np.isfinite(v) else None
    return x


# ----------------------------------------------------------------------------------- diagnostics

# : Below this coverage isotropy (smallest eigenvalue of r * mean(u u^T); 1 = uniform sphere), or
# with
#: the force directions inside a cap narrower than COVERAGE_MIN_CAP_DEG, offsets are unreliable.
#: Decision: docs/calib_design.md D18.
COVERAGE_MIN_ISOTROPY = 0.35
#: Decision: docs/calib_design.md D18.
COVERAGE_MIN_CAP_DEG = 100.0
#: Coverage statistics use at most this many (evenly strided) samples.
#: Decision: docs/calib_design.md D18.
COVERAGE_MAX_ROWS = 100_000


def coverage_diagnostics(U: np.ndarray) -> dict:
    """How well the load directions excite the measurement space.

    Parameters
    ----------
    U : ndarray of shape (n_samples, r)
        Load vectors in any orthonormal frame (magnitude is ignored).

    Returns
    -------
    dict with
        ``isotropy``: smallest eigenvalue of ``r * mean(u u^T)`` for unit ``u`` (1 for uniform
        cover,
        0 when all directions lie in a plane);
        ``mean_direction_norm``: ``|mean(u)|`` (0 for a full sphere, 1 for a single direction);
        ``cap_half_angle_deg``: largest angle between a direction and the mean direction;
        ``covered_fraction``: fraction of equal cells of the sphere (r=3: the 20 faces of an
        icosahedron) or circle (r=2: 12 arcs) that contain at least one direction.
    """
    U = np.asarray(U, dtype=float)
    if len(U) > COVERAGE_MAX_ROWS:  # direction statistics: an evenly strided subsample suffices
        U = U[:: int(np.ceil(len(U) / COVERAGE_MAX_ROWS))]
    r = U.shape[1]
    norms = np.sqrt(np.einsum("ij,ij->i", U, U))
    good = norms > 0
    u = (U / norms[:, None]) if good.all() else U[good] / norms[good, None]
    if len(u) == 0:
        return {
            "isotropy": 0.0,
            "mean_direction_norm": 1.0,
            "cap_half_angle_deg": 0.0,
            "covered_fraction": 0.0,
        }
    second = r * (u.T @ u) / len(u)
    iso = float(np.linalg.eigvalsh(second)[0])
    mean = u.mean(axis=0)
    mnorm = float(np.linalg.norm(mean))
    if mnorm > 1e-12:
        ang = np.degrees(np.arccos(np.clip(u @ (mean / mnorm), -1, 1)))
        cap = float(ang.max())
    else:
        cap = 180.0
    cells = _cell_centres(r)
    if cells is not None:
        hit = np.zeros(len(cells), dtype=bool)
        for i in range(0, len(u), 1 << 16):
            hit[np.argmax(u[i : i + (1 << 16)] @ cells.T, axis=1)] = True
        frac = hit.sum() / len(cells)
    else:
        frac = float("nan")
    return {
        "isotropy": iso,
        "mean_direction_norm": mnorm,
        "cap_half_angle_deg": cap,
        "covered_fraction": float(frac),
    }


def _cell_centres(r: int) -> np.ndarray | None:
    if r == 2:
        a = 2 * np.pi * (np.arange(12) + 0.5) / 12
        return np.column_stack([np.cos(a), np.sin(a)])
    if r == 3:
        # face centres of an icosahedron = vertices of a dodecahedron: 20 equal-area cells
        phi = (1 + 5**0.5) / 2
        v = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
        for a in (-1, 1):
            for b in (-1, 1):
                v += [(0, a / phi, b * phi), (a / phi, b * phi, 0), (a * phi, 0, b / phi)]
        v = np.asarray(v, dtype=float)
        return v / np.linalg.norm(v, axis=1, keepdims=True)
    return None


#: The mean unit direction of a cap of half-angle theta, uniform in area, has norm
#: ``(1 + cos theta) / 2``: above this value (a cap of COVERAGE_MIN_CAP_DEG) coverage is poor too.
#: Unlike the largest angle it is an average, so a few noisy directions do not hide a cap.
#: Decision: docs/calib_design.md D18.
COVERAGE_MAX_MEAN_NORM = (1 + float(np.cos(np.radians(COVERAGE_MIN_CAP_DEG)))) / 2


def excitation_is_poor(cov: dict) -> bool:
    """True when the coverage is too poor for a reliable offset (see module constants)."""
    return (
        (cov["isotropy"] < COVERAGE_MIN_ISOTROPY)
        or (cov["cap_half_angle_deg"] < COVERAGE_MIN_CAP_DEG)
        or (cov.get("mean_direction_norm", 0.0) > COVERAGE_MAX_MEAN_NORM)
    )


#: A CalibrationWarning is raised when an offset standard error exceeds this fraction of its
#: channel's span (range of the data in that channel).
#: Decision: docs/calib_design.md D64.
OFFSET_STDERR_MAX_FRACTION = 0.05


def channel_span(Z: np.ndarray) -> np.ndarray:
    """Range (max - min) of every channel of Z (n, p), shape (p,)."""
    return np.asarray(Z.max(axis=0) - Z.min(axis=0), dtype=float)


def propagate(fn, x: np.ndarray, cov: np.ndarray, p: int) -> tuple[np.ndarray, np.ndarray]:
    """Standard errors of ``offset, C = fn(x)`` for parameters x with covariance ``cov``.

    First-order (delta method): central differences of fn along the eigenvectors of cov, each
    a fraction of its standard deviation, so a locally linear fn gives the exact propagation.
    Returns (offset_stderr (p,), C_stderr like C); infinite if cov is not finite.
    """
    off0, C0 = fn(x)
    if not np.all(np.isfinite(cov)):
        return np.full(p, np.inf), np.full(C0.shape, np.inf)
    w, V = np.linalg.eigh((cov + cov.T) / 2)
    w = np.clip(w, 0, None)
    var = np.zeros(p + C0.size)
    for k in range(len(w)):
        sd = np.sqrt(w[k])
        if sd == 0:
            continue
        h = 1e-3 * sd
        a = fn(x + h * V[:, k])
        b = fn(x - h * V[:, k])
        g = np.r_[a[0] - b[0], (a[1] - b[1]).ravel()] / (2 * h) * sd
        var += g**2
    se = np.sqrt(var)
    return se[:p], se[p:].reshape(C0.shape)


def add_uncertainty(cal, offset_se: np.ndarray, C_se: np.ndarray, span: np.ndarray,
                    offset_cov: np.ndarray | None = None,
                    load_span: np.ndarray | None = None) -> None:
    """Store standard errors in ``cal.diagnostics`` and warn when the offset is not identified.

    Keys: ``offset_stderr`` (p,), ``C_stderr`` (dof, p), ``span`` (p,), ``offset_stderr_rel_span``
    (p,) and its max ``offset_stderr_max_rel_span``; ``offset_identified`` is False (and a
    CalibrationWarning raised) when any channel's offset standard error exceeds
    :data:`OFFSET_STDERR_MAX_FRACTION` of that channel's span.

    Channels whose offset barely reaches the loads (with ``offset_cov``, the offset's
    covariance (p, p), and ``load_span``, the range of the calibrated loads over the data
    (dof,)): the rule above judges an offset against its channel's span, which is the load's
    reach for a channel that carries the load, but only noise for a channel that reads no load
    or a load weaker than its noise. What matters is the loads: channel c's offset error moves
    them by ``|C[:, c]| offset_stderr[c]`` (``offset_stderr_reach_load_span``, the largest over
    the load axes as a fraction of their span). A channel that fails the rule but whose reach
    stays within ``OFFSET_STDERR_MAX_FRACTION / sqrt(p)`` (so that p such channels with
    independent errors stay within the limit together) is left out of the rule
    (``offset_rule_channels``: (p,) bool), only where the whole offset's error carried into the
    loads (``C offset_cov C^T``, correlations included) stays within the limit on every axis
    (``offset_stderr_rel_load_span``) and some channel passes the rule: a fit that is lost has
    every channel uncertain, and is judged by every channel as before. Why: a 6-axis sensor
    holding a gripper whose centre of mass lies on the tool axis has ``T_z = 0`` in every pose,
    or a load on it weaker than its noise; on such simulated wrist rigs the fits measured
    0.94-1.33x least squares with every load known, as the oracle, and were refused at 5-8 % of
    that channel's span (``tests/calib/test_signal_free_channel.py``).
    """
    rel = offset_se / np.maximum(span, 1e-300)
    use = np.ones(len(rel), bool)
    rel_load = reach = None
    C = np.asarray(cal.C, float)
    C_se = np.asarray(C_se, float)
    p = len(rel)
    if (offset_cov is not None and load_span is not None and C.ndim == 2
            and p == C.shape[1] and p > C.shape[0]):
        lsp = np.maximum(np.asarray(load_span, float), 1e-300)
        with np.errstate(over="ignore", invalid="ignore"):
            reach = np.max(np.abs(C) * np.asarray(offset_se, float)[None, :] / lsp[:, None],
                           axis=0)
            S = C @ np.asarray(offset_cov, float) @ C.T
            rel_load = np.sqrt(np.clip(np.diag(S), 0, None)) / lsp
        fail = ~(rel <= OFFSET_STDERR_MAX_FRACTION)
        negligible = fail & (reach <= OFFSET_STDERR_MAX_FRACTION / np.sqrt(p))
        if (negligible.any() and not fail.all() and np.all(np.isfinite(rel_load))
                and float(np.max(rel_load)) <= OFFSET_STDERR_MAX_FRACTION):
            use = ~negligible
    worst = float(np.max(rel[use])) if len(rel) else 0.0
    ok = bool(worst <= OFFSET_STDERR_MAX_FRACTION)
    cal.diagnostics.update(
        {
            "offset_stderr": offset_se,
            "C_stderr": C_se,
            "span": span,
            "offset_stderr_rel_span": rel,
            "offset_stderr_max_rel_span": worst,
            "offset_rule_channels": use,
            "offset_stderr_rel_load_span": rel_load,
            "offset_stderr_reach_load_span": reach,
            "offset_identified": ok,
        }
    )
    if not ok:
        ch = int(np.argmax(np.where(use, rel, -np.inf)))
        warn(
            f"the offset is not identified: its standard error reaches {worst:.1%} of the data's "
            f"span (channel {ch}), above {OFFSET_STDERR_MAX_FRACTION:.0%}; move the load "
            "through more directions"
        )


def magnitude_stats(loads: np.ndarray) -> dict:
    """Mean, std and coefficient of variation of the load magnitude, shape (n, dof) -> dict."""
    mag = np.linalg.norm(np.asarray(loads)[:, :3], axis=1)
    mean = float(mag.mean())
    std = float(mag.std())
    return {
        "magnitude_mean": mean,
        "magnitude_std": std,
        "magnitude_cv": std / mean if mean > 0 else float("nan"),
    }
