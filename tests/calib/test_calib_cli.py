"""CLI round trips through calib.cli.main in tmp_path, and one-line errors on bad input."""

import json

import numpy as np
import pytest

from calib.cli import main
from calib.data.io import read_csv, write_csv
from calib.estimators.ft6 import random_known_loads
from calib.simulation.simulate import paper_trial, random_shape, simulate

CH = [f"g{i}" for i in range(1, 9)]


def run(argv, capsys):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def raw3(tmp_path):
    d = paper_trial(2, rng=0)
    write_csv(tmp_path / "raw.csv", CH, d.Z)
    F = np.eye(3) * 9.0
    write_csv(tmp_path / "known.csv", CH + ["Fx", "Fy", "Fz"], np.hstack([F @ d.S + d.offset, F]))
    return d


@pytest.mark.parametrize("method", ["centered", "paper"])
def test_fit_apply_round_trip_3dof(tmp_path, capsys, raw3, method):
    code, out, err = run(
        [
            "fit",
            tmp_path / "raw.csv",
            "--dof",
            3,
            "--bias",
            "--method",
            method,
            "--known",
            tmp_path / "known.csv",
            "--out",
            tmp_path / "cal.json",
        ],
        capsys,
    )
    assert code == 0, err
    assert "wrote" in out and err == ""
    cal = json.loads((tmp_path / "cal.json").read_text())
    assert np.array(cal["C"]).shape == (3, 8) and len(cal["offset"]) == 8 and cal["dof"] == 3
    diag = cal["diagnostics"]
    for key in (
        "singular_values",
        "rank_gap",
        "coverage",
        "condition_number_C",
        "residual_magnitude_rms",
    ):
        assert key in diag
    assert np.mean(np.abs(np.array(cal["offset"]) - raw3.offset)) < 0.5
    code, out, err = run(
        ["apply", tmp_path / "cal.json", tmp_path / "raw.csv", "--out", tmp_path / "loads.csv"],
        capsys,
    )
    assert code == 0, err
    header, loads = read_csv(tmp_path / "loads.csv")
    assert header == ["Fx", "Fy", "Fz"] and loads.shape == (176, 3)
    # loads in the user's frame, within the noise (peak 3 counts ~ 2 %)
    assert np.sqrt(np.mean((loads - raw3.loads) ** 2)) < 0.2


def test_fit_6dof_with_known_loads(tmp_path, capsys):
    rng = np.random.default_rng(0)
    S = random_shape(6, 8, rng)
    z0 = rng.normal(size=8)
    d = simulate(S, 200, rng, magnitude=10, offset=z0, lever_arm=[0, 0, 0.1])
    Mk = random_known_loads(6, rng, 10, 1)
    cols = CH + ["Fx", "Fy", "Fz", "Tx", "Ty", "Tz"]
    write_csv(tmp_path / "raw.csv", CH, d.Z)
    write_csv(tmp_path / "known.csv", cols, np.hstack([Mk @ S + z0, Mk]))
    code, out, err = run(
        [
            "fit",
            tmp_path / "raw.csv",
            "--dof",
            6,
            "--bias",
            "--known",
            tmp_path / "known.csv",
            "--out",
            tmp_path / "cal.json",
        ],
        capsys,
    )
    assert code == 0, err
    code, _, err = run(
        ["apply", tmp_path / "cal.json", tmp_path / "raw.csv", "--out", tmp_path / "loads.csv"],
        capsys,
    )
    header, loads = read_csv(tmp_path / "loads.csv")
    assert header == ["Fx", "Fy", "Fz", "Tx", "Ty", "Tz"]
    assert np.allclose(loads, d.loads, atol=1e-8)


def test_drop_nonfinite_opt_in(tmp_path, capsys, raw3):
    Z = raw3.Z.copy()
    Z[5, 1] = np.nan
    write_csv(tmp_path / "bad.csv", CH, Z)
    code, _, err = run(
        ["fit", tmp_path / "bad.csv", "--dof", 3, "--bias", "--out", tmp_path / "c.json"], capsys
    )
    assert code == 2 and err.count("\n") == 1 and "NaN/inf" in err and "--drop-nonfinite" in err
    assert not (tmp_path / "c.json").exists()
    code, out, err = run(
        [
            "fit",
            tmp_path / "bad.csv",
            "--dof",
            3,
            "--bias",
            "--drop-nonfinite",
            "--out",
            tmp_path / "c.json",
        ],
        capsys,
    )
    assert code == 0 and "dropped 1 non-finite row(s)" in out


