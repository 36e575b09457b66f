"""File formats: raw/known CSV and calibration JSON (written atomically by
:mod:`sfm_common.files`)."""

from __future__ import annotations

import csv
import itertools
import json
import os
import stat
import warnings
from array import array

import numpy as np

from calib.data.result import Calibration, CalibrationError
from calib.data.stream import ChunkSource
from sfm_common.cli import one_line
from sfm_common.files import atomic_write_text

#: Decision: docs/calib_design.md D1.
LOAD_COLUMNS = ("Fx", "Fy", "Fz", "Tx", "Ty", "Tz")


def load_columns(dof: int) -> list[str]:
    """Load column names for ``dof``: Fx,Fy | Fx,Fy,Fz | Fx..Tz."""
    return list(LOAD_COLUMNS[: {2: 2, 3: 3, 6: 6}[dof]])


def open_regular(path, **text_options):
    """``open(path, "r", **text_options)``, refusing (one-line :class:`CalibrationError`) what
    is not a regular file: a directory, device, socket, or a FIFO, which would block the command
    until someone writes to it. The file is opened non-blocking and checked with ``fstat`` on the
    open descriptor, so nothing can be swapped in between the check and the read. A missing or
    unreadable file raises ``OSError`` as ``open`` does."""
    path = os.fspath(path)
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise CalibrationError(f"{path} is not a regular file (a directory, FIFO or device)")
        if getattr(os, "O_NONBLOCK", 0):
            os.set_blocking(fd, True)
        return open(fd, **text_options)
    except BaseException:
        os.close(fd)
        raise


def _open_csv(path):
    # utf-8-sig: a byte-order mark (CSV saved by Excel) is not part of the first name
    return open_regular(path, newline="", encoding="utf-8-sig")


def read_csv(path: str) -> tuple[list[str], np.ndarray]:
    """Header names and float data (n, k). Unparseable cells are an error; 'nan'/'inf' parse.

    Well-formed files go through numpy's C parser (``np.loadtxt``, about its speed and memory:
    ``benchmarks/calib_csv_speed.py``); a file it rejects is read again row by row, to name the
    first bad line (its line number in the file) or to accept what Python's ``csv``/``float``
    accept and numpy does not (quoted numbers, ``1_000``).
    """
    try:
        with _open_csv(path) as f:
            header, skipped = _read_header(f, path)
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", UserWarning)  # "input contained no data"
                    # comments=None: a '#' is a bad value, as in the row-by-row reader, not a
                    # silently dropped row
                    data = np.loadtxt(f, delimiter=",", dtype=float, ndmin=2, comments=None)
            except ValueError:  # includes UnicodeDecodeError: the careful reader reports it
                data = None
        if data is not None and data.size == 0:
            data = data.reshape(0, len(header))
        if data is None or data.shape[1] != len(header):
            data = _read_rows_slowly(path, len(header), skipped)
    except OSError as e:
        raise CalibrationError(f"cannot read {path}: {e.strerror}") from None
    except UnicodeDecodeError:
        raise CalibrationError(f"{path} is not a text CSV file") from None
    except csv.Error as e:  # e.g. a field over csv.field_size_limit()
        raise CalibrationError(f"{path}: not a readable CSV file ({one_line(e)})") from None
    return header, data


def _read_header(f, path: str) -> tuple[list[str], int]:
    """The header names of an open CSV and the physical lines up to and including it.

    The first line that is not blank is the header: one name per column, every name non-empty,
    printable, not a number (a file whose first line holds numbers has no header; its first
    reading would be taken for channel names) and used once. Surrounding spaces and a leading
    byte-order mark are not part of a name. Anything else is a one-line
    :class:`CalibrationError`."""
    header_line = ""
    skipped = 0  # physical lines up to and including the header
    for header_line in f:
        skipped += 1
        if header_line.strip(" \t\r\n\ufeff"):
            break
    else:
        raise CalibrationError(f"{path} is empty")
    header = [h.strip().lstrip("\ufeff").strip()
              for h in next(csv.reader([header_line.lstrip(" \t\ufeff")]))]
    check_header(header, f"{path} line {skipped}")
    return header, skipped


