"""Channels that are an exact affine copy of another channel of the same log.

A log can hold one reading twice: the same channel logged in two units (counts and volts), or
copied into a second column by the logging software. A copy adds nothing about the load, and
its noise is its original's, so a fit that weighs the channels as independent counts that noise
twice. Measured (stop 65) on the payload study's default case (seeds 10,000-10,005, channel 0
copied as ``2 z_0 + 5``), the held-out error over least squares with every load known went from
0.85-1.10x to 1.01-1.45x for the joint fit and from 1.07-2.24x to 1.17-5.34x for the centered
route; least squares (every load known) does not change. So :func:`calib.joint.fit_joint` and
:func:`calib.bias.fit_bias` fit the log without its copies and give each copy a column of zeros
in ``C`` (:func:`expand`): the loads are then those of the log without the copy, and the copy's
offset is its original's, mapped by the same affine relation. So does
:func:`calib.least_squares.fit_least_squares` with a bias (in-memory arrays), for a reason of
its own: its centred columns then differ only by the rounding of the copy's shift, which its
solve's cut-off keeps (a copy shifted by 843 standard deviations put 1e6 into ``C``, stop 66).

"Exact": the affine regression of a channel on an earlier channel leaves at most
:data:`COPY_TOLERANCE` of its variance. Distinct channels leave far more: at least 3.7e-4 over
every pair of every case of the payload study (10 rigs a case, the wrench channels' torques
included, which follow their forces closely) and of :func:`calib.simulate.simulate_rig`, 2.5e-3
on the real printed sensor's sets and 5.3e-2 on the real wrist sensor. A copy written with few
significant digits, or one read through a second amplifier with noise of its own, leaves more
than the tolerance and is fitted as a channel of its own, as before (docs/calib.md, "A channel
that repeats another": such a repeat costs 1.1-1.6x).
"""

from __future__ import annotations

import numpy as np

from .result import Calibration, warn

#: Largest share of a channel's variance the affine regression on an earlier channel may leave
#: for it to be that channel's exact copy (module docstring).
COPY_TOLERANCE = 1e-10


def find_copies(Z) -> list[tuple[int, int, float, float]]:
    """``(copy, original, scale, shift)`` for every channel of ``Z`` (n, p) that is an exact
    affine copy of an earlier channel, ``z_copy = scale z_original + shift`` over the rows
    finite in every channel; the original is the first channel it copies (never itself a copy).
    Empty for fewer than 3 finite rows, or values too large to square in double precision."""
    Z = np.asarray(Z, float)
    if Z.ndim != 2 or Z.shape[1] < 2:
        return []
    Z = Z[np.all(np.isfinite(Z), axis=1)]
    if len(Z) < 3:
        return []
    with np.errstate(all="ignore"):
        mu = Z.mean(axis=0)
        Zc = Z - mu
        ss = np.einsum("ij,ij->j", Zc, Zc)
    if not np.all(np.isfinite(ss)):
        return []  # values beyond what double precision squares: the fit's checks refuse them
    found, copied = [], set()
    for d in range(Z.shape[1]):
        if not ss[d] > 0:
            continue
        for c in range(d):
            if c in copied or not ss[c] > 0:
                continue
            with np.errstate(all="ignore"):
                b = float(Zc[:, c] @ Zc[:, d]) / float(ss[c])
                left = Zc[:, d] - b * Zc[:, c]
                rest = float(left @ left)
            if np.isfinite(b) and b != 0 and rest <= COPY_TOLERANCE * float(ss[d]):
                found.append((d, c, b, float(mu[d] - b * mu[c])))
                copied.add(d)
                break
    return found


