"""Benchmark: shape from motion with bias on 1,000,000 x 8 samples.

Reports the wall time of ``calib.estimators.bias.fit_bias`` (centered route: Gram-matrix PCA,
chunked
ellipsoid fit) against numpy's own thin SVD of the same matrix measured in the same run, and the
peak extra memory (tracemalloc, which sees numpy's allocations) relative to the input array.

Targets: < 1 s; peak extra memory <= 3x the input array.

    .venv/bin/python benchmarks/calib_speed.py [--n 1000000] [--repeat 5]
"""

from __future__ import annotations

import argparse
import statistics
import time
import tracemalloc
import warnings

import numpy as np

from calib.data.result import CalibrationWarning
from calib.estimators.bias import fit_bias
from calib.simulation.simulate import paper_trial


def make_data(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    d = paper_trial(3, rng=seed, n=n)
    return np.ascontiguousarray(d.Z), d.offset


def median_times(fns, repeat):
    """Median wall time of each function over ``repeat`` alternating rounds, and the last
    outputs (alternating, so background load hits every one alike)."""
    times = [[] for _ in fns]
    outs = [None] * len(fns)
    for _ in range(repeat):
        for k, fn in enumerate(fns):
            t0 = time.perf_counter()
            outs[k] = fn()
            times[k].append(time.perf_counter() - t0)
    return [statistics.median(t) for t in times], outs


def peak_extra_bytes(fn):
    tracemalloc.start()
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    fn()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak - base


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--method", choices=("centered", "paper"), default="centered")
    args = ap.parse_args(argv)

    Z, z0 = make_data(args.n)
    warnings.simplefilter("ignore", CalibrationWarning)

    def sfm():
        return fit_bias(Z, 3, method=args.method)

    def svd():
        return np.linalg.svd(Z, full_matrices=False)

    sfm()  # warm-up (imports, BLAS threads)
    (t_sfm, t_svd), (cal, _) = median_times([sfm, svd], args.repeat)
    mem_sfm = peak_extra_bytes(sfm)
    mem_svd = peak_extra_bytes(svd)
    err = float(np.mean(np.abs(cal.offset - z0)))
    print(f"data: {Z.shape[0]:,} x {Z.shape[1]} float64 ({Z.nbytes / 1e6:.0f} MB), Trial 3 noise")
    print(
        f"calib fit_bias({args.method}): {t_sfm:.3f} s (median of {args.repeat}); "
        f"target < 1 s: {'met' if t_sfm < 1 else 'MISSED'}"
    )
    print(f"numpy thin SVD:           {t_svd:.3f} s; ratio calib / numpy SVD = {t_sfm / t_svd:.2f}")
    print(
        f"peak extra memory: calib {mem_sfm / 1e6:.1f} MB = {mem_sfm / Z.nbytes:.2f}x input "
        f"(target <= 3x: {'met' if mem_sfm <= 3 * Z.nbytes else 'MISSED'}); "
        f"numpy SVD {mem_svd / 1e6:.1f} MB = {mem_svd / Z.nbytes:.2f}x"
    )
    print(f"offset error (mean abs, counts): {err:.4f}")
    return {"t_sfm": t_sfm, "t_svd": t_svd, "mem_ratio": mem_sfm / Z.nbytes, "offset_err": err}


if __name__ == "__main__":
    main()
