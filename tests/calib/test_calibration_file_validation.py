"""CAL.json is data from elsewhere: every malformed field is a one-line error, never a traceback
and never NaN loads."""

import json

import numpy as np
import pytest

from calib.cli import main
from calib.data.io import load_calibration
from calib.data.result import CalibrationError

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


@pytest.mark.parametrize("scale, message", [(1e300, "beyond what a fit"),
                                            (1e-300, "too small to fit")])
def test_readings_beyond_double_precision_are_one_line(tmp_path, capsys, scale, message):
    rng = np.random.default_rng(0)
    raw = tmp_path / "raw.csv"
    np.savetxt(raw, rng.normal(size=(100, 4)) * scale, delimiter=",", header="a,b,c,d",
               comments="")
    for extra in ([], ["--bias"]):
        code = main(["fit", str(raw), "--dof", "3", *extra, "--out", str(tmp_path / "c.json")])
        err = capsys.readouterr().err
        assert code == 2 and message in err and err.count("\n") == 1, err


def test_fewer_samples_than_channels_is_refused(tmp_path, capsys):
    raw = tmp_path / "raw.csv"
    np.savetxt(raw, np.random.default_rng(0).normal(size=(20, 50)), delimiter=",",
               header=",".join(f"c{i}" for i in range(50)), comments="")
    code = main(["fit", str(raw), "--dof", "3", "--out", str(tmp_path / "c.json")])
    assert code == 2 and "20 samples for 50 channels" in capsys.readouterr().err
    assert not (tmp_path / "c.json").exists()


def test_pure_noise_is_refused_as_its_warning_says(tmp_path, capsys):
    """A log of pure noise: the route's warning says the calibration is unreliable, so the
    verdict does (exit 3, one line, nothing written, never "reliable" beside that
    warning); written only on request, then called UNRELIABLE."""
    raw = tmp_path / "raw.csv"
    np.savetxt(raw, np.random.default_rng(0).normal(size=(200, 8)), delimiter=",",
               header=",".join(f"c{i}" for i in range(8)), comments="")
    args = ["fit", str(raw), "--dof", "3", "--magnitude", "9", "--out", str(tmp_path / "c.json")]
    code = main(args)
    err = capsys.readouterr().err
    assert code == 3 and not (tmp_path / "c.json").exists()
    assert err.count("\n") == 1 and "no rank-3 structure" in err
    code = main(args + ["--allow-unreliable"])
    out, err = capsys.readouterr()
    assert code == 0 and "UNRELIABLE" in out and "no rank-3 structure" in err
