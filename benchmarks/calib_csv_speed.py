"""``calib.data.io.read_csv`` against its peer ``np.loadtxt`` on the same file, in the same run.

    python benchmarks/calib_csv_speed.py [--rows 2000000] [--cols 8] [--rounds 3] [--with-old]

Each reader runs in a fresh subprocess (so its peak RSS is its own), alternating with the peer,
``--rounds`` times; the medians are reported. Peak RSS includes the imports: ``calib.data.io``
imports
the calib package (scipy), about 50 MB more than numpy alone, so the "read" column (peak minus the
RSS after the imports) is the cost of reading itself. Target: within 1.5x of the peer's time and
peak memory. ``--with-old`` also runs the row-by-row reader ``read_csv`` replaced (csv.reader and
a Python loop; 11.8 s and 844 MB for 2M x 8 when it was replaced, 15x the peer) and ``read_csv``
on the same file with its last row damaged (the careful fallback, which names the bad line).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

OURS, PEER = "calib.data.io.read_csv", "np.loadtxt (peer)"
CODE = {
    OURS: ("from calib.data.io import read_csv", "h, d = read_csv(PATH)"),
    PEER: ("import numpy as np", "d = np.loadtxt(PATH, delimiter=',', skiprows=1)"),
}
# The reader calib.data.io.read_csv had before the numpy fast path (git 762913c^), for --with-old.
OLD_READER = '''
import csv
import numpy as np
def old_read_csv(path):
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    rows = [r for r in rows if r and any(c.strip() for c in r)]
    header = [h.strip() for h in rows[0]]
    data = np.empty((len(rows) - 1, len(header)))
    for i, r in enumerate(rows[1:], start=2):
        if len(r) != len(header):
            raise ValueError(f"line {i}: {len(r)} fields")
        data[i - 2] = [float(c) for c in r]
    return header, data
'''
EXTRA = {
    "row-by-row (old)": (OLD_READER, "h, d = old_read_csv(PATH)"),
    "read_csv, bad last row": (
        "from calib.data.io import read_csv\nfrom calib.data.result import CalibrationError",
        "try:\n    read_csv(PATH_BAD)\nexcept CalibrationError as e:\n    d = e",
    ),
}
# Peak RSS is VmHWM from /proc/self/status: getrusage's ru_maxrss survives execve on Linux, so in
# a child it starts at the parent's peak (this script's, holding the generated data), not at 0.
RUNNER = """
import resource, sys, time
def peak_mb():
    try:
        with open("/proc/self/status") as f:
            return next(int(x.split()[1]) for x in f if x.startswith("VmHWM:")) / 1024
    except (OSError, StopIteration):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
sys.path.insert(0, {root!r})
PATH, PATH_BAD = sys.argv[1], sys.argv[2]
{imports}
base = peak_mb()
t = time.perf_counter()
{code}
wall = time.perf_counter() - t
peak = peak_mb()
print(wall, peak, base, repr(d.shape if hasattr(d, "shape") else str(d)))
"""


def measure(name: str, reader: tuple[str, str], path: str, bad: str) -> tuple[float, float, float]:
    imports, code = reader
    out = subprocess.run(
        [sys.executable, "-c", RUNNER.format(root=ROOT, imports=imports, code=code), path, bad],
        capture_output=True, text=True, check=True).stdout.split(maxsplit=3)
    if name == "read_csv, bad last row" and "line" not in out[3]:
        raise SystemExit(f"the damaged file was not refused with its line: {out[3]}")
    return float(out[0]), float(out[1]), float(out[2])


def ratio(a: float, b: float) -> str:
    return f"{a / b:.2f}x" if b >= 1 else "n/a (the peer's is under 1 MB)"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=2_000_000)
    ap.add_argument("--cols", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--with-old", action="store_true",
                    help="also the replaced row-by-row reader and the fallback on a bad last row")
    args = ap.parse_args()
    readers = dict(CODE, **(EXTRA if args.with_old else {}))
    with tempfile.TemporaryDirectory() as tmp:
        path, bad = os.path.join(tmp, "raw.csv"), os.path.join(tmp, "bad.csv")
        data = np.random.default_rng(0).normal(0, 100, (args.rows, args.cols))
        header = ",".join(f"z{i}" for i in range(args.cols))
        np.savetxt(path, data, delimiter=",", header=header, comments="", fmt="%.6g")
        del data
        if args.with_old:
            with open(path, "rb") as src, open(bad, "wb") as dst:
                dst.write(src.read())
                dst.write(b"1,x" + b",1" * (args.cols - 2) + b"\n")
        size_mb = os.path.getsize(path) / 2**20
        results = {name: [] for name in readers}
        for _ in range(args.rounds):
            for name, reader in readers.items():
                results[name].append(measure(name, reader, path, bad))
    print(f"{args.rows} rows x {args.cols} columns ({size_mb:.0f} MB), median of "
          f"{args.rounds} alternating rounds, each in a fresh process:")
    med = {n: tuple(statistics.median(x[i] for x in r) for i in range(3))
           for n, r in results.items()}
    for name, (wall, peak, base) in med.items():
        print(f"  {name:<24} {wall:6.2f} s   peak RSS {peak:6.0f} MB   "
              f"(imports {base:4.0f} MB, read {peak - base:5.0f} MB)")
    ours, peer = med[OURS], med[PEER]
    print(f"ratio to the peer: time {ours[0] / peer[0]:.2f}x, "
          f"peak memory {ours[1] / peer[1]:.2f}x, "
          f"memory for reading {ratio(ours[1] - ours[2], peer[1] - peer[2])} "
          "(target <= 1.5x each)")
    if args.with_old:
        old = med["row-by-row (old)"]
        print(f"the replaced reader: {old[0] / ours[0]:.1f}x the time and {old[1] / ours[1]:.1f}x "
              f"the peak memory of read_csv ({old[0] / peer[0]:.1f}x / {old[1] / peer[1]:.1f}x "
              "the peer)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
