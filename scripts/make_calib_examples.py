"""Write the bundled example logs of docs/calib.md into examples/calib/ (seeded, deterministic).

    python scripts/make_calib_examples.py [--out examples/calib]

Every file is a CSV with a header of column names (channels g1..gN, loads Fx,Fy,Fz), the
readings written with 7 significant digits. What each file is, and the seed it came from, is in
examples/calib/README.md. The magnetometer log is real data (tests/data/magnetometer/bazhin,
MIT licence): converted from its ``x y z`` text to a CSV, its licence copied beside it.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# one line a module (the package's modules are being moved: easy to rewrite)
from calib.routes.joint import choose_known_poses  # noqa: E402
from calib.simulation.simulate import simulate_payload_rig, simulate_rig  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MAG = os.path.join(ROOT, "tests", "data", "magnetometer", "bazhin")
LOADS = ["Fx", "Fy", "Fz"]

RIG_SEED = 0  # simulate_rig: 12 poses x 60 readings, 8 channels, every imperfection at default
PAYLOAD_SEED = 10_000  # simulate_payload_rig: 80 poses, one reading each, 8 gauges
SWEEP_SEED = 10_000  # simulate_payload_rig(sweep=True): 400 readings of one slow motion


def write(path, header, rows) -> None:
    rows = np.atleast_2d(np.asarray(rows, float))
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(",".join(header) + "\n")
        for r in rows:
            f.write(",".join(f"{x:.7g}" for x in r) + "\n")


def channels(p: int) -> list[str]:
    return [f"g{i}" for i in range(1, p + 1)]


def static_rig(out: str) -> None:
    """A 12-pose rig: half of every pose trains (rig_raw.csv), half tests (rig_test.csv)."""
    rig = simulate_rig(RIG_SEED, poses=12, samples=60)
    ch = channels(rig.Z.shape[1])
    tr, te = rig.split("alternate")
    write(os.path.join(out, "rig_poses.csv"), ["ux", "uy", "uz"], rig.directions)
    known = choose_known_poses(rig.directions, 4)  # what `calib plan rig_poses.csv` recommends
    means, poses = rig.pose_means(tr)
    write(os.path.join(out, "rig_known.csv"), ch + LOADS,
          np.hstack([means[known], rig.stated_loads[poses[known]]]))
    write(os.path.join(out, "rig_raw.csv"), ch, rig.Z[tr])
    # every training row with the load its pose was stated to carry: least squares' input
    write(os.path.join(out, "rig_all_known.csv"), ch + LOADS,
          np.hstack([rig.Z[tr], rig.stated_loads[rig.pose[tr]]]))
    write(os.path.join(out, "rig_test.csv"), ch + LOADS,
          np.hstack([rig.Z[te], rig.stated_loads[rig.pose[te]]]))


def one_reading(out: str, name: str, seed: int, **kw) -> None:
    """A payload rig: every other pose (or reading) trains, the others test; 4 known loads on
    the training poses choose_known_poses picks."""
    rig = simulate_payload_rig(seed, **kw)
    ch = channels(rig.Z.shape[1])
    M = rig.stated_loads[rig.pose]
    tr, te = rig.split("poses")
    known = choose_known_poses(M[tr] / np.linalg.norm(M[tr], axis=1, keepdims=True), 4)
    write(os.path.join(out, f"{name}_raw.csv"), ch, rig.Z[tr])
    write(os.path.join(out, f"{name}_known.csv"), ch + LOADS,
          np.hstack([rig.Z[tr][known], M[tr][known]]))
    write(os.path.join(out, f"{name}_test.csv"), ch + LOADS, np.hstack([rig.Z[te], M[te]]))


def magnetometer(out: str) -> None:
    """bazhin/mag_out.txt (``x y z`` integer counts, 347 rows) as a CSV, with its licence."""
    xyz = np.loadtxt(os.path.join(MAG, "mag_out.txt"))
    write(os.path.join(out, "magnetometer.csv"), ["mx", "my", "mz"], xyz)
    shutil.copyfile(os.path.join(MAG, "LICENSE"), os.path.join(out, "magnetometer.LICENSE"))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.path.join(ROOT, "examples", "calib"))
    a = ap.parse_args(argv)
    os.makedirs(a.out, exist_ok=True)
    static_rig(a.out)
    one_reading(a.out, "payload", PAYLOAD_SEED, poses=80)
    one_reading(a.out, "sweep", SWEEP_SEED, poses=400, sweep=True)
    magnetometer(a.out)
    for f in sorted(os.listdir(a.out)):
        print(f"{f}: {os.path.getsize(os.path.join(a.out, f))} bytes")


if __name__ == "__main__":
    main()
