"""scripts/calib_wrist_check.py (the wrist protocol on a real wrist F/T sensor's logs) on a
simulated one written in the data's own format: poses as base-frame quaternions, the wrench
rotated into the base frame."""

import numpy as np
from scipy.spatial.transform import Rotation

from calib.simulation.simulate import simulate_payload_rig


def _write(tmp_path, seed=7):
    rig = simulate_payload_rig(seed, poses=100, wrench=True, gauges=8)
    U = rig.directions[rig.pose]
    rng = np.random.default_rng(seed)
    R = np.empty((len(U), 3, 3))
    for i, u in enumerate(U):  # a sensor orientation whose base z reads -u in the sensor frame
        a = np.cross(-u, rng.normal(size=3))
        a /= np.linalg.norm(a)
        R[i] = np.stack([a, np.cross(-u, a), -u])  # rows: base x, y, z in the sensor frame
    pos = rng.normal(size=(len(U), 3))
    quat = Rotation.from_matrix(R).as_quat()  # sensor -> base
    world = np.hstack([np.einsum("nij,nj->ni", R, rig.Z[:, :3]),
                       np.einsum("nij,nj->ni", R, rig.Z[:, 3:])])
    np.savetxt(tmp_path / "recorded_messages_pose_100.txt", np.hstack([pos, quat]),
               delimiter=", ")
    np.savetxt(tmp_path / "recorded_messages_wrench_100.txt", world, delimiter=", ")
    return rig


def test_the_script_recovers_the_weight_and_reports_every_route(tmp_path, capsys, load_script):
    rig = _write(tmp_path)
    load_script("calib_wrist_check").main(["--data", str(tmp_path)])
    out = capsys.readouterr().out
    weight = float(out.split("weight ")[1].split(" N")[0])
    assert abs(weight - rig.magnitude) < 0.01 * rig.magnitude, (weight, rig.magnitude)
    assert "least squares, every load known" in out
    joint = next(line for line in out.splitlines() if line.startswith("joint:"))
    ratio = float(joint.split("x least squares")[0].split()[-1])
    assert 0.5 < ratio < 3.0, joint
    assert "noise correlated across channels" in joint
    for route in ("centered", "paper"):
        assert any(line.startswith(route + ":") for line in out.splitlines())


def test_a_malformed_folder_is_one_line(tmp_path, load_script):
    import pytest

    (tmp_path / "recorded_messages_pose_100.txt").write_text("1, 2, 3\n")
    (tmp_path / "recorded_messages_wrench_100.txt").write_text("1, 2, 3, 4, 5, 6\n")
    with pytest.raises(SystemExit, match="expected"):
        load_script("calib_wrist_check").main(["--data", str(tmp_path)])


def test_missing_nonregular_and_nonfinite_files_are_one_line(tmp_path, load_script):
    import os

    import pytest

    main = load_script("calib_wrist_check").main
    with pytest.raises(SystemExit, match="recorded_messages_pose_100.txt"):
        main(["--data", str(tmp_path)])  # missing
    os.mkfifo(tmp_path / "recorded_messages_pose_100.txt")  # would block a plain open
    (tmp_path / "recorded_messages_wrench_100.txt").write_text("1, 2, 3, 4, 5, 6\n")
    with pytest.raises(SystemExit, match="not a regular file"):
        main(["--data", str(tmp_path)])
    os.remove(tmp_path / "recorded_messages_pose_100.txt")
    (tmp_path / "recorded_messages_pose_100.txt").write_text("0, 0, 0, 0, 0, 0, nan\n")
    with pytest.raises(SystemExit, match="NaN or inf"):
        main(["--data", str(tmp_path)])
