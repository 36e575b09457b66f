"""What ``calib fit`` and ``calib apply`` accept as input files: a CSV header of non-empty,
unique column names (a byte-order mark stripped), in memory and streamed (``--chunk-rows``); only
regular files (a FIFO is refused at once, never waited on); joint-only options only with
``--method joint``. Every refusal is one line on stderr with exit status 2."""

import csv
import io
import json
import os
import signal

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calib.cli import main
from calib.data.io import CSVSource, read_csv, write_csv
from calib.data.result import CalibrationError
from calib.simulation.simulate import paper_trial

CH = [f"g{i}" for i in range(1, 9)]


@pytest.fixture
def deadline():
    """Fail (instead of hanging the suite) if the test blocks for 20 s, e.g. on a FIFO."""
    def timeout(*_):
        raise TimeoutError("blocked: an input was waited on instead of refused")

    old = signal.signal(signal.SIGALRM, timeout)
    signal.alarm(20)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)


def run(argv, capsys):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, err


def refused(code, err, *words):
    assert code == 2 and err.startswith("calib: error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    for w in words:
        assert w in err, err


@pytest.fixture(scope="module")
def trial():
    return paper_trial(2, rng=0)


@pytest.fixture
def good(tmp_path, trial):
    path = tmp_path / "raw.csv"
    write_csv(path, CH, trial.Z)
    return path


FIT = ["--dof", "3", "--magnitude", "9.81"]


# ------------------------------------------------------------------------------ headers
def _body(trial):
    return "\n".join(",".join(repr(float(x)) for x in row) for row in trial.Z) + "\n"


@pytest.mark.parametrize("chunk", [[], ["--chunk-rows", "50"]])
@pytest.mark.parametrize("first, words", [
    (None, ["line 1", "no header", "holds numbers"]),             # the first reading as header
    (",,,,,,,", ["line 1", "no column names"]),                    # refused, not skipped
    (" , , ,,,,, ", ["line 1", "no column names"]),
    ("g1,g2,,g4,g5,g6,g7,g8", ["line 1", "column 3 has no name"]),
    ("g1,g2,g3,g4,g5,g6,g7,g1", ["duplicate column names", "'g1' twice"]),
    ("g1,g2,g3,g4,g5,g6,g7, g1 ", ["duplicate column names"]),     # the same name once stripped
    ("g1,g2,g3,g4,g5,g6,g7,3.5", ["no header", "'3.5'"]),
    ("g1,g2,g3,g4,g5,g6,g7,nan", ["no header", "'nan'"]),
    ("g1,g2,g3,g4,g5,g6,g7,g\u200b8", ["invisible or control character"]),
])
def test_fit_refuses_a_bad_header_in_one_line(tmp_path, capsys, trial, chunk, first, words):
    path = tmp_path / "raw.csv"
    path.write_text(("" if first is None else first + "\n") + _body(trial))
    code, err = run(["fit", path, *FIT, *chunk, "--out", tmp_path / "cal.json"], capsys)
    refused(code, err, str(path), *words)
    assert not (tmp_path / "cal.json").exists()


def test_apply_refuses_a_raw_file_without_a_header(tmp_path, capsys, good, trial):
    cal = tmp_path / "cal.json"
    assert run(["fit", good, *FIT, "--out", cal], capsys)[0] == 0
    bare = tmp_path / "bare.csv"
    bare.write_text(_body(trial))
    code, err = run(["apply", cal, bare, "--out", tmp_path / "loads.csv"], capsys)
    refused(code, err, "no header")
    assert not (tmp_path / "loads.csv").exists()


def test_known_file_without_a_header_is_refused(tmp_path, capsys, good, trial):
    known = tmp_path / "known.csv"
    known.write_text("1,2,3,4,5,6,7,8,9,10,11\n" * 4)
    code, err = run(["fit", good, "--dof", "3", "--known", known, "--out", tmp_path / "c.json"],
                    capsys)
    refused(code, err, str(known), "no header")


@pytest.mark.parametrize("chunk", [[], ["--chunk-rows", "50"]])
@pytest.mark.parametrize("prefix", ["\ufeff", "\ufeff\ufeff", "\n\ufeff", " \ufeff"])
def test_a_byte_order_mark_is_stripped_and_the_fit_is_unchanged(tmp_path, capsys, good, chunk,
                                                                prefix):
    plain = tmp_path / "plain.json"
    assert run(["fit", good, *FIT, *chunk, "--out", plain], capsys)[0] == 0
    bom = tmp_path / "bom.csv"
    bom.write_bytes(prefix.encode("utf-8") + good.read_bytes())
    out = tmp_path / "bom.json"
    code, err = run(["fit", bom, *FIT, *chunk, "--out", out], capsys)
    assert code == 0, err
    a, b = json.loads(plain.read_text()), json.loads(out.read_text())
    assert b["channels"] == CH and a["C"] == b["C"] and a["offset"] == b["offset"]


def _names():
    chars = st.characters(blacklist_categories=("Cs",), blacklist_characters="\r\n\x00")
    name = st.one_of(
        st.text(chars, max_size=6),
        st.sampled_from(["", " ", "g1", "g2", " g1", "1", "-2.5", "1e3", "nan", "inf", "x",
                         "\ufeffg1", "\ufeff", ",", '"', "a,b", "\t", "\u200b"]))
    return st.lists(name, min_size=1, max_size=6)


def _expected(names):
    """The stripped names if they make a valid header, else None."""
    stripped = [n.strip().lstrip("\ufeff").strip() for n in names]

    def number(s):
        try:
            float(s)
            return True
        except ValueError:
            return False
    ok = (all(stripped) and not any(number(s) for s in stripped)
          and all(s.isprintable() for s in stripped) and len(set(stripped)) == len(stripped))
    return stripped if ok else None


@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(names=_names(), bom=st.booleans())
def test_random_header_rows(tmp_path, names, bom):
    """Random header rows, written as a CSV writer quotes them: accepted exactly when the names,
    stripped of spaces and a byte-order mark, are non-empty, printable, not numbers and unique;
    the in-memory and streamed readers agree; a refusal is one line."""
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(names)
    rows = np.arange(3 * len(names), dtype=float).reshape(3, len(names)) + 0.5
    text = buf.getvalue() + "".join(",".join(repr(float(x)) for x in r) + "\n" for r in rows)
    path = tmp_path / "h.csv"
    path.write_bytes(("\ufeff" if bom else "").encode() + text.encode("utf-8"))
    expect = _expected(names)
    results = []
    for read in (read_csv, lambda p: (lambda s: (s.header, s.to_array()))(CSVSource(p, 2))):
        try:
            results.append(read(str(path)))
        except CalibrationError as e:
            assert "\n" not in str(e) and str(path) in str(e), str(e)
            results.append(None)
    if expect is None:
        assert results == [None, None], (names, results)
    else:
        for header, data in results:
            assert header == expect
            np.testing.assert_array_equal(data, rows)


# ------------------------------------------------------------------------ regular files only
@pytest.mark.parametrize("which", ["cal", "raw"])
def test_apply_refuses_a_fifo_at_once(tmp_path, capsys, good, deadline, which):
    cal = tmp_path / "cal.json"
    assert run(["fit", good, *FIT, "--out", cal], capsys)[0] == 0
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    args = [fifo, good] if which == "cal" else [cal, fifo]
    code, err = run(["apply", *args, "--out", tmp_path / "loads.csv"], capsys)
    refused(code, err, str(fifo), "not a regular file")
    assert not (tmp_path / "loads.csv").exists()


@pytest.mark.parametrize("chunk", [[], ["--chunk-rows", "50"]])
def test_fit_refuses_a_fifo_or_directory_as_any_input(tmp_path, capsys, good, deadline, chunk):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    for argv in (["fit", fifo, *FIT], ["fit", good, "--dof", "3", "--known", fifo],
                 ["fit", tmp_path, *FIT], ["fit", good, "--dof", "3", "--known", tmp_path]):
        code, err = run([*argv, *chunk, "--out", tmp_path / "c.json"], capsys)
        refused(code, err, "not a regular file")


def test_apply_refuses_a_directory_or_device_as_cal(tmp_path, capsys, good):
    for cal in (tmp_path, "/dev/zero"):
        code, err = run(["apply", cal, good, "--out", tmp_path / "loads.csv"], capsys)
        refused(code, err, "not a regular file")


def test_an_output_is_never_an_input(tmp_path, capsys, good):
    cal = tmp_path / "cal.json"
    assert run(["fit", good, *FIT, "--out", cal], capsys)[0] == 0
    before = {p: p.read_bytes() for p in (cal, good)}
    link = tmp_path / "link.csv"
    os.symlink(good, link)
    for argv in (["fit", good, *FIT, "--out", good], ["fit", good, *FIT, "--out", link],
                 ["apply", cal, good, "--out", cal], ["apply", cal, good, "--out", good],
                 ["apply", cal, good, "--out", link]):
        code, err = run(argv, capsys)
        refused(code, err, "also an input")
    assert before == {p: p.read_bytes() for p in (cal, good)}


# ---------------------------------------------------------------------- joint-only options
@pytest.mark.parametrize("option", [["--known-samples", "10"], ["--known-sigma", "0.01"],
                                    ["--magnitude-sigma", "0.1"]])
@pytest.mark.parametrize("method", [[], ["--method", "centered"], ["--method", "paper"]])
def test_joint_options_without_method_joint_are_refused(tmp_path, capsys, good, option, method):
    code, err = run(["fit", good, "--dof", "3", "--bias", *method, *option, "--magnitude",
                     "9.81", "--out", tmp_path / "c.json"], capsys)
    refused(code, err, option[0], "--method joint")
    assert not (tmp_path / "c.json").exists()


def test_library_readers_refuse_a_fifo_at_once(tmp_path, deadline):
    from calib.data.io import load_calibration
    from calib.estimators.magnetometer import load_furbrain, load_xyz

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    for load in (read_csv, lambda p: CSVSource(p), load_calibration, load_furbrain, load_xyz):
        with pytest.raises(CalibrationError, match="not a regular file"):
            load(str(fifo))
