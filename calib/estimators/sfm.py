"""Shape from motion without bias (paper eqs. 7-14) and the frame alignment from known pairs.

Pipeline for ``Z`` (n, p) of a constant-magnitude load moved over orientations:

1. SVD ``Z = U Sigma V^T`` (7), keep rank r (8); ``M^ = U* Sigma*^1/2``, ``S^ = Sigma*^1/2 V*^T``
(9).
2. The unit-magnitude constraint ``|m_i| = 1`` (14) is linear in the symmetric ``Q = A^-1 A^-T``:
   ``m^_i^T Q m^_i = 1``, solved in the least-squares sense over all rows.
3. Factor ``Q = L L^T`` (``L = A^-1``; the symmetric square root is used, which fixes the
   arbitrary rotation canonically). Then ``M = M^ L``, ``S = L^-1 S^`` (11), ``C = (S^T)^+`` (5).
4. A few known (z, m) pairs rotate and scale ``C`` into the user's frame (orthogonal Procrustes
   with scale, :func:`align_to_known`).

The SVD is taken through the p x p Gram matrix ``Z^T Z`` for large n, which never forms U.
"""

from __future__ import annotations

import numpy as np

from calib.data.result import (
    COVERAGE_MAX_ROWS,
    Calibration,
    CalibrationError,
    coverage_diagnostics,
    excitation_is_poor,
    warn,
)
from calib.data.stream import CHUNK_ROWS as CHUNK_ROWS  # re-exported: rows per block of a pass
from calib.data.stream import (
    QR,
    ChunkSource,
    MappedSource,
    as_source,
    blocks_of,
    check_scan_samples,
    scan,
)
from calib.data.validate import check_dof, check_matrix, check_rank, force_rank

#: Above this many rows the right singular vectors come from the Gram matrix (no n x p U).
#: Decision: docs/calib_design.md D11.
GRAM_THRESHOLD_ROWS = 20_000


def gram(Z, center: np.ndarray | None = None) -> np.ndarray:
    """``(Z - center)^T (Z - center)`` of shape (p, p), accumulated in chunks of rows (Z an
    array or a :class:`calib.data.stream.ChunkSource`)."""
    p = Z.p if isinstance(Z, ChunkSource) else Z.shape[1]
    G = np.zeros((p, p))
    for block in blocks_of(Z):
        if center is not None:
            block = block - center
        G += block.T @ block
    return G


