"""Every route on a real 3D-printed 8-channel force sensor, with the real-rig protocol.

Data (not shipped: the repository has no licence file): github.com/jonurce/FTS_Calibration,
``Datasets/12_final_extra_bounded/data/data_<set>.0_R.._P.._Y...csv``: five load sets (a mass at
five positions; about 3 N in set 0, 10 N in the others), 12 static poses each, about 2,000 samples
per pose; columns ``Timestamp,Fx,Fy,Fz,Mx,My,Mz,s0..s7`` (a reference F/T sensor's load and the
printed sensor's 8 channels, integer counts). Fetch it yourself and point ``--data`` at the folder.

Protocol: every ``--stride``-th sample of every pose is kept (7: about 285 of 2,000, "a few
hundred samples per pose"), then even samples of every pose train, odd ones test
(``--split halves``: first and second half); the test target is the reference load, and the
error is the held-out load rms, ``sqrt(mean |m_hat - m|^2)`` in N. Least squares with every load
known (per-row loads, affine) is the reference; ``least squares, channel`` is the same data under
the ``channel`` model (each channel straightened by its own square; below 1x means the model
fits this sensor better than affine). The joint route gets the training rows in pose order and 4
known pose means on the poses :func:`calib.routes.joint.choose_known_poses` recommends (from the
reference load directions; ``--known-poses first`` takes the first 4 instead, a fixed choice);
centered and paper routes get the same 4 known loads. Prints per set the held-out rms of least
squares and each route's ratio to it, and whether ``calib fit`` would exit 3.

    python scripts/calib_real_rig.py --data DIR [--stride S] [--split alternate|halves]
                                   [--known K] [--known-poses recommended|first] [--diagnose]

``--diagnose`` adds, per set, where the joint route's error comes from (true pose labels): the
pose fit's chosen optimum against the one reached from the *true* directions of the unknown poses
(a search failure would show as a lower cost there); the best an affine forward model and one
with two shared quadratic forms can do (fitted with all 12 loads known, then the 8 unknown
directions re-inferred from it on their spheres); and a full quadratic forward model started from
the true directions (identifiable or not).
"""

from __future__ import annotations

import argparse
import glob
import os
import sys
import warnings

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from calib.estimators.bias import fit_bias  # noqa: E402
from calib.estimators.least_squares import fit_least_squares  # noqa: E402
from calib.estimators.models import fit_model  # noqa: E402
from calib.estimators.rig.fit import rig_pose_loads  # noqa: E402
from calib.estimators.rig.model import ForwardModel, IndexModel  # noqa: E402
from calib.routes.crosscheck import crosscheck  # noqa: E402
from calib.routes.joint import choose_known_poses, fit_joint  # noqa: E402
from calib.verdict.reliability import assess  # noqa: E402


def load_set(folder: str, k: int):
    files = sorted(glob.glob(os.path.join(folder, f"data_{k}.0_*.csv")))
    if not files:
        return None
    blocks = [np.genfromtxt(f, delimiter=",", skip_header=1) for f in files]
    Z = np.vstack([b[:, 7:15] for b in blocks])
    M = np.vstack([b[:, 1:4] for b in blocks])
    pose = np.concatenate([np.full(len(b), j) for j, b in enumerate(blocks)])
    within = np.concatenate([np.arange(len(b)) for b in blocks])
    count = np.concatenate([np.full(len(b), len(b)) for b in blocks])
    return Z, M, pose, within, count


def _traceless(M, g):
    """The 5 quadratic forms of a load that are not constant on a sphere of radius g."""
    x, y, z = (np.asarray(M) / g).T
    return np.column_stack([x * x - y * y, x * x + y * y - 2 * z * z, x * y, x * z, y * z])


class _QuadraticForward(ForwardModel):
    """zbar = A m + o + Q q(m) per channel (q: the traceless quadratic forms): the most a
    second-order sensor model adds; used only to show whether it is identifiable here."""

    def linear(self, M, W):
        pd = self.pd
        X = np.column_stack([M, np.ones(pd.P), _traceless(M, self.magnitude)])
        R = np.empty_like(pd.means)
        for c in range(pd.p):
            b = np.linalg.lstsq(X * W[:, c:c + 1], pd.means[:, c] * W[:, c], rcond=None)[0]
            R[:, c] = (pd.means[:, c] - X @ b) * W[:, c]
        return None, R


