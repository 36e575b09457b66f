"""Channels that are an exact affine copy of another channel of the same log, or an exact affine
combination of earlier channels (a sum or difference channel).

A log can hold one reading twice: the same channel logged in two units (counts and volts), or
copied into a second column by the logging software. A copy adds nothing about the load, and
its noise is its original's, so a fit that weighs the channels as independent counts that noise
twice. Measured on the payload study's default case (seeds 10,000-10,005, channel 0
copied as ``2 z_0 + 5``), the held-out error over least squares with every load known went from
0.85-1.10x to 1.01-1.45x for the joint fit and from 1.07-2.24x to 1.17-5.34x for the centered
route; least squares (every load known) does not change. So :func:`calib.routes.joint.fit_joint` and
:func:`calib.estimators.bias.fit_bias` fit the log without its copies and give each copy a column
of zeros in
``C`` (:func:`expand`): the loads are then those of the log without the copy, and the copy's
offset is its original's, mapped by the same affine relation. So does
:func:`calib.estimators.least_squares.fit_least_squares` with a bias (in-memory arrays), for a
reason of
its own: its centred columns then differ only by the rounding of the copy's shift, which its
solve's cut-off keeps (a copy shifted by 843 standard deviations put 1e6 into ``C``).

"Exact": the affine regression of a channel on an earlier channel leaves at most
:data:`COPY_TOLERANCE` of its variance. Distinct channels leave far more: at least 3.7e-4 over
every pair of every case of the payload study (10 rigs a case, the wrench channels' torques
included, which follow their forces closely) and of :func:`calib.simulation.simulate.simulate_rig`,
2.5e-3
on the real printed sensor's sets and 5.3e-2 on the real wrist sensor. A copy written with few
significant digits, or one read through a second amplifier with noise of its own, leaves more
than the tolerance and is fitted as a channel of its own, as before (docs/calib.md, "A channel
that repeats another": such a repeat costs 1.1-1.6x).

Combinations (:func:`find_combinations`): a channel that the affine regression on every
earlier channel kept leaves with at most :data:`COMBINATION_TOLERANCE` (1e-12) of its variance is
left out the same way. Measured without that: a channel combining 2 or 3 others (payload default
case, seeds 10,000-10,005, appended) cost the joint fit 1.00-1.48x and the centered route 0.87-4.29x
its fit without it; now both are the same as without it. The later channel of a dependency is the
one left out: where a combination is logged before a channel it combines, that channel is left out
instead, and the fit still moves, the combination's noise being correlated with its channels' (the
same rigs: joint 0.92-1.35x, centered 0.76-3.17x, least squares 1.00x): which of the dependent
channels carries noise of its own is not known from the dependency alone.
"""

from __future__ import annotations

import numpy as np

from calib.data.result import Calibration, warn

#: Largest share of a channel's variance the affine regression on an earlier channel may leave
#: for it to be that channel's exact copy (module docstring).
#: Decision: docs/calib_design.md D4.
COPY_TOLERANCE = 1e-10
#: Largest share of a channel's variance the affine regression on every earlier channel kept may
#: leave for it to be their exact combination (:func:`find_combinations`). Far below
#: :data:`COPY_TOLERANCE`: once the earlier channels read the whole load, what a distinct channel
#: leaves is its noise alone, at least 9.4e-6 of its variance over the payload study's cases and
#: ``simulate_rig`` (10 rigs each), and 1e-10 for a sensor whose noise is 1e-5 of its spread.
#: 1e-12 is noise of one part per million of the spread (beyond a 20-bit reading), and keeps a
#: combination written with six significant digits (about 1e-13).
#: Decision: docs/calib_design.md D5.
COMBINATION_TOLERANCE = 1e-12
#: Residual degrees of freedom the combination regression needs (rows beyond its parameters):
#: with as many rows as parameters any channel is a combination of the others.
#: Decision: docs/calib_design.md D5.
COMBINATION_MIN_DOF = 10
#: Rows :func:`find_combinations` searches on (evenly strided; a channel found is confirmed on
#: every row): a log of 1e6 readings costs it as much as one of 20,000.
#: Decision: docs/calib_design.md D5.
COMBINATION_ROWS = 20_000
#: The copy search's screen (:func:`_copies`): pairs whose squared correlation is below
#: ``1 - SCREEN_SLACK`` are not copies (a copy leaves at most ``COPY_TOLERANCE`` = 1e-10 of its
#: variance, ``r^2 >= 1 - 1e-10``; the Gram entries' rounding is about 1e-15 of their size), and
#: :data:`SCREEN_BLOCK` channels are screened at a time (a block's Gram columns: p x 512 doubles).
#: Decision: docs/calib_design.md D4.
SCREEN_SLACK = 1e-6
#: Decision: docs/calib_design.md D4.
SCREEN_BLOCK = 512


