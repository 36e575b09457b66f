"""Low-signal study: shape from motion with bias on sensors whose shortest load axis has a
signal-to-noise ratio of 20-50, directions within a 60 degree cap, 4 known pairs.

    python scripts/calib_low_signal.py [--sensors 200] [--workers 2] [--doc docs/calib_study.md]

Generator (independent of ``calib_study.py``'s, seeds 20,000 + k): a random 3 x 8 shape
(``random_shape``, singular-value ratio uniform 1-10) with each channel scaled by e^U(-2, 2);
offsets N(0, (20 x the channel's largest coefficient)^2); load magnitude 10; 176 readings over a
60 degree cap; Gaussian noise per channel, relative levels uniform 1-3 (times the channel's
norm), scaled so that the shortest load axis's signal over the rms noise, ``g s_min / rms(sd)``,
is uniform in 20-50. The first 4 readings are the known pairs (single readings).

Routes: ``joint`` (``calib fit --bias --known`` default: the maximum-likelihood forward fit),
``centered`` (whitened, auto prior) and ``paper``. Metrics:

- offset error: mean over channels of |error| / span (the data's range), in %; beside it the
  Cramer-Rao bound: per sensor 20 draws from the bound's offset covariance (the forward model's
  inverse Schur complement at the true parameters and noise), the same metric, pooled;
- "> 20 % silent": fits with a channel more than 20 % of its span off that ``calib fit`` would
  accept (``calib.verdict.reliability.assess`` empty) without a warning naming that channel;
- coverage: share of channel offsets whose error is within 1.96 of their stated standard errors
  (nominal 95 %);
- warned / refused: share of fits with any CalibrationWarning / an unreliable verdict (exit 3).
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import time
import warnings
from concurrent.futures import ProcessPoolExecutor

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from calib.data.result import CalibrationError, CalibrationWarning  # noqa: E402
from calib.estimators.bias import fit_bias  # noqa: E402
from calib.estimators.forward.problem import Problem, curvature
from calib.estimators.forward.refits import _global_cov  # noqa: E402
from calib.routes.joint import fit_joint  # noqa: E402
from calib.simulation.simulate import random_shape, sample_directions  # noqa: E402
from calib.verdict.reliability import assess  # noqa: E402

ROUTES = ("joint", "centered", "paper")
BEGIN, END = "<!-- calib_low_signal:begin -->", "<!-- calib_low_signal:end -->"


def make_sensor(seed: int, n: int = 176, p: int = 8, cap: float = 60.0):
    rng = np.random.default_rng(20_000 + seed)
    S = random_shape(3, p, rng, condition=rng.uniform(1, 10)) * np.exp(rng.uniform(-2, 2, p))
    z0 = rng.normal(size=p) * 20 * np.abs(S).max(axis=0)
    g = 10.0
    U = sample_directions(n, 3, rng, cap_half_angle_deg=cap)
    smin = np.linalg.svd(S, compute_uv=False)[-1]
    snr = rng.uniform(20, 50)
    rel = rng.uniform(1, 3, p) * np.linalg.norm(S, axis=0) / np.linalg.norm(S, axis=0).mean()
    sd = rel / np.sqrt(np.mean(rel**2)) * g * smin / snr
    Z = g * U @ S + z0 + rng.normal(size=(n, p)) * sd
    return S, z0, g, U, Z, sd


def bound_cov(S, z0, g, U, Z, sd, k: int = 4) -> np.ndarray:
    """The Cramer-Rao bound of the offsets: the forward model at the true parameters."""
    pr = Problem(Z, None, None, np.arange(k), g * U[:k], magnitude=g)
    fit = {"A": S.T.copy(), "o": z0.copy(), "g": g, "U": U[k:],
           "W": np.broadcast_to(1 / sd, Z.shape).copy()}
    fit.update(curvature(pr, fit))
    cov = _global_cov(fit)
    idx = [c * 4 + 3 for c in range(len(z0))]
    return cov[np.ix_(idx, idx)]


def one(seed: int) -> dict:
    S, z0, g, U, Z, sd = make_sensor(seed)
    span = Z.max(axis=0) - Z.min(axis=0)
    L = np.linalg.cholesky(bound_cov(S, z0, g, U, Z, sd))
    rng = np.random.default_rng(seed)
    out = {"bound": [float(np.mean(np.abs(L @ rng.standard_normal(len(z0))) / span)) * 100
                     for _ in range(20)]}
    Zk, Mk = Z[:4], g * U[:4]
    for route in ROUTES:
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always", CalibrationWarning)
            try:
                if route == "joint":
                    cal = fit_joint(Z, Zk, Mk, known_samples=1)
                else:
                    cal = fit_bias(Z, 3, method=route, known_Z=Zk, known_M=Mk)
            except CalibrationError:
                out[route] = None
                continue
            problems = assess(cal, Zk, Mk)
        err = np.abs(cal.offset - z0) / span * 100
        se = np.asarray(cal.diagnostics.get("offset_stderr", np.full(len(z0), np.nan)), float)
        msgs = [str(x.message) for x in w if issubclass(x.category, CalibrationWarning)]
        named = {int(c) for m in msgs + problems for c in re.findall(r"channel (\d+)", m)}
        bad = [int(c) for c in np.flatnonzero(err > 20)]
        out[route] = {"offset": float(err.mean()),
                      "silent_bad": bool(bad and not problems and not set(bad) <= named),
                      "covered": np.abs(cal.offset - z0) <= 1.96 * se,
                      "warned": bool(msgs), "refused": bool(problems)}
    return out


def table(res: list[dict]) -> str:
    b = np.concatenate([r["bound"] for r in res])
    bmed, b95 = float(np.median(b)), float(np.percentile(b, 95))
    lines = ["| route | offset error median / p95 (% of span) | p95 / bound's p95 | "
             "> 20 % silent | stderr coverage (nominal 95 %) | warned | refused (exit 3) |",
             "|---|---|---|---|---|---|---|",
             f"| Cramer-Rao bound | {bmed:.3g} / {b95:.3g} | 1 | | | | |"]
    for route in ROUTES:
        v = [r[route] for r in res if r[route] is not None]
        off = np.array([x["offset"] for x in v])
        cov = np.concatenate([x["covered"] for x in v])
        lines.append(
            f"| {route} | {np.median(off):.3g} / {np.percentile(off, 95):.3g} | "
            f"{np.percentile(off, 95) / b95:.2f} | {sum(x['silent_bad'] for x in v)} | "
            f"{cov.mean():.1%} | {np.mean([x['warned'] for x in v]):.0%} | "
            f"{np.mean([x['refused'] for x in v]):.0%} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sensors", type=int, default=200, help="sensors (default 200)")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                    help="processes (default: every core)")
    ap.add_argument("--doc", default=os.path.join("docs", "calib_study.md"),
                    help="markdown file whose calib_low_signal markers get the table "
                    "(default docs/calib_study.md; '' prints only)")
    a = ap.parse_args(argv)
    t0 = time.time()
    with ProcessPoolExecutor(a.workers) as ex:
        res = list(ex.map(one, range(a.sensors), chunksize=4))
    block = (f"Produced by `python scripts/calib_low_signal.py --sensors {a.sensors}` (set-up in "
             f"its docstring), {time.time() - t0:.0f} s with {a.workers} worker(s).\n\n"
             + table(res))
    print(block)
    if a.doc:
        with open(a.doc) as f:
            text = f.read()
        if BEGIN in text and END in text:
            i, j = text.index(BEGIN) + len(BEGIN), text.index(END)
            text = text[:i] + "\n" + block + "\n" + text[j:]
        else:
            text += ("\n## Low signal, 60 degree cap\n\n" + BEGIN + "\n" + block
                     + "\n" + END + "\n")
        tmp = a.doc + ".tmp"
        with open(tmp, "w") as f:
            f.write(text)
        os.replace(tmp, a.doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
