"""Fuzzed files through sfm_learn's loaders and the ``mkv`` commands (hypothesis).

Whatever the bytes, a load either succeeds with finite content or fails with one line (a
``ValueError`` subclass from the library; exit status 2 and no traceback from the command), and
no input file changes.
"""

import hashlib
import io
import json
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sfm_learn.cli import main
from sfm_learn.eigenspace.policy import PolicyFileError, SfMPolicy, fit_policy

FUZZ = settings(max_examples=60, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])


@pytest.fixture(scope="module")
def good_policy(tmp_path_factory, small_train):
    d = tmp_path_factory.mktemp("fuzz")
    return fit_policy(small_train).save(d / "good.npz")


def members(path):
    with zipfile.ZipFile(path) as zf:
        return {n: zf.read(n) for n in zf.namelist()}


def write_members(path, content):
    with zipfile.ZipFile(path, "w") as zf:
        for n, b in content.items():
            zf.writestr(n, b)


def load_outcome(path):
    """'ok' (and the content is finite) or 'error' (one line); anything else fails the test."""
    try:
        pol = SfMPolicy.load(path)
    except PolicyFileError as e:
        assert "\n" not in str(e)
        return "error"
    assert np.all(np.isfinite(pol.projector.coef_)) and np.all(np.isfinite(pol.thresholds))
    return "ok"


@FUZZ
@given(data=st.binary(max_size=2000))
def test_random_bytes(tmp_path, data):
    path = tmp_path / "p.npz"
    path.write_bytes(data)
    assert load_outcome(path) == "error"


@FUZZ
@given(cut=st.floats(0.0, 1.0))
def test_truncated_files(tmp_path, good_policy, cut):
    raw = open(good_policy, "rb").read()
    path = tmp_path / "p.npz"
    path.write_bytes(raw[: int(cut * (len(raw) - 1))])
    assert load_outcome(path) == "error"


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-10**20, 10**20) | st.floats(allow_nan=False)
    | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner,
                                                                 max_size=3),
    max_leaves=6)


@FUZZ
@given(key=st.sampled_from(["format", "format_version", "feature_spec", "projector", "training",
                            "env_id", "sensor_names", "n_components"]),
       value=JSON_VALUES)
def test_malformed_metadata_fields(tmp_path, good_policy, key, value):
    content = members(good_policy)
    meta = json.loads(content["metadata.json"])
    meta[key] = value
    content["metadata.json"] = json.dumps(meta).encode()
    path = tmp_path / "p.npz"
    write_members(path, content)
    load_outcome(path)  # either outcome, never another exception


@FUZZ
@given(member=st.sampled_from(["projector.coef_.npy", "projector.intercept_.npy",
                               "projector.mean_.npy", "projector.scale_.npy",
                               "projector.components_.npy", "thresholds.npy",
                               "projector.n_components_.npy", "projector.stat.r.npy"]),
       value=st.sampled_from([np.nan, np.inf, -np.inf, 3e38, 0.0, -1.0]),
       shape=st.sampled_from(["same", "scalar", "row"]))
def test_damaged_arrays(tmp_path, good_policy, member, value, shape):
    content = members(good_policy)
    a = np.load(io.BytesIO(content[member]))
    if shape == "same":
        b = np.full(a.shape, value, dtype=np.float64)
    elif shape == "scalar":
        b = np.asarray(value)
    else:
        b = np.full((1,) + a.shape, value)
    buf = io.BytesIO()
    np.save(buf, b)
    content[member] = buf.getvalue()
    path = tmp_path / "p.npz"
    write_members(path, content)
    outcome = load_outcome(path)
    if not np.isfinite(value) and shape != "scalar" and a.size and member != "projector.stat.r.npy":
        assert outcome == "error"


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.binary(max_size=300))
def test_commands_on_fuzzed_files_are_one_line(tmp_path, capsys, good_policy, data):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(data)
    before = hashlib.sha256(data).hexdigest()
    for argv in (["fit", str(bad), "--out", str(tmp_path / "o.npz")],
                 ["compare", str(bad), str(good_policy)],
                 ["eval", "--env", "MKVJam-v0", "--policy", f"sfm:{bad}", "--episodes", "1"],
                 ["train-bc", str(bad), "--out", str(tmp_path / "o.zip")]):
        code = main(argv)
        err = capsys.readouterr().err
        assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, (argv, err)
    assert hashlib.sha256(bad.read_bytes()).hexdigest() == before
    assert not (tmp_path / "o.npz").exists() and not (tmp_path / "o.zip").exists()


@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(flips=st.lists(st.tuples(st.floats(0, 1), st.integers(0, 255)), min_size=1, max_size=30))
def test_flipped_bytes_in_policy_and_dataset_files(tmp_path, good_policy, small_train, flips):
    """Damage inside the zip's compressed streams (zlib errors, 'encrypted' member flags)."""
    from mkv_env.dataset import DatasetError, load, save

    data_path = tmp_path / "d_ok.npz"
    if not data_path.exists():
        save(small_train, data_path)
    for path, loader, error in ((good_policy, SfMPolicy.load, PolicyFileError),
                                (data_path, load, DatasetError)):
        raw = bytearray(open(path, "rb").read())
        for where, byte in flips:
            raw[min(int(where * len(raw)), len(raw) - 1)] = byte
        bad = tmp_path / "flipped.npz"
        bad.write_bytes(bytes(raw))
        try:
            loader(bad)
        except error as e:
            assert "\n" not in str(e)


def _npy_with_unclosed_header() -> bytes:
    # the header numpy parses as a Python literal, cut mid-tuple: the tokenizer raises
    # TokenError, neither ValueError nor SyntaxError (found by the flipped-bytes test above)
    import struct

    header = "{'descr': '<i8', 'fortran_order': False, 'shape': (2, "
    header += " " * (64 - 10 - len(header) - 1) + "\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode() + bytes(16)


def test_a_npy_header_the_tokenizer_rejects_is_a_one_line_error(tmp_path, good_policy,
                                                                small_train):
    from mkv_env.dataset import DatasetError, load, save

    data_path = tmp_path / "d.npz"
    save(small_train, data_path)
    for path, loader, error in ((good_policy, SfMPolicy.load, PolicyFileError),
                                (str(data_path), load, DatasetError)):
        content = members(path)
        first = next(n for n in content if n.endswith(".npy"))
        content[first] = _npy_with_unclosed_header()
        bad = tmp_path / "bad.npz"
        write_members(bad, content)
        with pytest.raises(error, match="TokenError|truncated or corrupt|not a readable") as e:
            loader(bad)
        assert "\n" not in str(e.value)
