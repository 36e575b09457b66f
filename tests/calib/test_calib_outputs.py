"""What calib writes: usual permissions (0644 under umask 022), atomic files and PNGs, never an
input destroyed or a device replaced."""

import hashlib
import os
import stat

import numpy as np
import pytest

from calib.cli import main
from calib.data.io import read_csv, write_csv
from calib.simulation.simulate import paper_trial

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


@pytest.mark.parametrize("text, message", [
    ("a,b\n1,2\n#3,4\n5,6\n", "line 3: non-numeric value"),  # '#' is not a comment: no row lost
    ("a,b\n1,2 # note\n", "line 2: non-numeric value"),
    ("a,b\n\n\n1,2\nx,3\n", "line 5: non-numeric value"),  # file lines, blank ones counted
    ("\n\na,b,c\n1,2,3\n\n1,2\n", "line 6: 2 fields, header has 3"),
    ('a,b\n"1,2\n3,4\n', "line 2: 1 fields, header has 2"),  # where the bad row starts
    ("a,b\n1," + "1" * 200_000 + "\nx,2\n", "line 2: field larger than field limit"),
    ("a,a\n1,2\n", "duplicate column names"),
    ("\n\n", "is empty"),
    ("\n , \n", "line 2: the header has no column names"),  # refused, not skipped
])
def test_csv_errors_name_the_file_line(tmp_path, text, message):
    from calib.data.result import CalibrationError

    p = tmp_path / "f.csv"
    p.write_text(text)
    with pytest.raises(CalibrationError, match=message) as e:
        read_csv(str(p))
    assert "\n" not in str(e.value)


def test_csv_fallback_reads_what_numpy_refuses_and_agrees_with_the_fast_path(tmp_path):
    from calib.data.io import _read_rows_slowly

    data = np.random.default_rng(1).normal(0, 100, (500, 4))
    data[3, 1], data[7, 2], data[9, 0] = np.nan, np.inf, -np.inf
    p = tmp_path / "f.csv"
    write_csv(p, list("abcd"), data)
    header, fast = read_csv(str(p))
    np.testing.assert_array_equal(fast, data)
    np.testing.assert_array_equal(_read_rows_slowly(str(p), 4, 1), data)
    q = tmp_path / "q.csv"
    q.write_text('a,b\n"1.5", 2\n1_000,-Infinity\n')  # numpy's parser rejects both lines
    np.testing.assert_array_equal(read_csv(str(q))[1], [[1.5, 2.0], [1000.0, -np.inf]])


def test_trials_progress_draws_no_carriage_returns_off_a_terminal(tmp_path, capsys):
    assert main(["trials", "--seeds", "1", "--no-plots", "--out", str(tmp_path / "t")]) == 0
    err = capsys.readouterr().err
    assert "\r" not in err and "calib trials" not in err, err


@pytest.mark.parametrize("argv, message", [
    (["trials", "--seeds", "-5"], "argument --seeds: expected a positive integer"),
    (["trials", "--seeds", "1.5"], "argument --seeds: expected a positive integer"),
    (["fit", "r.csv", "--dof", "3", "--magnitude", "0"], "argument --magnitude: expected a "
                                                         "positive number, got '0'"),
    (["fit", "r.csv", "--dof", "3", "--magnitude", "-1"], "argument --magnitude"),
    (["fit", "r.csv", "--dof", "3", "--magnitude", "nan"], "argument --magnitude"),
    (["fit", "r.csv", "--dof", "3", "--magnitude", "inf"], "argument --magnitude"),
])
def test_bad_numbers_are_one_line_usage_errors(tmp_path, capsys, argv, message):
    code = main(argv + ["--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("calib: error: ") and err.count("\n") == 1, err
    assert message in err and not os.path.exists(tmp_path / "o")


def test_a_byte_order_mark_is_not_part_of_the_first_name(tmp_path):
    p = tmp_path / "excel.csv"
    p.write_bytes("\ufeffa,b\n1,2\n".encode("utf-8"))
    header, data = read_csv(str(p))
    assert header == ["a", "b"] and data.tolist() == [[1.0, 2.0]]


def test_a_fifo_or_directory_input_is_refused_without_waiting(tmp_path, capsys):
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    for raw in (fifo, tmp_path):
        code = main(["fit", str(raw), "--dof", "3", "--out", str(tmp_path / "c.json")])
        err = capsys.readouterr().err
        assert code == 2 and "not a regular file" in err and err.count("\n") == 1, err
