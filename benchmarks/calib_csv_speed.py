"""``calib.io.read_csv`` against its peer ``np.loadtxt`` on the same file, in the same run.

    python benchmarks/calib_csv_speed.py [--rows 2000000] [--cols 8] [--rounds 3]

Each reader runs in a fresh subprocess (so its peak RSS is its own), alternating with the peer,
``--rounds`` times; the medians are reported. Target: within 1.5x of the peer's time and memory
(the row-by-row reader it replaced took 11.8 s and 844 MB for 2M x 8, 15x the peer).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile

import numpy as np

CODE = {
    "calib.io.read_csv": "from calib.io import read_csv; h, d = read_csv(PATH)",
    "np.loadtxt (peer)": "import numpy as np; d = np.loadtxt(PATH, delimiter=',', skiprows=1)",
}
RUNNER = """
import resource, sys, time
PATH = sys.argv[1]
t = time.perf_counter()
{code}
wall = time.perf_counter() - t
print(wall, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, d.shape[0])
"""


def measure(code: str, path: str) -> tuple[float, float]:
    out = subprocess.run([sys.executable, "-c", RUNNER.format(code=code), path],
                         capture_output=True, text=True, check=True).stdout.split()
    return float(out[0]), float(out[1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=2_000_000)
    ap.add_argument("--cols", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "raw.csv")
        data = np.random.default_rng(0).normal(0, 100, (args.rows, args.cols))
        header = ",".join(f"z{i}" for i in range(args.cols))
        np.savetxt(path, data, delimiter=",", header=header, comments="", fmt="%.6g")
        del data
        size_mb = os.path.getsize(path) / 2**20
        results = {name: [] for name in CODE}
        for _ in range(args.rounds):
            for name, code in CODE.items():
                results[name].append(measure(code, path))
    print(f"{args.rows} rows x {args.cols} columns ({size_mb:.0f} MB), median of "
          f"{args.rounds} alternating rounds, each in a fresh process:")
    med = {n: (statistics.median(w for w, _ in r), statistics.median(m for _, m in r))
           for n, r in results.items()}
    for name, (wall, rss) in med.items():
        print(f"  {name:<20} {wall:6.2f} s   peak RSS {rss:6.0f} MB")
    ours, peer = med["calib.io.read_csv"], med["np.loadtxt (peer)"]
    print(f"ratio to the peer: time {ours[0] / peer[0]:.2f}x, memory {ours[1] / peer[1]:.2f}x "
          "(target <= 1.5x each)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
