"""scripts/calib_payload_study.py: its options' one-line errors and a one-rig run of a chosen
case (the study itself is run by hand; docs/calib_study.md)."""

import pytest


@pytest.mark.parametrize("argv, message", [
    (["--cases", "gauges"], "names 6 cases, not one"),
    (["--cases", "no such case"], "names 0 cases, not one"),
    (["--cases", "default,"], "names 0 cases, not one"),
    (["--cases", "default", "--write", "{doc}"], "--write replaces the whole table"),
    (["--rigs", "0"], "must be at least 1"),
    (["--workers", "0"], "must be at least 1"),
    (["--write", "/nonexistent/calib_study.md"], "is not a regular file"),
    (["--write", "/dev/null"], "is not a regular file"),
])
def test_bad_options_are_one_line_errors(load_script, capsys, tmp_path, argv, message):
    mod = load_script("calib_payload_study")
    doc = tmp_path / "study.md"
    doc.write_text("# a study\n")
    with pytest.raises(SystemExit) as e:
        mod.main([a.replace("{doc}", str(doc)) for a in argv])
    assert doc.read_text() == "# a study\n"  # nothing written
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert message in err[-1] and "Traceback" not in "".join(err)


def test_one_case_prints_its_row_only(load_script, capsys):
    mod = load_script("calib_payload_study")
    mod.main(["--rigs", "1", "--workers", "1", "--cases", "20 poses"])
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| ") and "case" not in line]
    assert len(rows) == 1 and rows[0].startswith("| 8 gauges, 20 poses |")
    assert "in predicted 95 % interval" in out and "of 1)" in out


def test_least_squares_offset_identified_only_where_the_directions_spread(load_script):
    # the column that tells refusals the data explain from the rest: least squares with every
    # load known identifies the offset of loads over the whole sphere, not of loads within a
    # narrow cone (the offset and the mean load are then one direction)
    import numpy as np

    mod = load_script("calib_payload_study")
    rng = np.random.default_rng(0)
    A, o = rng.normal(size=(3, 6)), rng.normal(size=6) * 50
    U = rng.normal(size=(60, 3))
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    narrow = np.array([0.0, 0.0, 1.0]) + 0.1 * rng.normal(size=(60, 3))
    narrow /= np.linalg.norm(narrow, axis=1, keepdims=True)
    for M, expected in ((10 * U, True), (10 * narrow, False)):
        Z = M @ A + o + 0.02 * rng.normal(size=(60, 6))
        assert mod.ls_offset_identified(Z, M) is expected
        # the units of the channels do not matter
        assert mod.ls_offset_identified(Z * np.logspace(-3, 3, 6), M) is expected