def _search_rows(Z: np.ndarray):
    """The rows the search runs on: at most :data:`COMBINATION_ROWS`, evenly strided, of the
    rows finite in every channel (a copy; the log itself is not copied); and the mask of the
    finite rows (None where every row is)."""
    fin = np.all(np.isfinite(Z), axis=1)
    step = max(1, int(fin.sum()) // COMBINATION_ROWS)
    if fin.all():
        return np.array(Z[::step]), None
    return Z[fin][::step], fin


def _holds(Z: np.ndarray, fin, d: int, cs, bs, tol: float) -> bool:
    """Whether ``z_d - bs . z_cs`` varies by at most ``tol`` of ``z_d``'s variance over every
    finite row (column by column: no copy of the log)."""
    with np.errstate(all="ignore"):
        left = Z[:, d].copy()
        for c, b in zip(cs, bs, strict=True):
            left -= b * Z[:, c]
        zd = Z[:, d]
        if fin is not None:
            left, zd = left[fin], zd[fin]
        return bool(np.var(left) <= tol * np.var(zd))


def _search(Z: np.ndarray):
    """``(fin, mu, Sc, ss, full)`` of the search rows (:func:`_search_rows`): their mean, the
    rows centred, each channel's sum of squares, and whether they are every finite row; None
    for fewer than 3 rows or values too large to square in double precision (the fit's own
    checks refuse those)."""
    S, fin = _search_rows(Z)
    if len(S) < 3:
        return None
    with np.errstate(all="ignore"):
        mu = S.mean(axis=0)
        Sc = S - mu
        ss = np.einsum("ij,ij->j", Sc, Sc)
    if not np.all(np.isfinite(ss)):
        return None
    return fin, mu, Sc, ss, len(S) == (len(Z) if fin is None else int(fin.sum()))


def find_copies(Z) -> list[tuple[int, int, float, float]]:
    """``(copy, original, scale, shift)`` for every channel of ``Z`` (n, p) that is an exact
    affine copy of an earlier channel, ``z_copy = scale z_original + shift`` over the rows
    finite in every channel; the original is the first channel it copies (never itself a copy).
    Searched on at most :data:`COMBINATION_ROWS` evenly strided rows, a copy found there
    confirmed on every row. Empty for fewer than 3 finite rows, or values too large to square
    in double precision."""
    Z = np.asarray(Z, float)
    if Z.ndim != 2 or Z.shape[1] < 2:
        return []
    return _copies(Z, _search(Z))


def _copies(Z: np.ndarray, search) -> list[tuple[int, int, float, float]]:
    """:func:`find_copies` on the rows :func:`_search` gave."""
    if search is None:
        return []
    fin, mu, Sc, ss, full = search
    found, copied = [], set()
    p = Z.shape[1]
    live = ss > 0
    for lo in range(0, p, SCREEN_BLOCK):
        hi = min(p, lo + SCREEN_BLOCK)
        # the screen: a pair whose correlation is not within SCREEN_SLACK of +-1 leaves far more
        # than COPY_TOLERANCE of the variance (rest / ss_d = 1 - r^2), whatever the rounding;
        # the pairs left are decided exactly, one by one, in the order the full loop takes them
        with np.errstate(all="ignore"):
            R = (Sc.T @ Sc[:, lo:hi]) / np.sqrt(ss)[:, None] / np.sqrt(ss[lo:hi])[None, :]
            r2 = R * R  # a correlation: |R| <= 1, no overflow
        near = (r2 >= 1 - SCREEN_SLACK) & live[:, None] & live[None, lo:hi]
        for d in range(lo, hi):
            cand = np.flatnonzero(near[:d, d - lo])
            if len(cand):
                _first_copy(Sc, ss, Z, fin, full, d, cand, copied, found, mu)
    return found


def _first_copy(Sc, ss, Z, fin, full, d, cand, copied, found, mu) -> None:
    """The exact test of :func:`_copies` for channel ``d`` against the screened earlier channels
    ``cand`` (ascending): the first that ``d`` copies is recorded."""
    for c in (int(c) for c in cand):
        if c in copied:
            continue
        with np.errstate(all="ignore"):
            b = float(Sc[:, c] @ Sc[:, d]) / float(ss[c])
            left = Sc[:, d] - b * Sc[:, c]
            rest = float(left @ left)
        if (np.isfinite(b) and b != 0 and rest <= COPY_TOLERANCE * float(ss[d])
                and (full or _holds(Z, fin, d, (c,), (b,), COPY_TOLERANCE))):
            found.append((d, c, b, float(mu[d] - b * mu[c])))
            copied.add(d)
            return


def find_combinations(Z) -> list[tuple[int, tuple[int, ...], tuple[float, ...], float]]:
    """``(channel, channels, coefficients, shift)`` for every channel of ``Z`` (n, p) that is an
    exact affine combination of earlier channels, ``z_channel = coefficients . z_channels +
    shift`` (the earlier channels kept: not themselves copies or combinations), its residual at
    most :data:`COMBINATION_TOLERANCE` of its variance; exact copies of one channel included
    (one channel, :data:`COPY_TOLERANCE`, as :func:`find_copies` finds them). The later channel
    of a dependency is the one named: a sum or difference channel is logged after the channels
    it combines. Searched on at most :data:`COMBINATION_ROWS` evenly strided rows, a channel
    found there confirmed on every row. Empty for fewer than 3 finite rows or values too large
    to square."""
    Z = np.asarray(Z, float)
    if Z.ndim != 2 or Z.shape[1] < 2:
        return []
    search = _search(Z)
    if search is None:
        return []
    fin, mu, Sc, ss, full = search
    copies = {d: (d, (c,), (b,), sh) for d, c, b, sh in _copies(Z, search)}
    found, kept = [], []
    for d in range(Z.shape[1]):
        if d in copies:
            found.append(copies[d])
            continue
        on = [c for c in kept if ss[c] > 0]  # (a constant channel: the fit refuses it)
        if len(on) >= 2 and ss[d] > 0 and len(Sc) - len(on) - 1 >= COMBINATION_MIN_DOF:
            X = Sc[:, on] / np.sqrt(ss[on])  # equilibrated: units do not matter
            try:
                with np.errstate(all="ignore"):
                    w = np.linalg.lstsq(X, Sc[:, d], rcond=None)[0]
                    left = Sc[:, d] - X @ w
                    rest = float(left @ left)
            except np.linalg.LinAlgError:
                w, rest = np.full(len(on), np.nan), np.inf
            if np.all(np.isfinite(w)) and rest <= COMBINATION_TOLERANCE * float(ss[d]):
                coef = w / np.sqrt(ss[on])
                if full or _holds(Z, fin, d, on, coef, COMBINATION_TOLERANCE):
                    found.append((d, tuple(int(c) for c in on), tuple(float(b) for b in coef),
                                  float(mu[d] - coef @ mu[on])))
                    continue
        kept.append(d)
    return found


def _as_general(copies):
    """Entries of :func:`find_copies` ``(d, c, b, s)`` or :func:`find_combinations` ``(d, cs, bs,
    s)``, all as the latter."""
    return [(d, (c,), (b,), sh) if np.ndim(c) == 0 else (d, tuple(c), tuple(b), sh)
            for d, c, b, sh in copies]


def _participants(cs, bs, Z=None):
    """The channels of a combination whose term is not rounding (above 1e-6 of the largest term,
    on the scale of the readings; all where ``Z`` is None)."""
    if Z is None or len(cs) == 1:
        return list(zip(cs, bs, strict=True))
    sd = np.nanstd(np.asarray(Z, float)[:, list(cs)], axis=0) * np.abs(bs)
    return [(c, b) for c, b, t in zip(cs, bs, sd, strict=True) if t > 1e-6 * sd.max()]


def expand(cal: Calibration, p: int, copies, Z=None) -> Calibration:
    """``cal``, fitted on the channels of a p-channel log that are not copies or combinations,
    as a calibration of all p: such a channel's column of ``C`` (and of its quadratic terms and
    standard errors) is 0, its offset its channels' mapped by its affine relation, its offset's
    standard error theirs combined (a copy's: its original's times ``|scale|``; a combination's
    taken as independent, root-sum-square). The channels a per-channel diagnostic of the fit
    names are the kept ones (``diagnostics["channel_copies"]`` lists them: ``channel``,
    ``copy_of``, ``scale``, ``shift`` for a copy; ``channel``, ``combination_of``,
    ``coefficients``, ``shift`` for a combination); the keys below are set out over all p
    channels. ``copies``: entries of :func:`find_copies` or :func:`find_combinations`; ``Z``, the
    log, gives a combination's span (a copy's is its original's times ``|scale|``)."""
    copies = sorted(_as_general(copies))  # in order: a copy may copy a combination
    drop = [d for d, _, _, _ in copies]
    keep = np.array([c for c in range(p) if c not in drop], int)

    def columns(X, fill=0.0):  # (..., len(keep)) -> (..., p): a dropped entry from ``fill``
        X = np.asarray(X)
        out = np.full(X.shape[:-1] + (p,), fill, dtype=X.dtype if X.dtype == bool else float)
        out[..., keep] = X
        return out

    offset = columns(cal.offset)
    for d, cs, bs, sh in copies:
        offset[d] = np.dot(bs, offset[list(cs)]) + sh
    quad = {}
    if cal.quadratic is not None:
        center, scale = columns(cal.quadratic_center), columns(cal.quadratic_scale, 1.0)
        for d, cs, bs, sh in copies:
            center[d] = np.dot(bs, center[list(cs)]) + sh
            scale[d] = float(np.sqrt(np.sum((np.asarray(bs) * scale[list(cs)]) ** 2)))
        quad = {"quadratic": columns(cal.quadratic), "quadratic_center": center,
                "quadratic_scale": scale}
    diag = dict(cal.diagnostics)
    span_of = None if Z is None else np.nanmax(Z, axis=0) - np.nanmin(Z, axis=0)
    for key in ("offset_stderr", "span", "offset_stderr_rel_span", "offset_rule_channels",
                "offset_stderr_reach_load_span", "C_stderr"):
        v = diag.get(key)
        if v is None or np.ndim(v) == 0 or np.shape(v)[-1] != len(keep):
            continue
        full = columns(v, True if np.asarray(v).dtype == bool else 0.0)
        for d, cs, bs, _ in copies:
            one = len(cs) == 1
            if key == "offset_stderr":
                full[d] = float(np.sqrt(np.sum((np.asarray(bs) * full[list(cs)]) ** 2)))
            elif key == "span":
                full[d] = (abs(bs[0]) * full[cs[0]] if one or span_of is None
                           else float(span_of[d]))
            elif key == "offset_stderr_rel_span" and one:
                full[d] = full[cs[0]]  # (both scale by |b|)
            elif key == "offset_rule_channels" and not one:
                full[d] = False  # its column of C is 0: its offset does not reach the loads
        diag[key] = full
    if "offset_stderr_rel_span" in diag and "offset_stderr" in diag and "span" in diag:
        rel = np.asarray(diag["offset_stderr_rel_span"], float)
        if rel.shape == (p,):
            for d, cs, _, _ in copies:
                if len(cs) > 1:
                    rel[d] = diag["offset_stderr"][d] / max(float(diag["span"][d]), 1e-300)
            diag["offset_stderr_rel_span"] = rel
    diag["channel_copies"] = [_entry(d, cs, bs, sh, Z) for d, cs, bs, sh in copies]
    diag["channels_fitted"] = [int(c) for c in keep]
    out = Calibration(C=columns(cal.C), offset=offset, dof=cal.dof, method=cal.method,
                      diagnostics=diag, **quad)
    return out


def _entry(d, cs, bs, sh, Z) -> dict:
    """One copy or combination as ``diagnostics["channel_copies"]`` lists it."""
    if len(cs) == 1:
        return {"channel": int(d), "copy_of": int(cs[0]), "scale": float(bs[0]),
                "shift": float(sh)}
    terms = _participants(cs, bs, Z)
    return {"channel": int(d), "combination_of": [int(c) for c, _ in terms],
            "coefficients": [float(b) for _, b in terms], "shift": float(sh)}


def _said(d, cs, bs, sh, Z) -> str:
    """One copy or combination in words, each channel as ``channel N`` (the CLI names them)."""
    if len(cs) == 1:
        return (f"channel {d} is an exact copy of channel {cs[0]} ({bs[0]:.6g} x channel {cs[0]} "
                f"{'+' if sh >= 0 else '-'} {abs(sh):.6g})")
    terms = _participants(cs, bs, Z)
    names = ", ".join(f"channel {c}" for c, _ in terms[:-1]) + f" and channel {terms[-1][0]}"
    rel = " ".join(f"{'+' if b >= 0 else '-'} {abs(b):.6g} x channel {c}" for c, b in terms)
    return (f"channel {d} is an exact combination of {names} ({rel.lstrip('+ ')} "
            f"{'+' if sh >= 0 else '-'} {abs(sh):.6g})")


def fit_without_copies(Z, known_Z, fit, dof: int):
    """``fit(Z_kept, known_Z_kept)`` on the channels of ``Z`` that are not exact copies or
    combinations of earlier channels (:func:`find_combinations`), expanded to every channel
    (:func:`expand`), with one warning naming them; None where ``Z`` is not an in-memory array,
    has none, or would keep fewer than ``dof + 1`` channels (the caller then fits it as it is).

    Why not fewer: a log whose channels are copies or combinations of ``dof`` channels or fewer
    has no room for noise, so it is noise-free (the paper's Trial 1: its sensor's gauges come in
    pairs that read one load component with opposite signs) or cannot be fitted; there is no
    noise to count twice, and the routes that need ``dof + 1`` channels (the paper's) still
    run."""
    if not isinstance(Z, (np.ndarray, list, tuple)):
        return None  # a streamed source or a dask array: not read twice for this
    try:
        Za = np.asarray(Z, float)
    except (TypeError, ValueError):
        return None  # the fit's own checks name what is wrong with it
    if Za.ndim != 2 or Za.shape[0] < Za.shape[1]:
        return None  # the fit refuses it (fewer samples than channels) before any search
    copies = find_combinations(Za)
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
    warn("; ".join(_said(*c, Za) for c in copies)
         + ": fitted without it (it adds nothing about the load, and its noise, which is its "
           "channels' own, would be counted twice); its column of C is 0")
    return expand(fit(Za[:, keep], Zk), p, copies, Za)
