"""Every route on a real commercial 6-axis F/T sensor on a robot wrist, with the wrist protocol.

Data (not shipped: the repository has no licence file): github.com/leledeyuan00/
Gravity-Compensation-F-T-sensor, ``datas/recorded_messages_pose_100.txt`` and
``datas/recorded_messages_wrench_100.txt``: an ATI Axia80 holding a gripper in 100 static poses,
one reading each. Pose rows ``x, y, z, qx, qy, qz, qw`` (the sensor link in the robot's base
frame); wrench rows ``Fx, Fy, Fz, Tx, Ty, Tz`` (N, N*m) expressed in the base frame. Fetch it
yourself and point ``--data`` at the folder holding the two files.

Protocol: the wrench is rotated back into the sensor frame (the channels); the load is the
gripper's weight in the sensor frame, ``R^T (0, 0, w)``, ``w`` the vertical force of the
base-frame model ``f = (0, 0, w) + R f_bias`` fitted by least squares (the kinematics' load).
Alternate poses train and the others test (``--split halves``: the first 50 train, a narrow
band of directions). Least squares with every load known (bias on) is the reference; the joint,
centered and paper routes get 4 known loads on the poses
:func:`calib.routes.joint.choose_known_poses`
recommends (``calib plan``), their readings the log's own rows (``known_samples=1``). Prints the
held-out load rms (``sqrt(mean |m_hat - m|^2)``, N) of least squares and each route's ratio to
it, whether ``calib fit`` would exit 3 and, for the joint route, its predicted held-out error and
whether the channels' noise was found correlated.

    python scripts/calib_wrist_check.py --data DIR [--split alternate|halves]
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from calib.data.io import open_regular  # noqa: E402
from calib.data.result import CalibrationError  # noqa: E402
from calib.estimators.bias import fit_bias  # noqa: E402
from calib.estimators.least_squares import fit_least_squares  # noqa: E402
from calib.routes.joint import choose_known_poses, fit_joint  # noqa: E402
from calib.verdict.reliability import assess  # noqa: E402
from sfm_common.cli import one_line  # noqa: E402

POSE = "recorded_messages_pose_100.txt"
WRENCH = "recorded_messages_wrench_100.txt"


def load(folder: str):
    """Sensor-frame readings (n, 6), the weight in the sensor frame (n, 3), and the base-frame
    force model's residual rms (N)."""
    def read(name):
        path = os.path.join(folder, name)
        try:
            with open_regular(path) as f:
                return np.loadtxt(f, delimiter=",", ndmin=2)
        except (OSError, ValueError, CalibrationError) as e:
            raise SystemExit(f"{path}: {one_line(e)}") from None

    pose, wrench = read(POSE), read(WRENCH)
    if not (np.all(np.isfinite(pose)) and np.all(np.isfinite(wrench))):
        raise SystemExit(f"{folder}: NaN or inf in {POSE} or {WRENCH}")
    if pose.shape[1] != 7 or wrench.shape[1] != 6 or len(pose) != len(wrench):
        raise SystemExit(f"{folder}: expected {POSE} rows of 7 and {WRENCH} rows of 6, "
                         f"one per pose; got {pose.shape} and {wrench.shape}")
    R = Rotation.from_quat(pose[:, 3:7]).as_matrix()  # sensor -> base, scalar last
    n = len(R)
    X = np.zeros((3 * n, 4))
    X[2::3, 0] = 1.0
    X[:, 1:] = R.reshape(3 * n, 3)
    theta, *_ = np.linalg.lstsq(X, wrench[:, :3].reshape(-1), rcond=None)
    rms = float(np.sqrt(np.mean((X @ theta - wrench[:, :3].reshape(-1)) ** 2)))
    Z = np.hstack([np.einsum("nji,nj->ni", R, wrench[:, :3]),
                   np.einsum("nji,nj->ni", R, wrench[:, 3:])])
    return Z, theta[0] * R[:, 2, :], rms


def held_out(C, o, Z, M) -> float:
    return float(np.sqrt(np.mean(np.sum(((Z - o) @ C.T - M) ** 2, axis=1))))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help=f"folder holding {POSE} and {WRENCH}")
    ap.add_argument("--split", choices=("alternate", "halves"), default="alternate")
    args = ap.parse_args(argv)
    Z, M, rms = load(args.data)
    n = len(Z)
    if args.split == "alternate":
        tr, te = np.arange(0, n, 2), np.arange(1, n, 2)
    else:
        tr, te = np.arange(n // 2), np.arange(n // 2, n)
    U = M[tr] / np.linalg.norm(M[tr], axis=1, keepdims=True)
    kn = choose_known_poses(U, 4)
    ls = fit_least_squares(Z[tr], M[tr], bias=True)
    ref = held_out(ls.C, ls.offset, Z[te], M[te])
    print(f"{n} poses, weight {np.linalg.norm(M[0]):.3f} N (base-frame force model rms "
          f"{rms:.3f} N), split {args.split}: {len(tr)} train, {len(te)} test; known poses "
          f"{', '.join(str(int(k) + 1) for k in kn)}")
    print(f"least squares, every load known: held-out rms {ref:.4f} N")
    Zk, Mk = Z[tr][kn], M[tr][kn]
    for route in ("joint", "centered", "paper"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                if route == "joint":
                    cal = fit_joint(Z[tr], Zk, Mk, 3, known_samples=1)
                else:
                    cal = fit_bias(Z[tr], 3, method=route, known_Z=Zk, known_M=Mk)
            except CalibrationError as e:
                print(f"{route}: no fit ({e})")
                continue
            problems = assess(cal, Zk, Mk)
        e = held_out(cal.C, cal.offset, Z[te], M[te])
        line = (f"{route}: {e / ref:.2f}x least squares, "
                + ("exit 3 (" + "; ".join(problems)[:160] + ")" if problems else "exit 0"))
        d = cal.diagnostics.get("joint", {})
        pe = d.get("predicted_error")
        if pe:
            lo, hi = pe["interval"]
            line += (f"; predicted {pe['rms']:.4f} [{lo:.4f}, {hi:.4f}] N, measured {e:.4f} "
                     + ("(inside)" if lo <= e <= hi else "(outside)"))
        nc = d.get("noise_correlation")
        if nc and nc.get("p_value") is not None:
            line += (f"; noise correlated across channels: p = {nc['p_value']:.1g}, "
                     + ("whitened" if nc["used"] else "not used"))
        print(line)


if __name__ == "__main__":
    main()