def bad_cases(tmp_path, raw3):
    write_csv(tmp_path / "few.csv", CH, raw3.Z[:5])
    Zc = raw3.Z.copy()
    Zc[:, 3] = 1.0
    write_csv(tmp_path / "const.csv", CH, Zc)
    (tmp_path / "text.csv").write_text(",".join(CH) + "\n" + ",".join(["1"] * 7 + ["x"]) + "\n")
    (tmp_path / "ragged.csv").write_text(",".join(CH) + "\n1,2,3\n")
    write_csv(tmp_path / "three.csv", CH[:3], raw3.Z[:, :3])
    t = np.linspace(0, 6, 100)
    write_csv(
        tmp_path / "planar.csv",
        CH,
        9 * np.column_stack([np.cos(t), np.sin(t), np.cos(t)]) / np.sqrt(2) @ raw3.S + raw3.offset,
    )
    (tmp_path / "cal_bad.json").write_text("{not json")
    # a wrench sensor's channels named like the load columns, and a known file repeating one
    wrench = ["Fx", "Fy", "Fz", "Tx", "Ty", "Tz", "c6", "c7"]
    write_csv(tmp_path / "wrench.csv", wrench, raw3.Z)
    write_csv(tmp_path / "wrench_known.csv", wrench + ["gx", "gy", "gz"],
              np.hstack([raw3.Z[:4], np.eye(3)[[0, 1, 2, 0]]]))
    (tmp_path / "dup_known.csv").write_text(
        ",".join(CH + [CH[0], "Fx", "Fy", "Fz"]) + "\n" + ",".join(["1"] * 12) + "\n")
    out = tmp_path / "o.json"
    return [
        (["fit", tmp_path / "wrench.csv", "--dof", 3, "--known", tmp_path / "wrench_known.csv",
          "--out", out], "also load column names"),
        (["fit", tmp_path / "raw.csv", "--dof", 3, "--known", tmp_path / "dup_known.csv",
          "--out", out], "duplicate column names"),
        (["fit", tmp_path / "missing.csv", "--dof", 3, "--out", out], "cannot read"),
        (["fit", tmp_path / "few.csv", "--dof", 3, "--bias", "--out", out], "5 samples"),
        (["fit", tmp_path / "const.csv", "--dof", 3, "--bias", "--out", out], "constant"),
        (["fit", tmp_path / "text.csv", "--dof", 3, "--out", out], "non-numeric"),
        (["fit", tmp_path / "ragged.csv", "--dof", 3, "--out", out], "3 fields"),
        (
            [
                "fit",
                tmp_path / "three.csv",
                "--dof",
                3,
                "--bias",
                "--method",
                "paper",
                "--out",
                out,
            ],
            "p >= r+1",
        ),
        (["fit", tmp_path / "planar.csv", "--dof", 3, "--bias", "--out", out], "rank-deficient"),
        (["fit", tmp_path / "raw.csv", "--dof", 5, "--out", out], "invalid choice"),
        (["fit", tmp_path / "raw.csv", "--dof", 6, "--out", out], "needs --known"),
        (
            [
                "fit",
                tmp_path / "raw.csv",
                "--dof",
                3,
                "--known",
                tmp_path / "few.csv",
                "--out",
                out,
            ],
            "lacks column",
        ),
        (
            ["apply", tmp_path / "cal_bad.json", tmp_path / "raw.csv", "--out", out],
            "not valid JSON",
        ),
        (["trials", "--seeds", 0, "--out", tmp_path / "tr"],
         "argument --seeds: expected a positive integer"),
        ([], "required"),
        (["fit", tmp_path / "raw.csv", "--dof", 3, "--out", out, "--bogus"],
         "unrecognized arguments: --bogus"),
        (["fit", tmp_path / "raw.csv"], "required: --dof, --out (see calib fit --help)"),
    ]