def principal(Z, center: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Singular values (p,) descending and right singular vectors V (p, p) of ``Z - center``.

    Z is an array or a :class:`calib.data.stream.ChunkSource` (above :data:`GRAM_THRESHOLD_ROWS`
    rows one pass over its blocks; below, it is small and read whole).
    Signs are deterministic: the largest-magnitude entry of every column of V is positive.
    """
    if isinstance(Z, ChunkSource):
        n, p = Z.count(), Z.p
        if n <= GRAM_THRESHOLD_ROWS:
            Z = Z.to_array()
    else:
        n, p = Z.shape
    if n > GRAM_THRESHOLD_ROWS:
        w, V = np.linalg.eigh(gram(Z, center))
        w, V = w[::-1], V[:, ::-1]
        s = np.sqrt(np.clip(w, 0, None))
    else:
        X = Z if center is None else Z - center
        _, s, Vt = np.linalg.svd(X, full_matrices=False)
        V = Vt.T
        if len(s) < p:  # fewer rows than channels
            s = np.concatenate([s, np.zeros(p - len(s))])
            V = np.linalg.svd(X, full_matrices=True)[2].T
    idx = np.argmax(np.abs(V), axis=0)
    V = V * np.sign(V[idx, np.arange(p)])
    return s, V


#: :func:`noise_scale`: iterated principal-axis factor analysis, at most FA_MAX_ITER rounds,
#: stopped once no channel's noise variance changes by more than FA_TOL (relative); a noise
#: variance is floored at FA_FLOOR of its channel's variance (scikit-learn's FactorAnalysis
#: floors at 1e-12 likewise). The cap matters near a Heywood case (a channel the factors explain
#: almost wholly), where the iteration creeps towards a zero noise variance for hundreds of
#: rounds; capped, that channel's weight stays finite. Every iterate is exactly equivariant.
#: Decision: docs/calib_design.md D17.
FA_MAX_ITER = 200
#: Decision: docs/calib_design.md D17.
FA_TOL = 1e-4
#: Decision: docs/calib_design.md D17.
FA_FLOOR = 1e-12


def noise_scale(cov: np.ndarray, r: int) -> tuple[np.ndarray, str]:
    """Each channel's noise standard deviation, up to one common factor, from the covariance
    ``cov`` (p, p), or a stack of them (B, p, p), of readings that follow an r-dimensional load
    plus independent per-channel noise: ``cov = L L^T + diag(psi)``, the factor-analysis model,
    fitted by iterated principal axes from half of each channel's variance (see
    :data:`FA_MAX_ITER`). Returns ``(sqrt(psi), "factor analysis")``, psi shaped as the
    diagonals.

    Where ``psi`` is not identified (Ledermann's bound: ``(p - r)^2 < p + r``, e.g. p <= 5 for
    r = 3) it returns each channel's standard deviation and ``"channel spread"``.

    Both are equivariant: scaling channel c by k scales its entry by k (the iteration works on
    ``cov / (s s^T)``), so dividing the readings by the result makes the routes that follow
    independent of the channels' units.
    """
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    var = np.maximum(np.diagonal(cov, axis1=-2, axis2=-1), 1e-300)
    p = var.shape[-1]
    if (p - r) ** 2 < p + r:
        return np.sqrt(var), "channel spread"
    psi = 0.5 * var
    for _ in range(FA_MAX_ITER):
        sd = np.sqrt(psi)
        w, V = np.linalg.eigh(cov / (sd[..., :, None] * sd[..., None, :]))
        lam2 = np.sum(V[..., -r:] ** 2 * np.clip(w[..., None, -r:] - 1.0, 0.0, None), axis=-1)
        new = np.maximum(var - psi * lam2, FA_FLOOR * var)
        done = np.max(np.abs(new / psi - 1.0)) < FA_TOL
        psi = new
        if done:
            break
    return np.sqrt(psi), "factor analysis"


#: Below this rank gap the data show no rank-r structure: the paper's noisiest trial still has
#: 9, pure noise about 1.
#: Decision: docs/calib_design.md D67.
MIN_RANK_GAP = 2.0


def rank_gap(s: np.ndarray, r: int) -> float:
    """``s[r-1] / s[r]``: how far the r-th singular value stands above the noise floor. Warns
    (CalibrationWarning) below :data:`MIN_RANK_GAP`."""
    if len(s) <= r:
        return float("inf")
    gap = float(s[r - 1] / s[r]) if s[r] > 0 else float("inf")
    if gap < MIN_RANK_GAP:
        warn(f"rank gap {gap:.3g} < {MIN_RANK_GAP:g}: the readings show no rank-{r} structure "
             "(is a load really moving through orientations? noise or unrelated channels?); "
             "the calibration is unreliable")
    return gap


def quadric_design(X: np.ndarray) -> np.ndarray:
    """Rows ``[x_j x_k (j<=k, off-diagonal doubled)]`` so that ``design @ q == x^T Q x``."""
    r = X.shape[1]
    cols = []
    for j in range(r):
        for k in range(j, r):
            cols.append(X[:, j] * X[:, k] * (1.0 if j == k else 2.0))
    return np.column_stack(cols)


def sym_from_vec(q: np.ndarray, r: int) -> np.ndarray:
    Q = np.zeros((r, r))
    it = iter(q)
    for j in range(r):
        for k in range(j, r):
            Q[j, k] = Q[k, j] = next(it)
    return Q


def fit_unit_quadric(X) -> np.ndarray:
    """Least-squares symmetric Q (r, r) with ``x_i^T Q x_i = 1`` for the rows of X (n, r).

    X is an array or a :class:`calib.data.stream.ChunkSource` (then one pass: a streaming QR of the
    design, the same minimum-norm solution as ``lstsq`` on the whole design up to rounding).
    """
    if not isinstance(X, ChunkSource):
        r = X.shape[1]
        D = quadric_design(X)
        q, *_ = np.linalg.lstsq(D, np.ones(len(X)), rcond=None)
        return sym_from_vec(q, r)
    return unit_quadric_and_plane(X, plane=False)[0]


def unit_quadric_and_plane(X: ChunkSource, plane: bool = True):
    """One pass over X (n, q): the unit quadric of :func:`fit_unit_quadric` and (``plane``)
    the least-squares ``a`` with ``X a = 1``. Returns (Q, a or None)."""
    r = X.p
    nq = r * (r + 1) // 2
    quad, lin = QR(), QR()
    for block in blocks_of(X):
        ones = np.ones((len(block), 1))
        quad.add(np.hstack([quadric_design(block), ones]))
        if plane:
            lin.add(np.hstack([block, ones]))
    Q = sym_from_vec(quad.lstsq(nq)[:, 0], r)
    return Q, (lin.lstsq(r)[:, 0] if plane else None)


def sqrt_psd(Q: np.ndarray) -> tuple[np.ndarray, bool]:
    """Symmetric square root of Q; returns (root, was_definite). Negative eigenvalues are
    clipped."""
    w, V = np.linalg.eigh((Q + Q.T) / 2)
    ok = bool(w.min() > 0)
    w = np.clip(w, 1e-12 * max(w.max(), 1e-300), None)
    return (V * np.sqrt(w)) @ V.T, ok


def fit_sfm(
    Z,
    dof: int = 3,
    known_Z=None,
    known_M=None,
    magnitude: float | None = None,
    drop_nonfinite: bool = False,
) -> Calibration:
    """Shape from motion without bias.

    Parameters
    ----------
    Z : array of shape (n, p), raw readings of a constant-magnitude load over orientations; or a
        ``dask.array.Array`` or :class:`calib.data.stream.ChunkSource`, streamed block by block
        (never held whole in memory: :mod:`calib.data.stream`)
    dof : 2 or 3 (for 6 use :func:`calib.estimators.ft6.fit_ft6`)
    known_Z, known_M : optional arrays (k, p) and (k, dof): known pairs that fix rotation and scale
    magnitude : optional load magnitude used as scale when no known pairs are given

    Returns
    -------
    Calibration (``method="sfm"``, zero offset). Without known pairs ``C`` maps to a unit-magnitude
    load in an arbitrary (canonical) frame, scaled by ``magnitude`` if given.
    """
    dof = check_dof(dof)
    if dof == 6:
        raise CalibrationError("6-DOF shape from motion needs known loads: use "
                               "calib.estimators.ft6.fit_ft6")
    r = force_rank(dof)
    data = scan(as_source(Z), "Z", drop_nonfinite)
    check_scan_samples(data, r * (r + 1) // 2 + 1)
    if data.p < r:
        raise CalibrationError(f"need at least {r} channels for dof={dof}, got {data.p}")
    n, src = data.n, data.source
    src.want(coverage_step(n))
    s, V = principal(src)
    check_rank(s, r, "Z")
    Vr, sr = V[:, :r], s[:r]
    Q = fit_unit_quadric(MappedSource(src, lambda b: (b @ Vr) / np.sqrt(sr), p=r))
    L, definite = sqrt_psd(Q)
    if not definite:
        warn("unit-norm quadric is not positive definite; excitation too poor or rank wrong")
    C_unit = (L.T / np.sqrt(sr)) @ Vr.T
    mags = magnitude_pass(src, lambda b: b @ C_unit.T)
    cov = coverage_diagnostics(src.strided(coverage_step(n)) @ C_unit.T)
    diag = {
        "n_samples": n,
        "n_dropped_nonfinite": data.nbad,
        "singular_values": s,
        "rank": r,
        "rank_gap": rank_gap(s, r),
        "coverage": cov,
        "condition_number_C": float(np.linalg.cond(C_unit)),
        "condition_number_Q": float(np.linalg.cond(Q)),
        "residual_magnitude_rms": mags["residual_magnitude_rms"],
    }
    # no "poor excitation" warning here: without an offset to find, a cap costs the shape
    # nothing measurable (40 random 8-channel sensors a cap, 4 known pairs, noise 1 %
    # of each channel's signal: held-out load error median 0.23 / 0.24 / 0.22 % of the load at
    # 45 / 60 / 90 degree caps, 0.25 % over the sphere; at 20 % noise 5.1 / 5.1 / 4.6 / 4.9 %).
    # The coverage stays in the diagnostics (excitation_poor), and it is the offset routes
    # (calib.estimators.bias) that warn.
    diag["excitation_poor"] = bool(excitation_is_poor(cov))
    cal = Calibration(
        C=C_unit, offset=np.zeros(data.p), dof=dof, method="sfm", diagnostics=diag
    )
    return finish_frame(cal, known_Z, known_M, magnitude)


def coverage_step(n: int) -> int:
    """Stride of the rows the coverage statistics use (at most COVERAGE_MAX_ROWS of n)."""
    return int(np.ceil(n / COVERAGE_MAX_ROWS)) if n > COVERAGE_MAX_ROWS else 1


def magnitude_pass(src: ChunkSource, loads) -> dict:
    """One pass: rms of ``|u| - 1`` and mean of ``|u|`` for the unit loads ``u = loads(block)``
    of every row."""
    n = 0
    sq = tot = 0.0
    for block in blocks_of(src):
        U = loads(block)
        mags = np.sqrt(np.einsum("ij,ij->i", U, U))
        n += len(mags)
        sq += float(np.sum((mags - 1) ** 2))
        tot += float(np.sum(mags))
    n = max(n, 1)
    return {"residual_magnitude_rms": float(np.sqrt(sq / n)), "magnitude_mean": tot / n}


def finish_frame(cal: Calibration, known_Z, known_M, magnitude) -> Calibration:
    """Apply known pairs (rotation + scale) or a bare magnitude to a unit-frame calibration."""
    if known_Z is not None and known_M is not None:
        R, scale, info = align_to_known(cal.C, cal.offset, known_Z, known_M)
        cal.C = scale * R @ cal.C
        cal.diagnostics["alignment"] = info
    elif magnitude is not None:
        cal.C = float(magnitude) * cal.C
    return cal


def align_to_known(C_unit: np.ndarray, offset: np.ndarray, known_Z, known_M):
    """Rotation R (r, r) in O(r) and scale s with ``m ~= s R C_unit (z - offset)``.

    Orthogonal Procrustes with scale on the force components of the known pairs. With pairs spanning
    only r-1 directions (2 pairs in 3-D, 1 in 2-D) a mirror image fits equally well: the proper
    rotation is chosen and a CalibrationWarning says so; a further pair removes the ambiguity.

    Returns (R, s, info) where info holds ``n_pairs``, ``residual_rms`` and ``mirror_ambiguous``.
    """
    Zk, _ = check_matrix(np.atleast_2d(known_Z), "known readings")
    Mk = np.atleast_2d(np.asarray(known_M, float))
    r = C_unit.shape[0]
    if len(Zk) != len(Mk):
        raise CalibrationError(f"{len(Zk)} known readings but {len(Mk)} known loads")
    if Mk.shape[1] < r:
        raise CalibrationError(f"known loads need at least {r} force columns, got {Mk.shape[1]}")
    Uk = (Zk - offset) @ C_unit.T
    Fk = Mk[:, :r]
    H = Uk.T @ Fk
    # Procrustes by hand (not scipy.linalg.orthogonal_procrustes): the singular values decide
    # whether the pairs leave a mirror ambiguity, and then the proper rotation is chosen (D)
    P, sig, Qt = np.linalg.svd(H)
    if sig[0] <= 0:
        raise CalibrationError("known loads are all zero: cannot fix rotation and scale")
    ambiguous = len(Zk) < r or sig[-1] <= 1e-9 * sig[0]
    if len(Zk) < r - 1 or (r > 1 and sig[r - 2] <= 1e-9 * sig[0]):
        raise CalibrationError(
            f"known loads span fewer than {r - 1} directions; rotation is not determined"
        )
    D = np.eye(r)
    if ambiguous:
        D[-1, -1] = np.sign(np.linalg.det(P @ Qt)) or 1.0
        warn(
            f"{len(Zk)} known pair(s) fix the frame only up to a mirror image; proper rotation "
            "assumed (add a pair off their plane to resolve)"
        )
    R = (P @ D @ Qt).T
    scale = float(np.trace(np.diag(sig) @ D) / np.sum(Uk**2))
    res = Fk - scale * Uk @ R.T
    info = {
        "n_pairs": len(Zk),
        "scale": scale,
        "residual_rms": float(np.sqrt(np.mean(res**2))),
        "mirror_ambiguous": bool(ambiguous),
    }
    return R, scale, info
