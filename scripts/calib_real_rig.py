"""Every route on a real 3D-printed 8-channel force sensor, with the issue-23 protocol.

Data (not shipped: the repository has no licence file): github.com/jonurce/FTS_Calibration,
``Datasets/12_final_extra_bounded/data/data_<set>.0_R.._P.._Y...csv``: five load sets (a mass at
five positions; about 3 N in set 0, 10 N in the others), 12 static poses each, about 2,000 samples
per pose; columns ``Timestamp,Fx,Fy,Fz,Mx,My,Mz,s0..s7`` (a reference F/T sensor's load and the
printed sensor's 8 channels, integer counts). Fetch it yourself and point ``--data`` at the folder.

Protocol: even samples of every pose train, odd ones test (``--split halves``: first and second
half); the test target is the reference load. Least squares with every load known (per-row
loads) is the reference; the joint route gets the training rows in pose order and 4 known pose
means on the poses :func:`calib.joint.choose_known_poses` recommends (from the reference load
directions); centered and paper routes get the same 4 known loads. Prints per set the held-out
rms of least squares and each route's ratio to it, and whether ``calib fit`` would exit 3.

    python scripts/calib_real_rig.py --data DIR [--split alternate|halves]
"""

from __future__ import annotations

import argparse
import glob
import os
import sys
import warnings

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from calib.bias import fit_bias  # noqa: E402
from calib.joint import choose_known_poses, fit_joint  # noqa: E402
from calib.least_squares import fit_least_squares  # noqa: E402
from calib.reliability import assess, crosscheck  # noqa: E402


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


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="folder of data_<set>.0_*.csv files")
    ap.add_argument("--split", choices=("alternate", "halves"), default="alternate")
    args = ap.parse_args(argv)
    print("| set | load (N) | least squares rms (N) | joint (default) | centered | paper |")
    print("|---|---|---|---|---|---|")
    for k in range(5):
        got = load_set(args.data, k)
        if got is None:
            continue
        Z, M, pose, within, count = got
        tr = within % 2 == 0 if args.split == "alternate" else within < count // 2
        te = ~tr
        P = pose.max() + 1
        loads = np.array([M[pose == j].mean(axis=0) for j in range(P)])
        means = np.array([Z[tr & (pose == j)].mean(axis=0) for j in range(P)])
        kn = choose_known_poses(loads, 4)
        Zk, Mk = means[kn], loads[kn]

        def err(cal, te=te, Z=Z, M=M):
            return float(np.sqrt(np.mean((cal.apply(Z[te]) - M[te]) ** 2)))

        ls = err(fit_least_squares(Z[tr], M[tr], bias=True))
        cells = []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cal = fit_joint(Z[tr], Zk, Mk, model="auto", drift="auto")
            cells.append((err(cal) / ls, bool(assess(cal, Zk, Mk))))
            for route in ("centered", "paper"):
                c = fit_bias(Z[tr], 3, method=route, known_Z=Zk, known_M=Mk)
                cc = crosscheck(c, Z[tr], Zk, Mk)
                if cc is not None:
                    c.diagnostics["crosscheck"] = cc
                cells.append((err(c) / ls, bool(assess(c, Zk, Mk))))
        g = float(np.median(np.linalg.norm(loads, axis=1)))
        print(f"| {k} | {g:.2f} | {ls:.3f} | " + " | ".join(
            f"{q:.2f}x{' (exit 3)' if bad else ''}" for q, bad in cells) + " |")


if __name__ == "__main__":
    main()
