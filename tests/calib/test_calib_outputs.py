"""What calib writes: usual permissions (0644 under umask 022), atomic files and PNGs, never an
input destroyed or a device replaced."""

import hashlib
import os
import stat

import numpy as np
import pytest

from calib.cli import main
from calib.io import read_csv, write_csv
from calib.simulate import paper_trial

CH = [f"g{i}" for i in range(1, 9)]


@pytest.fixture
def umask_022():
    old = os.umask(0o022)
    yield
    os.umask(old)


@pytest.fixture
def raw(tmp_path):
    write_csv(tmp_path / "raw.csv", CH, paper_trial(2, rng=0).Z)
    return tmp_path / "raw.csv"


def modes(root):
    out = {}
    for dirpath, _, names in os.walk(root):
        for n in names:
            p = os.path.join(dirpath, n)
            out[os.path.relpath(p, root)] = stat.S_IMODE(os.stat(p).st_mode)
    return out


def test_every_output_is_0644_and_no_temp_file_remains(tmp_path, raw, umask_022, capsys):
    assert main(["fit", str(raw), "--dof", "3", "--bias", "--magnitude", "9",
                 "--out", str(tmp_path / "cal.json")]) == 0
    assert main(["apply", str(tmp_path / "cal.json"), str(raw),
                 "--out", str(tmp_path / "loads.csv")]) == 0
    assert main(["trials", "--seeds", "2", "--quiet", "--out", str(tmp_path / "trials")]) == 0
    found = modes(tmp_path)
    written = {k: v for k, v in found.items() if k != "raw.csv"}
    assert "cal.json" in written and "loads.csv" in written
    assert any(k.endswith(".png") for k in written) and "trials/trials.md" in written
    assert set(written.values()) == {0o644}, written
    assert not [k for k in found if os.path.basename(k).startswith(".tmp-")]


def digest(p):
    return hashlib.sha256(open(p, "rb").read()).hexdigest()


@pytest.mark.parametrize("case", ["fit_onto_raw", "apply_onto_raw", "apply_onto_cal",
                                  "fit_onto_device", "apply_onto_directory"])
def test_an_output_never_replaces_an_input_or_a_device(tmp_path, raw, capsys, case):
    assert main(["fit", str(raw), "--dof", "3", "--bias", "--magnitude", "9",
                 "--out", str(tmp_path / "cal.json")]) == 0
    capsys.readouterr()
    cal = tmp_path / "cal.json"
    (tmp_path / "d").mkdir()
    argv = {
        "fit_onto_raw": ["fit", raw, "--dof", "3", "--out", raw],
        "apply_onto_raw": ["apply", cal, raw, "--out", raw],
        "apply_onto_cal": ["apply", cal, raw, "--out", cal],
        "fit_onto_device": ["fit", raw, "--dof", "3", "--out", "/dev/null"],
        "apply_onto_directory": ["apply", cal, raw, "--out", tmp_path / "d"],
    }[case]
    before = {p: digest(tmp_path / p) for p in ("raw.csv", "cal.json")}
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert {p: digest(tmp_path / p) for p in before} == before
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)


def test_csv_fast_path_and_the_line_of_a_bad_row(tmp_path, capsys):
    good = tmp_path / "good.csv"
    good.write_text("a, b ,c\n\n1,2,3\nnan,inf,-4\n")
    header, data = read_csv(str(good))
    assert header == ["a", "b", "c"]
    np.testing.assert_array_equal(data, [[1.0, 2.0, 3.0], [np.nan, np.inf, -4.0]])
    bad = tmp_path / "bad.csv"
    bad.write_text("a,b,c\n1,2,3\n4,x,6\n")
    code = main(["fit", str(bad), "--dof", "2", "--out", str(tmp_path / "c.json")])
    assert code == 2 and "line 3: non-numeric value" in capsys.readouterr().err
