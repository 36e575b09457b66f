"""The calibration study: every calibration route x every case, medians and 95th percentiles over
random sensors. Writes its block of docs/calib_study.md (committed) and prints the tables.

    python scripts/calib_study.py [--sensors 200] [--out docs/calib_study.md]

Cases (3-DOF, seeded; sensor k uses seed k):
- motion cases: random 3 x 8 shape (``random_shape``, singular-value ratio uniform 1-10),
  magnitude 10, offsets N(0, 20^2), 176 samples, uniform noise of half-width 0.2 (the
  trials' random-shape set-up), directions over the full sphere or a 90 / 60 degree cap;
  "anisotropic" = the 60 degree cap with the ratio drawn from 5-10;
- p = r: a Gaussian 3 x 3 shape (condition numbers up to the thousands), magnitude 1, offsets
  N(0, 1), 176 samples, Gaussian noise 0.01, full sphere and 90 degree cap;
- static-pose rig: 12 poses of a 3.03 N proof mass, 100 samples each, shape as above x 10
  counts/N, Gaussian noise 0.05, offsets N(0, 20^2); 4 poses have known loads (reading = the
  pose's mean); "spread": the 4 known poses are the most spread of the 12
  (``calib.routes.joint.choose_known_poses``), a rig-design choice.

Routes: least squares with every load known (``bias=True``), centered (auto prior = the
route's default; always prior tau 0.1; no prior), paper (centered and paper whiten their
channels by default), joint (``calib fit --bias`` with 2 or more known loads uses it
by default). Every shape-from-motion route gets 4 known
pairs (motion cases: the first 4 samples with their true loads) for its frame. The joint route
is told the accuracy of its known pairs: single readings in the motion cases
(``known_samples=1``), pose means of 100 readings on the rig (``known_samples=100``).

Metrics: offset error = mean over channels of |offset error| / span, span = the channel's range
in the data (max - min), in %; least squares identifies only C z0, so it has none. Load error =
RMS error on 300 noise-free test loads of the same magnitude over the sphere, in % of the
magnitude. Warned = fraction of fits raising a CalibrationWarning.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from concurrent.futures import ProcessPoolExecutor

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from calib.data.result import CalibrationError, CalibrationWarning  # noqa: E402
from calib.estimators.bias import fit_bias  # noqa: E402
from calib.estimators.least_squares import fit_least_squares  # noqa: E402
from calib.routes.joint import choose_known_poses, fit_joint  # noqa: E402
from calib.simulation.simulate import random_shape, sample_directions, simulate  # noqa: E402

CASES = ["full sphere", "90 deg cap", "60 deg cap", "anisotropic (ratio 5-10), 60 deg",
         "p = r = 3, full sphere", "p = r = 3, 90 deg cap", "static-pose rig, 4 known",
         "static-pose rig, 4 known spread"]
ROUTES = ["least squares, all known", "centered (auto prior)", "centered, prior always",
          "centered, no prior", "paper", "joint (default with known pairs)"]


def make_case(case: str, seed: int):
    rng = np.random.default_rng(seed)
    if case.startswith("p = r"):
        S = rng.normal(size=(3, 3))
        z0 = rng.normal(size=3)
        cap = 90 if "90" in case else None
        d = simulate(S, 176, rng, magnitude=1.0, cap_half_angle_deg=cap, noise=0.01,
                     noise_kind="gaussian", offset=z0)
        Z, M, g = d.Z, d.loads, 1.0
        Zk, Mk = Z[:4], M[:4]
    elif case.startswith("static"):
        S = random_shape(3, 8, rng, condition=rng.uniform(1, 10)) * 10
        z0 = rng.normal(size=8) * 20
        g = 3.03
        F = g * sample_directions(12, 3, rng)
        Z = np.repeat(F @ S + z0, 100, axis=0)
        Z = Z + rng.normal(size=Z.shape) * 0.05
        M = np.repeat(F, 100, axis=0)
        # 4 known poses: the first 4 (random), or the 4 most spread (choose_known_poses)
        known = choose_known_poses(F, 4) if case.endswith("spread") else np.arange(4)
        Zk, Mk = Z.reshape(12, 100, 8)[known].mean(axis=1), F[known]
    else:
        lo = 5 if case.startswith("aniso") else 1
        S = random_shape(3, 8, rng, condition=rng.uniform(lo, 10))
        z0 = rng.normal(size=8) * 20
        cap = {"full sphere": None, "90 deg cap": 90}.get(case, 60)
        g = 10.0
        d = simulate(S, 176, rng, magnitude=g, cap_half_angle_deg=cap, noise=0.2, offset=z0)
        Z, M = d.Z, d.loads
        Zk, Mk = Z[:4], M[:4]
    Ft = g * sample_directions(300, 3, rng)
    return Z, M, Zk, Mk, z0, Ft @ S + z0, Ft, g


def fit_route(route, Z, M, Zk, Mk, single=False):
    if route.startswith("least"):
        return fit_least_squares(Z, M, bias=True)
    if route == "paper":
        return fit_bias(Z, 3, method="paper", known_Z=Zk, known_M=Mk)
    if route.startswith("joint"):
        # the user states how many readings each known reading averages: 1 in the motion
        # cases (single readings), 100 on the rig (pose means)
        return fit_joint(Z, Zk, Mk, known_samples=1 if single else 100)
    prior = {"centered (auto prior)": "auto", "centered, prior always": 0.1,
             "centered, no prior": None}[route]
    return fit_bias(Z, 3, known_Z=Zk, known_M=Mk, isotropy_prior=prior)


def one(args):
    case, seed = args
    Z, M, Zk, Mk, z0, Zt, Ft, g = make_case(case, seed)
    span = Z.max(axis=0) - Z.min(axis=0)
    out = {}
    for route in ROUTES:
        if route == "paper" and Z.shape[1] < 4:
            continue
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always", CalibrationWarning)
            try:
                cal = fit_route(route, Z, M, Zk, Mk, single=not case.startswith("static"))
            except CalibrationError:
                out[route] = (np.nan, np.nan, True, True)
                continue
        off = (np.nan if route.startswith("least")
               else float(np.mean(np.abs(cal.offset - z0) / span)) * 100)
        load = float(np.sqrt(np.mean((cal.apply(Zt) - Ft) ** 2))) / g * 100
        warned = any(issubclass(x.category, CalibrationWarning) for x in w)
        out[route] = (off, load, warned, False)
    return case, seed, out


def fmt(v):
    v = np.asarray(v, float)
    v = v[np.isfinite(v)]
    if not len(v):
        return "n/a"
    return f"{np.median(v):.3g} / {np.percentile(v, 95):.3g}"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sensors", type=int, default=200)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--out", default=os.path.join("docs", "calib_study.md"))
    a = ap.parse_args(argv)
    t0 = time.time()
    jobs = [(c, s) for c in CASES for s in range(a.sensors)]
    res = {c: {r: [] for r in ROUTES} for c in CASES}
    with ProcessPoolExecutor(a.workers) as ex:
        for case, _, out in ex.map(one, jobs, chunksize=8):
            for r, v in out.items():
                res[case][r].append(v)
    L = [f"# calib study: routes x cases ({a.sensors} random sensors per case)", "",
         "Produced by `python scripts/calib_study.py` (set-up in its docstring). Cells: median / "
         "95th percentile. Offset error in % of the channel's span in the data (mean over "
         "channels); load error = RMS on 300 noise-free test loads in % of the load magnitude; "
         "warned = fits raising a CalibrationWarning; failed = fits refused with an error.", ""]
    for metric, k in (("Offset error (% of span)", 0), ("Load error (% of magnitude)", 1)):
        L += [f"## {metric}", "", "| case | " + " | ".join(ROUTES) + " |",
              "|---" * (len(ROUTES) + 1) + "|"]
        for c in CASES:
            L.append(f"| {c} | " + " | ".join(fmt([v[k] for v in res[c][r]]) if res[c][r]
                                               else "n/a" for r in ROUTES) + " |")
        L.append("")
    L += ["## Warned / failed (% of fits)", "", "| case | " + " | ".join(ROUTES) + " |",
          "|---" * (len(ROUTES) + 1) + "|"]
    for c in CASES:
        cells = []
        for r in ROUTES:
            v = res[c][r]
            cells.append(f"{100 * np.mean([x[2] for x in v]):.0f} / "
                         f"{100 * np.mean([x[3] for x in v]):.0f}" if v else "n/a")
        L.append(f"| {c} | " + " | ".join(cells) + " |")
    L += ["", f"Run time {time.time() - t0:.0f} s with {a.workers} worker(s)."]
    text = "\n".join(L) + "\n"
    from sfm_common.files import atomic_write_text

    # the study's own block of a.out (the other studies keep theirs: calib_rig_study,
    # calib_payload_study, calib_low_signal write between their own markers)
    begin, end = "<!-- calib_study:begin -->", "<!-- calib_study:end -->"
    old = ""
    if os.path.exists(a.out):
        with open(a.out, encoding="utf-8") as f:
            old = f.read()
    if begin in old and end in old:
        head, rest = old.split(begin, 1)
        atomic_write_text(a.out, head + begin + "\n" + text + end + rest.split(end, 1)[1])
    else:
        atomic_write_text(a.out, begin + "\n" + text + end + "\n" + old)
    print(text)


if __name__ == "__main__":
    main()
