"""Benchmark: a 1e8 x 8 log, larger than memory, calibrated by streaming (centered route).

The rows come chunk by chunk from a seeded simulator (the paper's Trial 3 sensor and noise): a
:class:`calib.data.stream.ChunkSource` whose block k is simulated from seed (seed, k) every time a
pass asks for it, so the 6.4 GB of readings never exist in memory at once. ``fit_bias`` streams
over it (scan, centred Gram, strided subsamples, full-data Gauss-Newton passes, diagnostics).

The named peer is the in-memory fit of a smaller log (default 2e6 x 8, data generated in memory
first) in the same run. Each measurement runs in a fresh subprocess, so the peak resident set
sizes (``resource.getrusage(RUSAGE_SELF).ru_maxrss``: the peak of the whole process, interpreter,
numpy and scipy included) do not mix.

Target: 1e8 x 8 in under 1 GB peak RSS.

    .venv/bin/python benchmarks/calib_stream.py [--rows 1e8] [--peer-rows 2e6] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
import warnings

import numpy as np


def rss_mb() -> float:
    """Peak resident set size of this process so far, MB (Linux reports kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def simulated_source(n: int, seed: int):
    from calib.data.stream import CHUNK_ROWS, ChunkSource
    from calib.simulation.simulate import paper_trial

    class SimulatedSource(ChunkSource):
        """n rows of Trial 3 readings, block k simulated from seed (seed, k) on every pass."""

        canonical = True  # blocks of CHUNK_ROWS rows

        def __init__(self):
            super().__init__()
            self.n, self.p = n, 8
            self.passes = 0
            d = paper_trial(3, rng=seed, n=1)
            self.offset = d.offset

        def _blocks(self):
            self.passes += 1
            for k, i in enumerate(range(0, n, CHUNK_ROWS)):
                m = min(CHUNK_ROWS, n - i)
                yield i, paper_trial(3, rng=[seed, k], n=m).Z

    return SimulatedSource()


def child(kind: str, n: int, seed: int) -> dict:
    from calib.data.result import CalibrationWarning
    from calib.estimators.bias import fit_bias
    from calib.simulation.simulate import paper_trial

    warnings.simplefilter("ignore", CalibrationWarning)
    base = rss_mb()
    if kind == "stream":
        Z = simulated_source(n, seed)
        z0 = Z.offset
    else:
        d = paper_trial(3, rng=seed, n=n)
        Z, z0 = np.ascontiguousarray(d.Z), d.offset
        del d
    t0 = time.perf_counter()
    cal = fit_bias(Z, 3, method="centered")
    t = time.perf_counter() - t0
    return {
        "kind": kind,
        "rows": n,
        "seconds": t,
        "peak_rss_mb": rss_mb(),
        "rss_before_data_mb": base,
        "passes": getattr(Z, "passes", None),
        "offset_mean_abs_error": float(np.mean(np.abs(cal.offset - z0))),
        "n_samples": cal.diagnostics["n_samples"],
        "prior_used": cal.diagnostics["ellipsoid"].get("prior_selection", {}).get("prior_used"),
    }


def measure(kind: str, n: int, seed: int) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", kind, "--rows", str(n),
                          "--seed", str(seed)], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def rows(text: str) -> int:
    return int(float(text))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=rows, default=100_000_000)
    ap.add_argument("--peer-rows", type=rows, default=2_000_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--child", choices=("stream", "memory"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.child, args.rows, args.seed)))
        return
    s = measure("stream", args.rows, args.seed)
    m = measure("memory", args.peer_rows, args.seed)
    gb = args.rows * 8 * 8 / 1e9
    print(f"streamed fit_bias(centered), {args.rows:,} x 8 ({gb:.1f} GB of readings, simulated "
          f"chunk by chunk): {s['seconds']:.1f} s, {s['passes']} passes, peak RSS "
          f"{s['peak_rss_mb']:.0f} MB (process peak; {s['rss_before_data_mb']:.0f} MB after "
          f"imports); target < 1 GB: {'met' if s['peak_rss_mb'] < 1024 else 'MISSED'}; "
          f"offset error {s['offset_mean_abs_error']:.3g}")
    print(f"peer, in-memory fit_bias(centered), {args.peer_rows:,} x 8: {m['seconds']:.2f} s, "
          f"peak RSS {m['peak_rss_mb']:.0f} MB (data {args.peer_rows * 64 / 1e6:.0f} MB, "
          f"generated in the same process); offset error {m['offset_mean_abs_error']:.3g}")
    rate_s = args.rows / s["seconds"]
    rate_m = args.peer_rows / m["seconds"]
    print(f"throughput: streamed {rate_s / 1e6:.2f} M rows/s, in-memory {rate_m / 1e6:.2f} M rows/s"
          f" (ratio {rate_m / rate_s:.2f}x; the stream re-simulates its rows on every pass)")


if __name__ == "__main__":
    main()