def check_header(names, where: str) -> None:
    """One-line :class:`CalibrationError` unless ``names`` are a header of non-empty, printable,
    non-numeric, unique column names (``where`` starts the message)."""
    hint = "the first line must name every column, e.g. g0,g1,g2"
    empty = [i + 1 for i, h in enumerate(names) if not h]
    if len(empty) == len(names):
        raise CalibrationError(f"{where}: the header has no column names; {hint}")
    if empty:
        raise CalibrationError(f"{where}: header column {empty[0]} has no name; {hint}")
    numbers = [h for h in names if _is_number(h)]
    if numbers:
        what = ("holds numbers, not column names" if len(numbers) == len(names)
                else f"has a number {numbers[0][:40]!r} for a column name")
        raise CalibrationError(f"{where}: no header: the first line {what}; {hint}")
    odd = next((h for h in names if not h.isprintable()), None)
    if odd is not None:
        raise CalibrationError(f"{where}: column name {odd[:40]!r} holds an invisible or control "
                               "character")
    seen: set[str] = set()
    for h in names:
        if h in seen:
            raise CalibrationError(f"{where}: duplicate column names in the header "
                                   f"({h[:40]!r} twice)")
        seen.add(h)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


class CSVSource(ChunkSource):
    """A CSV file read ``chunk_rows`` lines at a time, a :class:`calib.data.stream.ChunkSource`:
    each pass reads the file again and holds one chunk in memory, so a log larger than memory can be
    fitted (``calib fit --chunk-rows``). The header is read (and checked) at once; a bad row is
    the same one-line error as :func:`read_csv`'s, found when a pass reaches it."""

    def __init__(self, path: str, chunk_rows: int = 1 << 17, progress: bool = False) -> None:
        super().__init__()
        self.progress = bool(progress)  # a bar per pass (rows read), drawn on a terminal only
        self._passes = 0
        self._rows: int | None = None  # data rows, known once a pass has read the whole file
        if int(chunk_rows) < 1:
            raise CalibrationError(f"chunk_rows must be positive, got {chunk_rows}")
        self.path = path
        self.chunk_rows = int(chunk_rows)
        with self._open() as f:
            self.header, self.skipped = self._guard(lambda: _read_header(f, path))
        self.p = len(self.header)

    def _open(self):
        try:
            return _open_csv(self.path)
        except OSError as e:
            raise CalibrationError(f"cannot read {self.path}: {e.strerror}") from None

    def _guard(self, fn):
        try:
            return fn()
        except OSError as e:
            raise CalibrationError(f"cannot read {self.path}: {e.strerror}") from None
        except UnicodeDecodeError:
            raise CalibrationError(f"{self.path} is not a text CSV file") from None
        except csv.Error as e:
            raise CalibrationError(f"{self.path}: not a readable CSV file ({one_line(e)})") \
                from None

    def _blocks(self):
        from sfm_common.progress import NullBar
        from sfm_common.progress import progress as progress_bar

        self._passes += 1
        if self.progress:  # rows; the total is known from the second pass on
            bar = progress_bar(self._rows, f"pass {self._passes}", unit="row", unit_scale=True)
        else:
            bar = NullBar()
        with bar, self._open() as f:
            yield from self._read_blocks(f, bar)

    def _read_blocks(self, f, bar):
        k, path = self.p, self.path
        try:
            for _ in range(self.skipped):
                next(f)
            line = self.skipped + 1  # file line number of the chunk's first line
            start = 0
            while True:
                lines = list(itertools.islice(f, self.chunk_rows))
                if not lines:
                    self._rows = start
                    return
                try:
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore", UserWarning)
                        data = np.loadtxt(lines, delimiter=",", dtype=float, ndmin=2,
                                          comments=None)
                except ValueError:
                    data = None
                if data is not None and data.size == 0:
                    data = data.reshape(0, k)
                extra = 0
                if data is None or data.shape[1] != k:
                    data, extra = _parse_lines(lines, f, k, path, line)
                line += len(lines) + extra
                bar.update(len(data))
                yield start, data
                start += len(data)
        except OSError as e:
            raise CalibrationError(f"cannot read {path}: {e.strerror}") from None
        except UnicodeDecodeError:
            raise CalibrationError(f"{path} is not a text CSV file") from None


