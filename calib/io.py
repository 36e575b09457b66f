"""File formats: raw/known CSV, calibration JSON, atomic writes."""

from __future__ import annotations

import csv
import json
import os
import tempfile

import numpy as np

from .result import Calibration, CalibrationError

LOAD_COLUMNS = ("Fx", "Fy", "Fz", "Tx", "Ty", "Tz")


def load_columns(dof: int) -> list[str]:
    """Load column names for ``dof``: Fx,Fy | Fx,Fy,Fz | Fx..Tz."""
    return list(LOAD_COLUMNS[: {2: 2, 3: 3, 6: 6}[dof]])


def atomic_write_text(path: str, text: str) -> None:
    """Write ``text`` to ``path`` via a temporary file in the same directory and os.replace."""
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", dir=d)
    try:
        with os.fdopen(fd, "w", newline="") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def read_csv(path: str) -> tuple[list[str], np.ndarray]:
    """Header names and float data (n, k). Unparseable cells are an error; 'nan'/'inf' parse."""
    try:
        with open(path, newline="") as f:
            rows = list(csv.reader(f))
    except OSError as e:
        raise CalibrationError(f"cannot read {path}: {e.strerror}") from None
    rows = [r for r in rows if r and any(c.strip() for c in r)]
    if not rows:
        raise CalibrationError(f"{path} is empty")
    header = [h.strip() for h in rows[0]]
    if len(set(header)) != len(header):
        raise CalibrationError(f"{path}: duplicate column names in header")
    data = np.empty((len(rows) - 1, len(header)))
    for i, r in enumerate(rows[1:], start=2):
        if len(r) != len(header):
            raise CalibrationError(f"{path} line {i}: {len(r)} fields, header has {len(header)}")
        try:
            data[i - 2] = [float(c) for c in r]
        except ValueError:
            raise CalibrationError(f"{path} line {i}: non-numeric value") from None
    return header, data


def write_csv(path: str, header, data: np.ndarray) -> None:
    lines = [",".join(header)]
    lines += [",".join(repr(float(x)) for x in row) for row in np.asarray(data)]
    atomic_write_text(path, "\n".join(lines) + "\n")


def split_known(header, data, channels, dof) -> tuple[np.ndarray, np.ndarray]:
    """From a KNOWN.csv table pick the channel columns (in RAW order) and the load columns."""
    cols = load_columns(dof)
    missing = [c for c in list(channels) + cols if c not in header]
    if missing:
        raise CalibrationError(f"known-load file lacks column(s) {missing}")
    idx = {h: i for i, h in enumerate(header)}
    return data[:, [idx[c] for c in channels]], data[:, [idx[c] for c in cols]]


def save_calibration(path: str, cal: Calibration, channels=None) -> None:
    d = cal.to_dict()
    if channels is not None:
        d["channels"] = list(channels)
    from .result import _jsonable

    atomic_write_text(path, json.dumps(_jsonable(d), indent=2) + "\n")


def load_calibration(path: str) -> tuple[Calibration, list[str] | None]:
    try:
        with open(path) as f:
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
