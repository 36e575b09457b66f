"""Fuzzed inputs through ``calib fit`` and ``calib apply`` (hypothesis): one line on stderr, exit
status 2, no traceback, and no file changed or half-written; or a clean success with finite
outputs."""

import hashlib
import json
import math
import os

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calib.cli import main
from calib.data.io import write_csv
from calib.simulation.simulate import paper_trial

FUZZ = settings(max_examples=40, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])
CH = [f"g{i}" for i in range(1, 9)]


def fresh(tmp_path):
    """A new folder per hypothesis example (tmp_path is shared by all examples of a test)."""
    import pathlib
    import tempfile

    return pathlib.Path(tempfile.mkdtemp(dir=tmp_path))


def snapshot(d):
    return {p: hashlib.sha256((d / p).read_bytes()).hexdigest() for p in os.listdir(d)}


def run(argv, capsys):
    code = main([str(a) for a in argv])
    return code, capsys.readouterr().err


def check_failure_or_clean(tmp_path, capsys, argv, out):
    before = snapshot(tmp_path)
    code, err = run(argv, capsys)
    assert "Traceback" not in err
    if code != 0:
        assert code == 2 and err.startswith("calib: error:") and err.count("\n") == 1, err
        assert snapshot(tmp_path) == before  # nothing written, nothing changed
    else:
        after = snapshot(tmp_path)
        assert {k: v for k, v in after.items() if k != out.name} == before
        text = out.read_text()
        assert "NaN" not in text and "nan" not in text.lower().replace("channels", "")


@FUZZ
@given(data=st.binary(max_size=1500))
def test_random_bytes_as_raw_csv(tmp_path, capsys, data):
    tmp_path = fresh(tmp_path)
    raw = tmp_path / "raw.csv"
    raw.write_bytes(data)
    out = tmp_path / "cal.json"
    check_failure_or_clean(tmp_path, capsys, ["fit", raw, "--dof", "3", "--out", out], out)


@FUZZ
@given(value=st.sampled_from([math.nan, math.inf, -math.inf, 1e308, 1e-308, 0.0, 1e200]),
       row=st.integers(0, 175), col=st.integers(0, 7), bias=st.booleans())
def test_damaged_values_in_a_good_log(tmp_path, capsys, value, row, col, bias):
    tmp_path = fresh(tmp_path)
    Z = paper_trial(2, rng=0).Z.copy()
    Z[row, col] = value
    raw = tmp_path / "raw.csv"
    write_csv(raw, CH, Z)
    out = tmp_path / "cal.json"
    argv = ["fit", raw, "--dof", "3", "--magnitude", "9", "--out", out]
    check_failure_or_clean(tmp_path, capsys, argv + (["--bias"] if bias else []), out)


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-10**6, 10**6) | st.floats() | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=4), inner,
                                                                max_size=3),
    max_leaves=10)


@FUZZ
@given(key=st.sampled_from(["C", "offset", "dof", "channels", "diagnostics", "method"]),
       value=JSON_VALUES)
def test_malformed_calibration_json(tmp_path, capsys, key, value):
    tmp_path = fresh(tmp_path)
    d = paper_trial(2, rng=0)
    raw = tmp_path / "raw.csv"
    write_csv(raw, CH, d.Z)
    good = {"C": np.eye(3, 8).tolist(), "offset": [0.0] * 8, "dof": 3, "channels": CH}
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps({**good, key: value}))
    out = tmp_path / "loads.csv"
    check_failure_or_clean(tmp_path, capsys, ["apply", cal, raw, "--out", out], out)