def test_every_bad_input_is_one_line(tmp_path, capsys, raw3):
    for argv, expect in bad_cases(tmp_path, raw3):
        code, out, err = run(argv, capsys)
        assert code == 2, argv
        assert err.startswith("calib: error:") and err.count("\n") == 1, err
        assert expect in err, (argv, err)
        assert not err.startswith("calib: error: calib"), err  # the prefix once
        assert "Traceback" not in err


def test_apply_checks_channel_names(tmp_path, capsys, raw3):
    run(["fit", tmp_path / "raw.csv", "--dof", 3, "--bias", "--out", tmp_path / "c.json"], capsys)
    write_csv(tmp_path / "other.csv", [f"h{i}" for i in range(8)], raw3.Z)
    code, _, err = run(
        ["apply", tmp_path / "c.json", tmp_path / "other.csv", "--out", tmp_path / "l.csv"], capsys
    )
    assert code == 2 and "lacks calibrated channel(s)" in err
    # reordered columns are matched by name
    write_csv(tmp_path / "rev.csv", CH[::-1], raw3.Z[:, ::-1])
    run(["apply", tmp_path / "c.json", tmp_path / "raw.csv", "--out", tmp_path / "a.csv"], capsys)
    run(["apply", tmp_path / "c.json", tmp_path / "rev.csv", "--out", tmp_path / "b.csv"], capsys)
    assert np.array_equal(read_csv(tmp_path / "a.csv")[1], read_csv(tmp_path / "b.csv")[1])


def test_partial_coverage_warns_on_one_line(tmp_path, capsys):
    d = paper_trial(2, rng=0, cap_half_angle_deg=60)
    write_csv(tmp_path / "cap.csv", CH, d.Z)
    code, out, err = run(
        ["fit", tmp_path / "cap.csv", "--dof", 3, "--bias", "--out", tmp_path / "c.json"], capsys
    )
    # a 60 degree cap leaves the offset unidentified: refused (exit 3), one line
    assert code == 3 and not (tmp_path / "c.json").exists()
    assert err.count("\n") == 1 and "offset is not identified" in err
    code, out, err = run(
        ["fit", tmp_path / "cap.csv", "--dof", 3, "--bias", "--out", tmp_path / "c.json",
         "--allow-unreliable"], capsys)
    assert code == 0 and "UNRELIABLE" in out
    assert "calib: warning: poor excitation" in err
    assert all(line.startswith("calib: warning:") for line in err.strip().splitlines())


def test_the_paper_route_under_poor_excitation_is_refused_and_says_why(tmp_path, capsys):
    """The paper route on a 90 degree cap: its warning calls the offset unreliable, so the
    verdict does too (exit 3, one line, nothing written); written only on request, and then
    the summary says UNRELIABLE, as the warning does."""
    d = paper_trial(2, rng=0, cap_half_angle_deg=90)
    write_csv(tmp_path / "cap.csv", CH, d.Z)
    args = ["fit", tmp_path / "cap.csv", "--dof", 3, "--bias", "--method", "paper", "--out",
            tmp_path / "c.json"]
    code, out, err = run(args, capsys)
    assert code == 3 and not (tmp_path / "c.json").exists()
    assert err.count("\n") == 1 and "paper route's offset is not identified" in err
    assert "use --method centered or joint" in err
    code, out, err = run(args + ["--allow-unreliable"], capsys)
    assert code == 0 and "UNRELIABLE" in out and (tmp_path / "c.json").exists()
    assert "poor excitation" in err and "the offset is unreliable" in err


def test_a_copied_channel_is_named_by_its_header_and_left_out(tmp_path, capsys, raw3):
    """A column logged twice (in other units): one warning naming both columns by their
    header names, the fit written, the copy's column of C 0."""
    Z = np.column_stack([raw3.Z, 1e3 * raw3.Z[:, 2] - 40.0])
    write_csv(tmp_path / "dup.csv", CH + ["g3_mV"], Z)
    F = np.eye(3) * 9.0
    Zk = F @ raw3.S + raw3.offset
    write_csv(tmp_path / "dupk.csv", CH + ["g3_mV", "Fx", "Fy", "Fz"],
              np.hstack([Zk, 1e3 * Zk[:, 2:3] - 40.0, F]))
    code, out, err = run(["fit", tmp_path / "dup.csv", "--dof", 3, "--bias", "--method",
                          "centered", "--known", tmp_path / "dupk.csv", "--out",
                          tmp_path / "c.json"], capsys)
    assert code == 0, err
    assert "calib: warning: channel 8 (g3_mV) is an exact copy of channel 2 (g3)" in err
    cal = json.loads((tmp_path / "c.json").read_text())
    assert np.all(np.array(cal["C"])[:, 8] == 0) and cal["channels"][8] == "g3_mV"


