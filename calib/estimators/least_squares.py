"""Least-squares calibration with known loads, paper eqs. (2)-(3): ``C^T = Z^+ M``.

With ``bias=True`` a column of ones is appended, ``[Z 1] [C^T; d^T] = M``, so the fit also absorbs a
constant load offset ``d`` (solved by centring, which keeps C in the data's row space). When p >
dof only ``C z0`` is identifiable from known loads, so the
reported channel offset is the minimum-norm ``z0 = -C^+ d`` (it reproduces the loads exactly).
"""

from __future__ import annotations

import numpy as np

from calib.data.result import Calibration, CalibrationError
from calib.data.stream import is_dask
from calib.data.validate import check_dof


def fit_least_squares(Z, M, bias: bool = False, drop_nonfinite: bool = False) -> Calibration:
    """Calibrate from known (z, m) pairs.

    Parameters
    ----------
    Z : array of shape (n, p), raw readings
    M : array of shape (n, dof), the known applied loads, dof in {2, 3, 6}
    Z and M may also be ``dask.array.Array`` objects or :class:`calib.data.stream.ChunkSource`
    objects of equal length: the normal equations are sums, streamed block by block (a
    streaming QR, the same solution as the in-memory ``lstsq`` up to rounding).
    bias : also fit a constant offset

    Returns
    -------
    Calibration with ``method="least_squares"``; diagnostics: ``singular_values`` of the design,
    ``condition_number``, ``residual_rms`` (load units), ``n_samples``.
    """
    from calib.data.stream import (
        QR,
        StackedSource,
        as_source,
        blocks_of,
        check_scan_samples,
        is_streamed,
    )
    from calib.data.stream import scan as scan_source

    if bias and not (is_streamed(Z) or is_streamed(M)):
        # a channel logged twice or a sum channel (an exact affine copy or combination,
        # calib.data.copies): fitted without it. A copy's centred column equals its original's but
        # for the rounding of its shift, which the solve's cut-off (relative eps) keeps: a copy
        # shifted by 843 standard deviations gave C entries of 1e6 and loads 14 units off
        # (found by tests/calib/test_equivariance.py)
        from calib.data.copies import fit_without_copies

        try:
            M_all = np.atleast_2d(np.asarray(M, float))
        except (TypeError, ValueError):
            M_all = None  # the checks below name what is wrong with it
        if M_all is not None and M_all.ndim == 2:
            out = fit_without_copies(Z, None, lambda Zs, _: fit_least_squares(
                Zs, M_all, bias, drop_nonfinite), M_all.shape[1])
            if out is not None:
                return out

    if is_streamed(Z) or is_streamed(M):
        if is_dask(Z) and is_dask(M):
            import dask.array as da

            if Z.shape[0] == M.shape[0]:
                both = as_source(da.hstack([Z, M]))
            else:
                both = None
        else:
            both = StackedSource(as_source(Z), as_source(M))
        zs, ms = as_source(Z), as_source(M)
        p, dof = zs.p, ms.p
        if both is None or (zs.n is not None and ms.n is not None and zs.n != ms.n):
            raise CalibrationError(f"Z has {zs.n} rows but the known loads have {ms.n}")
    else:
        Z = np.asarray(Z, float)
        M = np.atleast_2d(np.asarray(M, float))
        if M.shape[0] != Z.shape[0]:
            raise CalibrationError(f"Z has {Z.shape[0]} rows but the known loads have "
                                   f"{M.shape[0]}")
        both = as_source(np.hstack([Z, M]), "known data")
        p, dof = Z.shape[1], M.shape[1]
    data = scan_source(both, "known data", drop_nonfinite)
    nbad = data.nbad
    dof = check_dof(dof)
    n = data.n
    need = dof + (1 if bias else 0)
    if n < need:
        raise CalibrationError(
            f"least squares needs at least {need} known loads for dof={dof}, got {n}"
        )
    zpart = StatsView(data, p)
    check_scan_samples(zpart, need, "known data", rows_per_channel=False)
    # one pass: streaming QR of the design [Z (1)] with the loads as right-hand sides (bias:
    # centred, which keeps C in the row space of the data), and of the loads alone
    zm, mm = data.mean[:p], data.mean[p:]
    design, loads = QR(), QR()
    for block in blocks_of(data.source):
        Zb, Mb = block[:, :p], block[:, p:]
        if bias:
            design.add(np.hstack([Zb - zm, Mb - mm]))
            loads.add(Mb)
        else:
            design.add(block)
            loads.add(Mb)
    sm = loads.singular_values()
    # the loads must span dof dimensions, else C is not determined in the missing directions
    if sm[-1] <= 1e-9 * sm[0]:
        raise CalibrationError(
            f"rank-deficient excitation: the known loads span {int((sm > 1e-9 * sm[0]).sum())} of "
            f"{dof} load dimensions"
        )
    C = design.lstsq(p).T
    if bias:
        # singular values of [Z 1]: the centred design's R plus the mean row, sqrt(n) [zm 1]
        top = QR()
        top.add(np.hstack([design.R[:, :p], np.zeros((len(design.R), 1))]))
        top.add(np.sqrt(n) * np.r_[zm, 1.0][None, :])
        top.n = n
        s = top.singular_values()
        d = mm - C @ zm
        offset = -np.linalg.pinv(C) @ d
    else:
        s = design.singular_values(p)
        offset = np.zeros(p)
    sq = 0.0
    for block in blocks_of(data.source):
        res = block[:, p:] - (block[:, :p] - offset) @ C.T
        sq += float(np.sum(res**2))
    diag = {
        "n_samples": n,
        "n_dropped_nonfinite": nbad,
        "singular_values": s,
        "condition_number": float(s[0] / s[-1]) if s[-1] > 0 else float("inf"),
        "residual_rms": float(np.sqrt(sq / max(n * dof, 1))),
    }
    return Calibration(C=C, offset=offset, dof=dof, method="least_squares", diagnostics=diag)


class StatsView:
    """The first ``p`` columns of a scan's statistics (the readings without the loads)."""

    def __init__(self, data, p):
        self.n, self.p = data.n, p
        self.min, self.max = data.min[:p], data.max[:p]

