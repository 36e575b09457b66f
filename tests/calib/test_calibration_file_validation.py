"""CAL.json is data from elsewhere: every malformed field is a one-line error, never a traceback
and never NaN loads."""

import json

import numpy as np
import pytest

from calib.cli import main
from calib.io import load_calibration
from calib.result import CalibrationError

GOOD = {"C": [[1.0, 0.0, 0.5], [0.0, 1.0, 0.5]], "offset": [0.1, 0.2, 0.3], "dof": 2,
        "channels": ["a", "b", "c"]}


@pytest.mark.parametrize("edit, message", [
    ({"C": "abc"}, "C must be"),
    ({"C": [[1, 2, 3], [4, 5]]}, "C must be"),
    ({"C": [[1.0, None, 0.5], [0.0, 1.0, 0.5]]}, "NaN"),
    ({"C": [[1.0, float("nan"), 0.5], [0.0, 1.0, 0.5]]}, "NaN"),
    ({"offset": [1, 2]}, "columns"),
    ({"offset": "x"}, "offset must be"),
    ({"dof": 7}, "dof must be 2, 3 or 6"),
    ({"dof": "2"}, "dof must be 2, 3 or 6"),
    ({"dof": 3}, "rows but dof"),
    ({"channels": 5}, "channels must be 3 distinct names"),
    ({"channels": ["a", "a", "b"]}, "channels must be 3 distinct names"),
    ({"diagnostics": [1]}, "diagnostics must be"),
])
def test_malformed_calibration_files(tmp_path, edit, message):
    path = tmp_path / "cal.json"
    path.write_text(json.dumps({**GOOD, **edit}))
    with pytest.raises(CalibrationError, match=message) as e:
        load_calibration(str(path))
    assert "\n" not in str(e.value)


def test_binary_and_npz_files_are_one_line(tmp_path, capsys):
    raw = tmp_path / "raw.csv"
    raw.write_text("a,b,c\n1,2,3\n")
    for content in (bytes(range(256)), b"PK\x03\x04" + b"\x00" * 40):
        cal = tmp_path / "cal.json"
        cal.write_bytes(content)
        code = main(["apply", str(cal), str(raw), "--out", str(tmp_path / "out.csv")])
        err = capsys.readouterr().err
        assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert not (tmp_path / "out.csv").exists()


def test_a_good_file_applies_to_finite_loads(tmp_path):
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(GOOD))
    cal, channels = load_calibration(str(path))
    loads = cal.apply(np.array([[1.0, 2.0, 3.0]]))
    assert channels == ["a", "b", "c"] and np.all(np.isfinite(loads))