def expand(cal: Calibration, p: int, copies) -> Calibration:
    """``cal``, fitted on the channels of a p-channel log that are not copies, as a calibration
    of all p: a copy's column of ``C`` (and of its quadratic terms and standard errors) is 0,
    its offset its original's mapped by the copy's affine relation, its offset's standard
    error its original's times ``|scale|``. The channels a per-channel diagnostic of the fit
    names are the kept ones (``diagnostics["channel_copies"]`` lists the copies: ``channel``,
    ``copy_of``, ``scale``, ``shift``); the keys below are set out over all p channels."""
    drop = [d for d, _, _, _ in copies]
    keep = np.array([c for c in range(p) if c not in drop], int)

    def columns(X, fill=0.0):  # (..., len(keep)) -> (..., p): a copy's entry from ``fill``
        X = np.asarray(X)
        out = np.full(X.shape[:-1] + (p,), fill, dtype=X.dtype if X.dtype == bool else float)
        out[..., keep] = X
        return out

    offset = columns(cal.offset)
    for d, c, b, s in copies:
        offset[d] = b * offset[c] + s
    quad = {}
    if cal.quadratic is not None:
        center, scale = columns(cal.quadratic_center), columns(cal.quadratic_scale, 1.0)
        for d, c, b, s in copies:
            center[d], scale[d] = b * center[c] + s, abs(b) * scale[c]
        quad = {"quadratic": columns(cal.quadratic), "quadratic_center": center,
                "quadratic_scale": scale}
    diag = dict(cal.diagnostics)
    for key in ("offset_stderr", "span", "offset_stderr_rel_span", "offset_rule_channels",
                "offset_stderr_reach_load_span", "C_stderr"):
        v = diag.get(key)
        if v is None or np.ndim(v) == 0 or np.shape(v)[-1] != len(keep):
            continue
        full = columns(v, True if np.asarray(v).dtype == bool else 0.0)
        if key in ("offset_stderr", "span"):
            for d, c, b, _ in copies:
                full[d] = abs(b) * full[c]
        elif key == "offset_stderr_rel_span":
            for d, c, _, _ in copies:
                full[d] = full[c]  # (both scale by |b|)
        diag[key] = full
    diag["channel_copies"] = [{"channel": int(d), "copy_of": int(c), "scale": float(b),
                               "shift": float(s)} for d, c, b, s in copies]
    diag["channels_fitted"] = [int(c) for c in keep]
    out = Calibration(C=columns(cal.C), offset=offset, dof=cal.dof, method=cal.method,
                      diagnostics=diag, **quad)
    return out


def fit_without_copies(Z, known_Z, fit, dof: int):
    """``fit(Z_kept, known_Z_kept)`` on the channels of ``Z`` that are not exact copies
    (:func:`find_copies`), expanded to every channel (:func:`expand`), with one warning naming
    the copies; None where ``Z`` is not an in-memory array, has no copy, or would keep fewer
    than ``dof + 1`` channels (the caller then fits it as it is).

    Why not fewer: a log whose channels are copies of ``dof`` channels or fewer has no room for
    noise, so it is noise-free (the paper's Trial 1: its sensor's gauges come in pairs that read
    one load component with opposite signs) or cannot be fitted; there is no noise to count
    twice, and the routes that need ``dof + 1`` channels (the paper's) still run."""
    if not isinstance(Z, (np.ndarray, list, tuple)):
        return None  # a streamed source or a dask array: not read twice for this
    try:
        Za = np.asarray(Z, float)
    except (TypeError, ValueError):
        return None  # the fit's own checks name what is wrong with it
    copies = find_copies(Za)
    if not copies:
        return None
    p = Za.shape[1]
    drop = {d for d, _, _, _ in copies}
    keep = [c for c in range(p) if c not in drop]
    if len(keep) < int(dof) + 1:
        return None
    Zk = None
    if known_Z is not None:
        Zk = np.atleast_2d(np.asarray(known_Z, float))
        if Zk.shape[1] == p:
            Zk = Zk[:, keep]
    warn("; ".join(f"channel {d} is an exact copy of channel {c} ({b:.6g} x channel {c} "
                   f"{'+' if s >= 0 else '-'} {abs(s):.6g})" for d, c, b, s in copies)
         + ": fitted without it (a copy adds nothing about the load, and its noise, counted "
           "twice, would weigh its original twice); its column of C is 0")
    return expand(fit(Za[:, keep], Zk), p, copies)