def _parse_lines(lines, f, k: int, path: str, line0: int) -> tuple[np.ndarray, int]:
    """The careful reader on one chunk of ``lines`` (starting at file line ``line0``); a quoted
    field that runs past the chunk takes further lines from ``f``. Returns (rows, number of
    extra lines taken)."""
    values = array("d")
    reader = csv.reader(itertools.chain(lines, f))
    line = line0
    try:
        while reader.line_num < len(lines):
            r = next(reader, None)
            if r is None:
                break
            if any(c.strip() for c in r):
                if len(r) != k:
                    raise CalibrationError(f"{path} line {line}: {len(r)} fields, header has {k}")
                try:
                    values.extend([float(c) for c in r])
                except ValueError:
                    raise CalibrationError(f"{path} line {line}: non-numeric value") from None
            line = line0 + reader.line_num
    except csv.Error as e:
        raise CalibrationError(f"{path} line {line}: {one_line(e)}") from None
    return np.frombuffer(values, dtype=float).reshape(-1, k), max(reader.line_num - len(lines), 0)


def _read_rows_slowly(path: str, k: int, skipped: int) -> np.ndarray:
    """The careful reader: one Python row at a time after the header's ``skipped`` lines, for the
    file line number of the first bad row. Values go to a flat ``array('d')`` (8 bytes each), so
    a large file read this way costs its data, not a list of Python rows."""
    values = array("d")
    with _open_csv(path) as f:
        for _ in range(skipped):
            next(f)
        reader = csv.reader(f)
        line = skipped + 1  # where the next row starts (a quoted field may span lines)
        try:
            for r in reader:
                if any(c.strip() for c in r):  # else a blank line (or only commas/spaces)
                    if len(r) != k:
                        raise CalibrationError(f"{path} line {line}: {len(r)} fields, header "
                                               f"has {k}")
                    try:
                        values.extend([float(c) for c in r])
                    except ValueError:
                        raise CalibrationError(f"{path} line {line}: non-numeric value") from None
                line = skipped + reader.line_num + 1
        except csv.Error as e:
            raise CalibrationError(f"{path} line {line}: {one_line(e)}") from None
    return np.frombuffer(values, dtype=float).reshape(-1, k)


def write_csv(path: str, header, data: np.ndarray) -> None:
    lines = [",".join(header)]
    lines += [",".join(repr(float(x)) for x in row) for row in np.asarray(data)]
    atomic_write_text(path, "\n".join(lines) + "\n")


def split_known(header, data, channels, dof) -> tuple[np.ndarray, np.ndarray]:
    """From a KNOWN.csv table pick the channel columns (in RAW order) and the load columns."""
    cols = load_columns(dof)
    clash = [c for c in channels if c in cols]
    if clash:  # e.g. a wrench sensor's channels named Fx..Tz: the loads would be read as them
        raise CalibrationError(
            f"channel name(s) {clash} are also load column names ({','.join(cols)} hold the "
            "known loads): rename the sensor's channels in both files (e.g. raw_Fx)")
    missing = [c for c in list(channels) + cols if c not in header]
    if missing:
        raise CalibrationError(f"known-load file lacks column(s) {missing}")
    idx = {h: i for i, h in enumerate(header)}
    return data[:, [idx[c] for c in channels]], data[:, [idx[c] for c in cols]]


def save_calibration(path: str, cal: Calibration, channels=None) -> None:
    d = cal.to_dict()
    if channels is not None:
        d["channels"] = list(channels)
    from calib.data.result import _jsonable

    atomic_write_text(path, json.dumps(_jsonable(d), indent=2) + "\n")


def load_calibration(path: str) -> tuple[Calibration, list[str] | None]:
    try:
        f = open_regular(path, encoding="utf-8")
    except OSError as e:
        raise CalibrationError(f"cannot read {path}: {e.strerror}") from None
    try:
        with f:
            d = json.load(f)
    except OSError as e:
        raise CalibrationError(f"cannot read {path}: {e.strerror}") from None
    except json.JSONDecodeError as e:
        raise CalibrationError(f"{path} is not valid JSON (line {e.lineno})") from None
    except (UnicodeDecodeError, ValueError):
        raise CalibrationError(f"{path} is not a text JSON file") from None
    if not isinstance(d, dict):
        raise CalibrationError(f"{path} does not hold a calibration object")
    try:
        cal = Calibration.from_dict(d)
    except CalibrationError as e:
        raise CalibrationError(f"{path}: {e}") from None
    channels = d.get("channels")
    if channels is not None and not (
            isinstance(channels, list) and all(isinstance(c, str) for c in channels)
            and len(set(channels)) == len(channels) == cal.n_channels):
        raise CalibrationError(f"{path}: channels must be {cal.n_channels} distinct names, one "
                               "per column of C")
    return cal, channels