def _reinferred(loads, means, kn, rank: int, seed: int = 0):
    """The pose loads a forward model fitted with *every* load known gives back for the poses
    not in ``kn``: each direction re-inferred on the sphere of its weighed magnitude, channels
    weighted by the model's own residual spread. ``rank`` 0: affine; r > 0: plus r shared
    traceless quadratic forms of the load with a gain per channel (fitted by alternating least
    squares)."""
    from scipy.optimize import least_squares

    P = len(loads)
    g = float(np.median(np.linalg.norm(loads, axis=1)))
    X = np.column_stack([loads, np.ones(P)])
    T = _traceless(loads, g)
    C = np.random.default_rng(seed).standard_normal((5, rank))
    for _ in range(200 if rank else 0):  # forms C given the gains, gains given the forms
        Bb = np.linalg.lstsq(np.column_stack([X, T @ C]), means, rcond=None)[0]
        R = means - X @ Bb[:4]
        C = np.linalg.lstsq(np.kron(Bb[4:].T, T), R.reshape(-1, order="F"),
                            rcond=None)[0].reshape(5, rank, order="F")
    B = np.linalg.lstsq(np.column_stack([X, T @ C]), means, rcond=None)[0]

    def model(m):
        m = np.atleast_2d(m)
        return np.column_stack([m, np.ones(len(m)), _traceless(m, g) @ C]) @ B

    w = 1.0 / np.maximum((means - model(loads)).std(axis=0), 1e-12)
    est = loads.copy()
    for j in np.setdiff1d(np.arange(P), kn):
        mag = np.linalg.norm(loads[j])

        def fun(th, j=j, mag=mag):
            u = [np.cos(th[0]) * np.cos(th[1]), np.cos(th[0]) * np.sin(th[1]), np.sin(th[0])]
            return (model(mag * np.asarray(u))[0] - means[j]) * w

        best = None
        for s in range(12):  # starts spread over the sphere
            u = np.random.default_rng(s).standard_normal(3)
            u /= np.linalg.norm(u)
            r = least_squares(fun, [np.arcsin(u[2]), np.arctan2(u[1], u[0])])
            if best is None or r.cost < best.cost:
                best = r
        a, b = best.x
        est[j] = mag * np.array([np.cos(a) * np.cos(b), np.cos(a) * np.sin(b), np.sin(a)])
    return est


