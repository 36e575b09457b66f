"""Chunk sources: data seen block by block, so logs larger than memory can be fitted.

A :class:`ChunkSource` has ``p`` columns and ``n`` rows (``None`` until a first pass has counted
them, e.g. for a CSV file) and yields ``(start_row, block)`` pairs in row order from
:meth:`ChunkSource.blocks`; every call is a new pass (a CSV file is read again, a dask array's
blocks are computed again, an in-memory array is sliced again). :meth:`ChunkSource.strided`
gathers the rows whose global index is a multiple of ``step``: the global row index decides, not
the block, so a strided subsample is the same whatever the chunking. Steps announced with
:meth:`ChunkSource.want` are gathered during the next full pass, without a pass of their own.

The fitting routes (:func:`calib.fit_bias`, :func:`calib.fit_sfm`,
:func:`calib.fit_least_squares`) turn their input into a source with :func:`as_source`; an
in-memory array becomes an :class:`ArraySource` sliced in :data:`CHUNK_ROWS` blocks, so the
in-memory and the streamed fits run the same code. Sources:

- :class:`ArraySource`: an in-memory (n, p) array;
- :class:`DaskSource`: a ``dask.array.Array``, one row-block computed at a time;
- :class:`CSVSource`: a CSV file read ``chunk_rows`` rows at a time (:mod:`calib.data.io`);
- :class:`MappedSource`: a row-wise function of another source (e.g. ``(Z - mu) @ V_r``),
  computed per block;
- :class:`FilteredSource`: another source without its non-finite rows;
- :class:`StackedSource`: two sources side by side (readings and known loads).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np

from calib.data.result import CalibrationError
from calib.data.validate import check_samples

#: Rows per block of an in-memory array (bounds the temporaries of every pass).
#: Decision: docs/calib_design.md D74.
CHUNK_ROWS = 1 << 17


class ChunkSource:
    """Rows of an (n, p) float matrix, block by block; see the module docstring.

    Subclasses implement :meth:`_blocks` (``(start_row, float block)`` in order, each pass
    anew) and set ``p`` (and ``n`` when known without a pass).
    """

    p: int
    n: int | None = None
    #: True when :meth:`_blocks` already yields the canonical blocks (see :meth:`blocks`).
    canonical: bool = False

    def __init__(self) -> None:
        self._strided: dict[int, np.ndarray] = {}
        self._wanted: set[int] = set()

    def _blocks(self) -> Iterator[tuple[int, np.ndarray]]:  # pragma: no cover - abstract
        raise NotImplementedError

    def blocks(self) -> Iterator[tuple[int, np.ndarray]]:
        """One pass: ``(start_row, block)`` with ``block`` a float (m, p) array. The rows of
        the steps announced by :meth:`want` are gathered on the way.

        Blocks are canonical: rows ``[k CHUNK_ROWS, (k+1) CHUNK_ROWS)`` whatever the source's own
        chunking (a CSV's ``chunk_rows``, a dask array's chunks), so every sum over blocks is
        taken in the same order as for the in-memory array and the results agree to the last
        bit, not just to rounding."""
        pending = sorted(self._wanted - set(self._strided))
        parts: dict[int, list] = {s: [] for s in pending}
        end = 0
        for start, block in (self._blocks() if self.canonical else _rechunk(self._blocks())):
            for s in pending:
                parts[s].append(block[(-start) % s :: s].copy())
            end = start + len(block)
            yield start, block
        self.n = end
        for s in pending:
            self._strided[s] = (np.concatenate(parts[s]) if parts[s]
                                else np.empty((0, self.p)))
            self._wanted.discard(s)

    def want(self, *steps: int) -> None:
        """Gather the rows ``i % step == 0`` of each step during the next full pass."""
        self._wanted |= {int(s) for s in steps if int(s) not in self._strided}

    def strided(self, step: int) -> np.ndarray:
        """Rows ``i % step == 0`` (i the global row index) as an array; a pass unless they were
        gathered already."""
        step = int(step)
        if step not in self._strided:
            self.want(step)
            for _ in self.blocks():
                pass
        return self._strided[step]

    def count(self) -> int:
        """Number of rows (a pass if not known yet)."""
        if self.n is None:
            for _ in self.blocks():
                pass
        return int(self.n)

    def to_array(self) -> np.ndarray:
        """All rows in memory (for small sources)."""
        return self.strided(1)


def _rechunk(blocks, rows: int = CHUNK_ROWS):
    """Blocks of exactly ``rows`` rows (the last may be shorter) from blocks of any size, row
    order kept; whole blocks inside a piece are views, pieces straddling blocks are copied."""
    buf: list[np.ndarray] = []
    have = 0
    start = 0
    for _, b in blocks:
        while len(b):
            if have == 0 and len(b) >= rows:
                yield start, b[:rows]
                start += rows
                b = b[rows:]
                continue
            take = b[: rows - have]
            buf.append(take)
            have += len(take)
            b = b[len(take) :]
            if have == rows:
                yield start, np.concatenate(buf)
                start += rows
                buf, have = [], 0
    if have:
        yield start, np.concatenate(buf)


class ArraySource(ChunkSource):
    """An in-memory (n, p) array sliced in blocks of ``chunk_rows`` (views, no copies)."""

    def __init__(self, Z: np.ndarray, chunk_rows: int = CHUNK_ROWS) -> None:
        super().__init__()
        self.Z = Z
        self.n, self.p = Z.shape
        self.chunk_rows = int(chunk_rows)
        self.canonical = self.chunk_rows == CHUNK_ROWS

    def _blocks(self):
        for i in range(0, self.n, self.chunk_rows):
            yield i, self.Z[i : i + self.chunk_rows]

    def want(self, *steps: int) -> None:
        pass

    def strided(self, step: int) -> np.ndarray:
        # contiguous like the rows a streamed pass gathers (same rounding in later products)
        return np.ascontiguousarray(self.Z[:: int(step)])


class MappedSource(ChunkSource):
    """``fn`` applied row-wise to every block of ``parent`` (``fn`` must act on rows
    independently, so that strided rows map to the same values)."""

    def __init__(self, parent: ChunkSource, fn: Callable[[np.ndarray], np.ndarray],
                 p: int | None = None) -> None:
        super().__init__()
        self.parent = parent
        self.fn = fn
        self.n = parent.n
        self.p = p if p is not None else fn(np.zeros((1, parent.p))).shape[1]

    def _blocks(self):
        for start, block in self.parent.blocks():
            yield start, self.fn(block)

    def blocks(self):
        yield from self._blocks()
        self.n = self.parent.n

    def want(self, *steps: int) -> None:
        self.parent.want(*steps)

    def strided(self, step: int) -> np.ndarray:
        return self.fn(self.parent.strided(step))


class FilteredSource(ChunkSource):
    """``parent`` without its rows holding NaN/inf; row indices count the kept rows."""

    def __init__(self, parent: ChunkSource, n: int | None = None) -> None:
        super().__init__()
        self.parent = parent
        self.p = parent.p
        self.n = n

    def _blocks(self):
        kept = 0
        for _, block in self.parent.blocks():
            good = np.isfinite(block).all(axis=1)
            if not good.all():
                block = block[good]
            yield kept, block
            kept += len(block)


class DaskSource(ChunkSource):
    """A 2-D ``dask.array.Array``: one row-block (all its columns) computed per step of a pass,
    so only one block is in memory at a time."""

    def __init__(self, arr) -> None:
        super().__init__()
        if arr.ndim != 2:
            raise CalibrationError(f"data must be 2-D (n_samples, n_channels), got shape "
                                   f"{arr.shape}")
        self.arr = arr
        self.p = int(arr.shape[1])
        n = arr.shape[0]
        self.n = int(n) if n == n else None  # nan: unknown chunk sizes

    def _blocks(self):
        start = 0
        for i in range(self.arr.numblocks[0]):
            block = np.ascontiguousarray(self.arr.blocks[i].compute(), dtype=float)
            if block.ndim != 2:
                block = block.reshape(len(block), -1)
            yield start, block
            start += len(block)


class StackedSource(ChunkSource):
    """Two sources of equal row count side by side (their blocks need not line up)."""

    def __init__(self, a: ChunkSource, b: ChunkSource) -> None:
        super().__init__()
        self.a, self.b = a, b
        self.p = a.p + b.p
        self.n = a.n if a.n is not None and a.n == b.n else None

    def _blocks(self):
        ia, ib = self.a.blocks(), self.b.blocks()
        ra = rb = np.empty((0, 0))
        start = 0
        while True:
            if len(ra) == 0:
                ra = next((blk for _, blk in ia), None)
            if len(rb) == 0:
                rb = next((blk for _, blk in ib), None)
            if ra is None or rb is None:
                if ra is not None or rb is not None:
                    raise CalibrationError("the readings and the known loads differ in length")
                return
            if len(ra) == 0 or len(rb) == 0:
                continue
            m = min(len(ra), len(rb))
            yield start, np.hstack([ra[:m], rb[:m]])
            ra, rb = ra[m:], rb[m:]
            start += m


def is_dask(x) -> bool:
    """True for a ``dask.array.Array`` (without importing dask)."""
    return type(x).__module__.split(".")[0] == "dask" and hasattr(x, "blocks")


def as_source(Z, name: str = "Z") -> ChunkSource:
    """A :class:`ChunkSource` for Z: a source itself, a dask array, or anything
    ``np.asarray`` takes (a 2-D array, one-line error otherwise)."""
    if isinstance(Z, ChunkSource):
        return Z
    if is_dask(Z):
        return DaskSource(Z)
    Z = np.asarray(Z, dtype=float)
    if Z.ndim != 2:
        raise CalibrationError(f"{name} must be 2-D (n_samples, n_channels), got shape {Z.shape}")
    return ArraySource(Z)


def is_streamed(Z) -> bool:
    """True when Z is not an in-memory array (a chunk source or a dask array)."""
    return isinstance(Z, ChunkSource) or is_dask(Z)


class Scan:
    """Result of :func:`scan`: the checked source (non-finite rows dropped if asked) and its
    column statistics."""

    def __init__(self, source, n, nbad, total, lo, hi):
        self.source = source
        self.n = n
        self.p = source.p
        self.nbad = nbad
        self.total = total
        self.min = lo
        self.max = hi

    @property
    def mean(self) -> np.ndarray:
        return self.total / max(self.n, 1)

    @property
    def span(self) -> np.ndarray:
        return np.asarray(self.max - self.min, dtype=float)


def scan(source: ChunkSource, name: str = "Z", drop_nonfinite: bool = False) -> Scan:
    """One pass: row count, non-finite rows, column sums, minima and maxima; the checks of
    :func:`calib.data.validate.check_matrix` (same one-line errors). Returns a :class:`Scan`
    whose source skips the non-finite rows when ``drop_nonfinite``."""
    p = source.p
    n = nbad = 0
    first = None
    total = np.zeros(p)
    lo = np.full(p, np.inf)
    hi = np.full(p, -np.inf)
    small = 0.0  # largest nonzero magnitude
    for start, block in source.blocks():
        good = np.isfinite(block).all(axis=1)
        if not good.all():
            bad = int((~good).sum())
            if first is None:
                first = start + int(np.flatnonzero(~good)[0])
            nbad += bad
            if not drop_nonfinite:
                continue
            block = block[good]
        if len(block) == 0:
            continue
        n += len(block)
        total += block.sum(axis=0)
        lo = np.minimum(lo, block.min(axis=0))
        hi = np.maximum(hi, block.max(axis=0))
        a = np.abs(block)
        small = max(small, float(a.max()))
    if nbad and not drop_nonfinite:
        raise CalibrationError(
            f"{name} has {nbad} row(s) with NaN/inf (first at row {first}); "
            "clean the data or opt in to dropping them (--drop-nonfinite)"
        )
    big = small
    if big > 1e150:
        raise CalibrationError(f"{name} has values of magnitude {big:.3g}: beyond what a fit in "
                               "double precision can square; rescale the readings")
    if 0 < big < 1e-150:
        raise CalibrationError(f"{name} has no value above {big:.3g} in "
                               "magnitude: too small to fit in double precision; rescale")
    src = FilteredSource(source, n) if nbad else source
    if n == 0:
        lo = hi = np.zeros(p)
    return Scan(src, n, nbad, total, lo, hi)


def check_scan_samples(sc: Scan, n_params: int, name: str = "Z",
                       rows_per_channel: bool = True) -> None:
    """:func:`calib.data.validate.check_samples` on the statistics of a scan."""
    check_samples(sc.n, sc.p, sc.min, sc.max, n_params, name, rows_per_channel)


def blocks_of(Y, chunk_rows: int = CHUNK_ROWS):
    """Blocks of an array (slices of ``chunk_rows``) or of a source."""
    if isinstance(Y, ChunkSource):
        for _, block in Y.blocks():
            yield block
    else:
        for i in range(0, len(Y), chunk_rows):
            yield Y[i : i + chunk_rows]


def rows_of(Y) -> int:
    return Y.count() if isinstance(Y, ChunkSource) else len(Y)


def strided_of(Y, step: int) -> np.ndarray:
    return Y.strided(step) if isinstance(Y, ChunkSource) else Y[:: int(step)]


class QR:
    """Streaming (tall-skinny) QR: the R factor of row blocks stacked one after another, so
    least squares over all rows equals ``numpy.linalg.lstsq`` on the whole matrix up to
    rounding (same singular values, same minimum-norm truncation)."""

    def __init__(self) -> None:
        self.R = None
        self.n = 0

    def add(self, A: np.ndarray) -> None:
        if len(A) == 0:
            return
        self.n += len(A)
        if self.R is not None:
            A = np.vstack([self.R, A])
        self.R = np.linalg.qr(A, mode="r")

    def lstsq(self, k: int) -> np.ndarray:
        """Minimum-norm least-squares solution for the first ``k`` columns as the design and the
        others as right-hand sides (``rcond`` as ``numpy.linalg.lstsq``'s default on the whole
        matrix)."""
        R = self.R
        rcond = np.finfo(float).eps * max(self.n, k)
        R11 = np.zeros((k, k))
        R11[: min(len(R), k)] = R[:k, :k]
        R12 = np.zeros((k, R.shape[1] - k))
        R12[: min(len(R), k)] = R[:k, k:]
        x, *_ = np.linalg.lstsq(R11, R12, rcond=rcond)
        return x

    def singular_values(self, k: int | None = None) -> np.ndarray:
        """Singular values of the first ``k`` columns (all if None), as many as
        ``min(n, k)``."""
        R = self.R if k is None else self.R[:, :k]
        s = np.linalg.svd(R, compute_uv=False)
        return s[: min(self.n, R.shape[1])]
