"""scripts/calib_real_rig.py (the real-rig protocol on a real rig's logs) on a simulated rig written
in the real data's file layout: the table and ``--diagnose`` run and report what they should."""

import re
from pathlib import Path

import numpy as np

from calib.simulation.simulate import simulate_rig


def _write_set(folder: Path, k: int, rig) -> None:
    """One file per pose, as github.com/jonurce/FTS_Calibration lays them out."""
    header = "Timestamp,Fx,Fy,Fz,Mx,My,Mz," + ",".join(f"s{c}" for c in range(8))
    for j in np.unique(rig.pose):
        rows = rig.pose == j
        n = int(rows.sum())
        table = np.column_stack([np.arange(n) * 0.005, rig.true_loads[rows], np.zeros((n, 3)),
                                 rig.Z[rows]])
        np.savetxt(folder / f"data_{k}.0_pose{j:02d}.csv", table, delimiter=",", header=header,
                   comments="")


def test_protocol_and_diagnosis_on_a_simulated_rig(tmp_path, capsys, load_script):
    rig = simulate_rig(np.random.default_rng(5), poses=12, samples=120, nonlinearity=0.0,
                       drift=0.0, wander=0.0, creep=0.0, hysteresis=0.0)
    _write_set(tmp_path, 0, rig)
    load_script("calib_real_rig").main(["--data", str(tmp_path), "--diagnose"])
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("| 0 |"))
    ratios = [float(x) for x in re.findall(r"([\d.]+)x", row)]
    # ratios: least squares under the channel model, joint, centered, paper
    assert len(ratios) == 4 and ratios[1] < 1.3  # a linear sensor: the joint route is near LS
    assert ratios[0] < 1.1  # and the channel model adds nothing to fit
    diag = next(line for line in out.splitlines() if line.startswith("set 0:"))
    got = dict(re.findall(r"(chosen \([\w ,]+\)|affine from true directions|bent from true "
                          r"directions|affine fitted on all 12 loads) ([\d.]+)x", diag))
    chosen = [k for k in got if k.startswith("chosen")]
    assert len(chosen) == 1 and chosen[0] in (
        "chosen (affine)", "chosen (bent)", "chosen (index model, degree 2)",
        "chosen (index model, degree 3)")
    assert set(got) - set(chosen) == {"affine from true directions", "bent from true directions",
                                      "affine fitted on all 12 loads"}
    assert float(got[chosen[0]]) < 1.3
    if "index model" in chosen[0]:
        assert "index model from true directions" in diag
    # on a linear sensor the affine model fitted on every load re-infers the directions well
    assert float(got["affine fitted on all 12 loads"]) < 1.2
    assert "full quadratic from true directions" in diag