def diagnose(Z, M, pose, tr, te, loads, means, kn, base) -> str:
    """One line: where the joint route's error comes from on this set (see the docstring)."""
    def ratio(pose_loads):
        cal = fit_least_squares(Z[tr], pose_loads[pose][tr], bias=True)
        return float(np.sqrt(np.mean(np.sum((cal.apply(Z[te]) - M[te]) ** 2, axis=1)))) / base

    s1 = rig_pose_loads(Z[tr], pose[tr], means[kn], loads[kn])
    pd, fin, W2 = s1["pd"], s1["final"], s1["W2"]
    truth = loads[pd.unknown] / np.linalg.norm(loads[pd.unknown], axis=1, keepdims=True)
    idx = s1["index"]
    chosen = (f"index model, degree {idx['degree']}" if idx.get("used")
              else "bent" if s1["bend"].get("used") else "affine")
    parts = [f"chosen ({chosen}) {ratio(fin['M']):.2f}x cost {fin['cost']:.3g}"]
    if idx.get("used"):
        M_true = fin["M"].copy()
        M_true[pd.unknown] = truth * idx["g"]
        t = IndexModel(pd, idx["g"], M_true).solve(idx["degree"] - 1, s1["W_final"])
        parts.append(f"index model from true directions {ratio(t['M']):.2f}x cost {t['cost']:.3g}")
    for name, bend in (("affine", False), ("bent", True)):
        fm = ForwardModel(pd)
        fm.bend = bend
        t = fm.solve(truth, fin["g"], W2)
        parts.append(f"{name} from true directions {ratio(t['M']):.2f}x cost {t['cost']:.3g}")
    # the models' limits: fitted with every load known, the unknown directions re-inferred
    for name, rank in (("affine", 0), ("rank-2 quadratic", 2)):
        est = _reinferred(loads, means, kn, rank)
        parts.append(f"{name} fitted on all 12 loads {ratio(est):.2f}x "
                     f"(pose loads off by up to {np.abs(est - loads).max():.2f} N)")
    q = _QuadraticForward(pd, float(np.median(np.linalg.norm(loads[kn], axis=1))))
    t = q.solve(truth, q.magnitude, W2)
    parts.append(f"full quadratic from true directions {ratio(t['M']):.2f}x "
                 f"(pose loads off by up to {np.linalg.norm(t['M'] - loads, axis=1).max():.1f} N)")
    return "; ".join(parts)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="folder of data_<set>.0_*.csv files")
    ap.add_argument("--split", choices=("alternate", "halves"), default="alternate")
    ap.add_argument("--stride", type=int, default=1, choices=range(1, 101), metavar="S",
                    help="keep every S-th sample of every pose (default 1: all of them)")
    ap.add_argument("--known-poses", choices=("recommended", "first"), default="recommended",
                    help="which poses get the known loads (default: choose_known_poses)")
    ap.add_argument("--known", type=int, default=4, choices=range(3, 12), metavar="K",
                    help="known pose means handed to the motion routes (default 4)")
    ap.add_argument("--diagnose", action="store_true",
                    help="also print where the joint route's error comes from (slow)")
    args = ap.parse_args(argv)
    notes = []
    print("| set | load (N) | least squares rms (N) | least squares, channel | joint (default) "
          "| centered | paper |")
    print("|---|---|---|---|---|---|---|")
    for k in range(5):
        got = load_set(args.data, k)
        if got is None:
            continue
        Z, M, pose, within, count = got
        keep = within % args.stride == 0
        Z, M, pose, within = Z[keep], M[keep], pose[keep], within[keep] // args.stride
        count = np.bincount(pose)[pose]
        tr = within % 2 == 0 if args.split == "alternate" else within < count // 2
        te = ~tr
        P = pose.max() + 1
        loads = np.array([M[pose == j].mean(axis=0) for j in range(P)])
        means = np.array([Z[tr & (pose == j)].mean(axis=0) for j in range(P)])
        kn = (choose_known_poses(loads, args.known) if args.known_poses == "recommended"
              else np.arange(args.known))
        Zk, Mk = means[kn], loads[kn]

        def err(cal, te=te, Z=Z, M=M):
            return float(np.sqrt(np.mean(np.sum((cal.apply(Z[te]) - M[te]) ** 2, axis=1))))

        ls = err(fit_least_squares(Z[tr], M[tr], bias=True))
        cells = []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            channel = err(fit_model(Z[tr], M[tr], "channel")) / ls
            cal = fit_joint(Z[tr], Zk, Mk, model="auto", drift="none")
            cells.append((err(cal) / ls, bool(assess(cal, Zk, Mk))))
            for route in ("centered", "paper"):
                c = fit_bias(Z[tr], 3, method=route, known_Z=Zk, known_M=Mk)
                cc = crosscheck(c, Z[tr], Zk, Mk)
                if cc is not None:
                    c.diagnostics["crosscheck"] = cc
                cells.append((err(c) / ls, bool(assess(c, Zk, Mk))))
        g = float(np.median(np.linalg.norm(loads, axis=1)))
        print(f"| {k} | {g:.2f} | {ls:.3f} | {channel:.2f}x | " + " | ".join(
            f"{q:.2f}x{' (exit 3)' if bad else ''}" for q, bad in cells) + " |", flush=True)
        if args.diagnose:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                notes.append(f"set {k}: " + diagnose(Z, M, pose, tr, te, loads, means, kn, ls))
    for line in notes:
        print(line)


if __name__ == "__main__":
    main()