def test_a_sum_channel_is_named_by_its_headers_and_left_out(tmp_path, capsys, raw3):
    """A column that is the sum of two others (logged after them): one warning naming the
    three by their header names, the fit written, its column of C 0."""
    Z = np.column_stack([raw3.Z, raw3.Z[:, 1] + 2.0 * raw3.Z[:, 4]])
    write_csv(tmp_path / "sum.csv", CH + ["g2+g5"], Z)
    F = np.eye(3) * 9.0
    Zk = F @ raw3.S + raw3.offset
    write_csv(tmp_path / "sumk.csv", CH + ["g2+g5", "Fx", "Fy", "Fz"],
              np.hstack([Zk, Zk[:, 1:2] + 2.0 * Zk[:, 4:5], F]))
    code, out, err = run(["fit", tmp_path / "sum.csv", "--dof", 3, "--bias", "--method",
                          "centered", "--known", tmp_path / "sumk.csv", "--out",
                          tmp_path / "c.json"], capsys)
    assert code == 0, err
    assert ("calib: warning: channel 8 (g2+g5) is an exact combination of channel 1 (g2) and "
            "channel 4 (g5) (1 x channel 1 (g2) + 2 x channel 4 (g5)") in err, err
    cal = json.loads((tmp_path / "c.json").read_text())
    assert np.all(np.array(cal["C"])[:, 8] == 0) and cal["channels"][8] == "g2+g5"


def test_trials_command_small(tmp_path, capsys):
    code, out, err = run(["trials", "--out", tmp_path / "tr", "--seeds", 4, "--quiet"], capsys)
    assert code == 0, err
    text = (tmp_path / "tr" / "trials.md").read_text()
    assert "## Trial 4" in text and "Table 1" in text and "gradient descent" in text
    for png in ("singular_values.png", "offset_error_vs_noise.png", "offset_error_vs_cap.png"):
        assert (tmp_path / "tr" / png).stat().st_size > 1000


def test_evaluate_states_the_error_vectors_rms_length_as_the_prediction_does(tmp_path, capsys):
    """``calib evaluate``'s held-out load rms is ``sqrt(mean |m_hat - m|^2)``, the measure of
    the load rms beside it and of the fit's predicted held-out error (it printed the rms over
    components, sqrt(3) smaller in 3-D, beside a prediction of the vector's length), and each
    axis's own rms after it."""
    from calib import fit_least_squares
    from calib.data.io import save_calibration

    rng = np.random.default_rng(4)
    S = rng.normal(size=(3, 8))
    M = rng.normal(size=(60, 3)) * 5.0
    Z = M @ S + rng.normal(size=(60, 8)) * 0.05
    cal = fit_least_squares(Z[:40], M[:40], bias=True)
    save_calibration(str(tmp_path / "cal.json"), cal, CH)
    write_csv(tmp_path / "test.csv", CH + ["Fx", "Fy", "Fz"], np.hstack([Z[40:], M[40:]]))
    code, out, err = run(["evaluate", tmp_path / "cal.json", tmp_path / "test.csv"], capsys)
    assert code == 0, err
    e = cal.apply(Z[40:]) - M[40:]
    length = np.sqrt(np.mean(np.sum(e**2, axis=1)))
    printed = float(out.split("held-out load rms ")[1].split()[0])
    assert printed == pytest.approx(length, rel=1e-3)
    assert printed > 1.5 * np.sqrt(np.mean(e**2))  # not the rms over components
    axes = [float(out.split(f"{c} ")[-1].split(",")[0]) for c in ("Fx", "Fy", "Fz")]
    np.testing.assert_allclose(axes, np.sqrt(np.mean(e**2, axis=0)), rtol=1e-3)
