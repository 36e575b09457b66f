"""Streamed fits (calib.data.stream: CSV chunks, dask arrays) equal the in-memory fits; strided
subsamples are chosen by the global row index; one-line errors and the CLI's --chunk-rows."""

import json
import warnings

import numpy as np
import pytest

from calib import fit_bias, fit_least_squares, fit_sfm
from calib.cli import main
from calib.data.io import CSVSource, write_csv
from calib.data.result import CalibrationError, CalibrationWarning
from calib.data.stream import (
    CHUNK_ROWS,
    QR,
    ArraySource,
    DaskSource,
    FilteredSource,
    MappedSource,
    as_source,
)
from calib.simulation.simulate import paper_trial

CH = [f"g{i}" for i in range(1, 9)]
N = 60_013  # > 50,000: strided subsample plus full-data steps; > 20,000: the Gram route
CHUNK = 7_777  # divides neither N nor CHUNK_ROWS


def close(a, b, tol=1e-9):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(a)), 1e-300)) <= tol


@pytest.fixture(scope="module")
def data():
    return paper_trial(3, rng=4, n=N)


@pytest.fixture(scope="module")
def csv_path(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("stream") / "raw.csv"
    write_csv(path, CH, data.Z)
    return path


def fits(fn, Z, path, **kw):
    """fn on the array, on the CSV in chunks of CHUNK rows and on a dask array."""
    da = pytest.importorskip("dask.array")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CalibrationWarning)
        return (fn(Z, **kw), fn(CSVSource(str(path), CHUNK), **kw),
                fn(da.from_array(Z, chunks=(10_007, 5)), **kw))


def rotated_onto(C, ref):
    P, _, Qt = np.linalg.svd(ref @ C.T)
    return P @ Qt @ C


@pytest.mark.parametrize("method", ["centered", "paper"])
def test_bias_routes_stream_equal_in_memory(data, csv_path, method):
    ref, csv, dsk = fits(lambda z, **kw: fit_bias(z, 3, **kw), data.Z, csv_path, method=method)
    # The streamed passes sum the same canonical blocks in the same order, so the results are
    # usually identical to the bit. The paper route's unit frame is a gauge (B -> R B leaves its
    # residuals unchanged) that its refinement fixes by rounding: data changed by one ulp turn
    # its C by ~1% (offset 3e-11, C up to that rotation 1e-9), so if the BLAS rounds a block
    # differently (alignment) only C up to rotation is comparable.
    tol = 1e-9 if method == "centered" else 1e-8
    for cal in (csv, dsk):
        C = cal.C if method == "centered" else rotated_onto(cal.C, ref.C)
        assert close(ref.C, C, tol) and close(ref.offset, cal.offset)
        for key in ("n_samples", "coverage", "rank_gap", "residual_magnitude_rms"):
            assert cal.diagnostics[key] == pytest.approx(ref.diagnostics[key], rel=1e-7)
        assert close(ref.diagnostics["offset_stderr"], cal.diagnostics["offset_stderr"], 1e-6)
    assert ref.diagnostics["n_samples"] == N
    # and it is a calibration: the offset is recovered
    assert np.max(np.abs(ref.offset - data.offset)) < 0.05 * np.max(np.abs(data.offset))


def test_sfm_stream_equal_in_memory(tmp_path, data):
    Z = data.Z - data.offset
    write_csv(tmp_path / "z.csv", CH, Z)
    ref, csv, dsk = fits(lambda z: fit_sfm(z, 3), Z, tmp_path / "z.csv")
    for cal in (csv, dsk):
        assert close(ref.C, cal.C) and np.all(cal.offset == 0)
        assert cal.diagnostics["coverage"] == pytest.approx(ref.diagnostics["coverage"])


@pytest.mark.parametrize("bias", [False, True])
def test_least_squares_stream_equal_in_memory(bias):
    da = pytest.importorskip("dask.array")
    rng = np.random.default_rng(0)
    n = 30_011
    M = rng.normal(size=(n, 3))
    Z = M @ rng.normal(size=(3, 8)) + 5.0 + 1e-3 * rng.normal(size=(n, 8))
    ref = fit_least_squares(Z, M, bias=bias)
    for Zs, Ms in ((da.from_array(Z, chunks=(4_001, 8)), da.from_array(M, chunks=(6_007, 3))),
                   (ArraySource(Z, 3_001), ArraySource(M, 5_003))):
        cal = fit_least_squares(Zs, Ms, bias=bias)
        assert close(ref.C, cal.C) and close(ref.offset, cal.offset, 1e-9 if bias else 0)
        d0, d1 = ref.diagnostics, cal.diagnostics
        assert close(d0["singular_values"], d1["singular_values"])
        assert d1["residual_rms"] == pytest.approx(d0["residual_rms"], rel=1e-9)
    # the streamed QR is lstsq on the whole matrix, as the old in-memory fit computed it
    X = np.hstack([Z, np.ones((n, 1))]) if bias else Z
    assert close(np.linalg.svd(X, compute_uv=False), ref.diagnostics["singular_values"], 1e-12)
    if not bias:
        Ct, *_ = np.linalg.lstsq(Z, M, rcond=None)
        assert close(Ct.T, ref.C, 1e-12)


def test_qr_lstsq_matches_numpy_including_rank_deficiency():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(50_000, 6))
    A[:, 5] = A[:, 0] + A[:, 1]  # rank 5: the minimum-norm solution
    b = rng.normal(size=(50_000, 2))
    qr = QR()
    for i in range(0, len(A), 9_999):
        qr.add(np.hstack([A[i : i + 9_999], b[i : i + 9_999]]))
    x, *_ = np.linalg.lstsq(A, b, rcond=None)
    assert close(x, qr.lstsq(6), 1e-10)
    assert close(np.linalg.svd(A, compute_uv=False)[:5], qr.singular_values(6)[:5], 1e-12)


def test_strided_rows_follow_the_global_index(data, csv_path):
    da = pytest.importorskip("dask.array")
    Z = data.Z
    for step in (1, 3, 7, 1_201, 50_000):
        want = Z[::step]
        assert np.array_equal(CSVSource(str(csv_path), CHUNK).strided(step), want)
        assert np.array_equal(DaskSource(da.from_array(Z, chunks=(9_001, 8))).strided(step), want)
        assert np.array_equal(ArraySource(Z, 5_000).strided(step), want)
    # several steps gathered in one pass; a derived source maps the same rows
    src = CSVSource(str(csv_path), CHUNK)
    src.want(2, 5)
    assert sum(len(b) for _, b in src.blocks()) == N and src.n == N
    assert np.array_equal(src._strided[2], Z[::2]) and np.array_equal(src._strided[5], Z[::5])
    proj = MappedSource(src, lambda b: b[:, :2] * 2.0)
    assert np.array_equal(proj.strided(5), Z[::5, :2] * 2.0)
    # blocks are canonical whatever the source's chunking
    starts = [s for s, _ in CSVSource(str(csv_path), CHUNK).blocks()]
    assert starts == list(range(0, N, CHUNK_ROWS))


def test_nonfinite_rows_per_chunk(tmp_path, data):
    Z = data.Z[:45_000].copy()
    Z[[7, 8_000, 31_111, 44_999], [0, 3, 5, 7]] = [np.nan, np.inf, -np.inf, np.nan]
    write_csv(tmp_path / "bad.csv", CH, Z)
    src = CSVSource(str(tmp_path / "bad.csv"), CHUNK)
    with pytest.raises(CalibrationError, match=r"4 row\(s\) with NaN/inf \(first at row 7\)"):
        fit_bias(src, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CalibrationWarning)
        ref = fit_bias(Z, 3, drop_nonfinite=True)
        cal = fit_bias(src, 3, drop_nonfinite=True)
    assert cal.diagnostics["n_dropped_nonfinite"] == 4 and cal.diagnostics["n_samples"] == 44_996
    assert close(ref.C, cal.C) and close(ref.offset, cal.offset)
    # the kept rows' index decides the strided rows
    kept = Z[np.isfinite(Z).all(axis=1)]
    filtered = FilteredSource(CSVSource(str(tmp_path / "bad.csv"), CHUNK))
    assert np.array_equal(filtered.strided(13), kept[::13])


def test_csv_errors_are_one_line(tmp_path, data):
    lines = ["g1,g2,g3"] + [f"{i},{i % 7},{i % 5}" for i in range(30)]
    lines[25] = "1,oops,3"
    (tmp_path / "a.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(CalibrationError, match=r"a.csv line 26: non-numeric value$"):
        fit_sfm(CSVSource(str(tmp_path / "a.csv"), 4), 2)
    lines[25] = "1,2"
    (tmp_path / "b.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(CalibrationError, match=r"b.csv line 26: 2 fields, header has 3$"):
        fit_sfm(CSVSource(str(tmp_path / "b.csv"), 4), 2)
    (tmp_path / "e.csv").write_text("\n\n")
    with pytest.raises(CalibrationError, match="is empty"):
        CSVSource(str(tmp_path / "e.csv"))
    with pytest.raises(CalibrationError, match="must be 2-D"):
        as_source(np.zeros(5))


def test_csv_quoted_field_across_a_chunk_boundary(tmp_path):
    rows = [f"{i}.5,{(i * 7) % 11},{(i * 3) % 13}" for i in range(40)]
    rows[9] = '"9.5",2,"3"'  # quoted numbers: the careful reader

    def source(row19, row30=None):
        r = list(rows)
        r[19] = row19
        if row30:
            r[30] = row30
        (tmp_path / "q.csv").write_text("a,b,c\n" + "\n".join(r) + "\n")
        return CSVSource(str(tmp_path / "q.csv"), 20)  # row 19 is the chunk's last line

    with pytest.raises(CalibrationError, match=r"q.csv line 21: non-numeric value$"):
        source('"19\n.5",1,2').to_array()
    got = source('"19.5\n",1,2').to_array()  # float() takes the trailing newline
    assert got.shape == (40, 3) and got[19, 0] == 19.5 and got[20, 0] == 20.5
    assert np.array_equal(got[:, 0], np.arange(40) + 0.5)
    with pytest.raises(CalibrationError, match=r"q.csv line 33: 2 fields, header has 3$"):
        source('"19.5\n",1,2', "1,2").to_array()  # line numbers count the extra line


def run(argv, capsys):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("bias", [True, False])
def test_cli_chunk_rows_equals_in_memory(tmp_path, capsys, csv_path, bias):
    outs = []
    for extra in ([], ["--chunk-rows", 9_999]):
        out = tmp_path / f"cal{len(extra)}.json"
        code, msg, err = run(["fit", csv_path, "--dof", 3, *(["--bias"] if bias else []),
                              "--magnitude", 9.81, *extra, "--out", out], capsys)
        assert code == 0, err
        outs.append(json.loads(out.read_text()))
    assert close(outs[0]["C"], outs[1]["C"]) and close(outs[0]["offset"], outs[1]["offset"],
                                                       1e-9 if bias else 0)
    assert outs[1]["channels"] == CH and outs[1]["diagnostics"]["n_samples"] == N


@pytest.fixture(scope="module")
def joint_ref(data):
    """4 known pairs (noise-free readings of known loads: the trial's own shape and offsets) and
    the in-memory joint fit with them, which the streamed and the CLI's chunked fits below are
    held to."""
    from calib import fit_joint
    from calib.simulation.simulate import (
        PAPER_FORCE_MAGNITUDE,
        paper_shape_matrix,
        sample_directions,
    )

    Mk = PAPER_FORCE_MAGNITUDE * sample_directions(4, 3, np.random.default_rng(1))
    Zk = Mk @ paper_shape_matrix() + data.offset
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CalibrationWarning)
        return Zk, Mk, fit_joint(data.Z, Zk, Mk, known_samples=1)


def test_joint_stream_equal_in_memory(data, csv_path, joint_ref):
    from calib import fit_joint

    da = pytest.importorskip("dask.array")
    Zk, Mk, ref = joint_ref
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CalibrationWarning)
        csv = fit_joint(CSVSource(str(csv_path), CHUNK), Zk, Mk, known_samples=1)
        dsk = fit_joint(da.from_array(data.Z, chunks=(10_007, 5)), Zk, Mk, known_samples=1)
    for cal in (csv, dsk):
        assert close(ref.C, cal.C) and close(ref.offset, cal.offset)
        assert cal.diagnostics["n_samples"] == N
        assert close(ref.diagnostics["offset_stderr"], cal.diagnostics["offset_stderr"], 1e-6)
    assert np.max(np.abs(ref.offset - data.offset)) < 0.05 * np.max(np.abs(data.offset))


def test_cli_chunk_rows_errors(tmp_path, capsys, csv_path):
    out = tmp_path / "cal.json"
    code, _, err = run(["fit", csv_path, "--dof", 3, "--bias", "--bootstrap", 10,
                        "--chunk-rows", 1000, "--out", out], capsys)
    assert code == 2 and not out.exists()
    assert err == "calib: error: --chunk-rows is not supported with --bootstrap\n"
    lines = ["g1,g2,g3"] + [f"{i},{i % 7},{i % 5}" for i in range(300)]
    lines[250] = "1,x,3"
    (tmp_path / "bad.csv").write_text("\n".join(lines) + "\n")
    code, _, err = run(["fit", tmp_path / "bad.csv", "--dof", 2, "--bias", "--chunk-rows", 64,
                        "--out", out], capsys)
    assert code == 2 and not out.exists()
    assert err == f"calib: error: {tmp_path / 'bad.csv'} line 251: non-numeric value\n"
    code, _, err = run(["fit", csv_path, "--dof", 3, "--chunk-rows", 0, "--out", out], capsys)
    assert code == 2 and err.count("\n") == 1 and not out.exists()


def test_cli_joint_chunk_rows_equals_in_memory(tmp_path, capsys, csv_path, joint_ref):
    """``calib fit --method joint --chunk-rows`` writes the in-memory joint fit of the same log
    and known pairs (the CSV holds every value to the bit)."""
    Zk, Mk, ref = joint_ref
    write_csv(tmp_path / "known.csv", CH + ["Fx", "Fy", "Fz"], np.hstack([Zk, Mk]))
    out = tmp_path / "cal.json"
    code, _, err = run(["fit", csv_path, "--dof", 3, "--bias", "--method", "joint",
                        "--known", tmp_path / "known.csv", "--known-samples", 1,
                        "--chunk-rows", 9_999, "--out", out], capsys)
    assert code == 0, err
    saved = json.loads(out.read_text())
    assert close(ref.C, saved["C"]) and close(ref.offset, saved["offset"])
    assert saved["method"] == "joint"


def test_ft6_stream_equal_in_memory(tmp_path):
    from calib.estimators.ft6 import fit_ft6, random_known_loads
    from calib.simulation.simulate import random_shape, simulate

    rng = np.random.default_rng(7)
    S = random_shape(6, 8, rng)
    z0 = rng.normal(size=8) * 2
    d = simulate(S, 30_011, rng, magnitude=10.0, offset=z0, lever_arm=rng.normal(size=3) * 0.1,
                 noise=0.01)
    Mk = random_known_loads(6, rng, 10.0, 1.0)
    path = tmp_path / "ft6.csv"
    write_csv(path, CH, d.Z)
    ref, csv, dsk = fits(lambda z, **kw: fit_ft6(z, Mk @ S + z0, Mk, **kw), d.Z, path)
    for cal in (csv, dsk):
        assert close(ref.C, cal.C) and close(ref.offset, cal.offset)
        assert cal.diagnostics["n_samples"] == 30_011
    known = tmp_path / "known.csv"
    write_csv(known, CH + ["Fx", "Fy", "Fz", "Tx", "Ty", "Tz"], np.hstack([Mk @ S + z0, Mk]))
    outs = []
    for extra in ([], ["--chunk-rows", 4_321]):
        out = tmp_path / f"cal{len(extra)}.json"
        assert main([str(a) for a in ["fit", path, "--dof", 6, "--bias", "--known", known,
                                      *extra, "--out", out]]) == 0
        outs.append(json.loads(out.read_text()))
    assert close(outs[0]["C"], outs[1]["C"]) and close(outs[0]["offset"], outs[1]["offset"])


def test_csv_passes_show_a_progress_bar_on_a_terminal(tmp_path, data, monkeypatch):
    import io
    import sys

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    path = tmp_path / "p.csv"
    write_csv(path, CH, data.Z[:30_000])
    err = Terminal()
    monkeypatch.setattr(sys, "stderr", err)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CalibrationWarning)
        shown = fit_bias(CSVSource(str(path), 5_000, progress=True), 3)
        plain = fit_bias(CSVSource(str(path), 5_000), 3)
    assert "pass 1" in err.getvalue() and "pass 2" in err.getvalue()
    assert np.array_equal(shown.C, plain.C) and np.array_equal(shown.offset, plain.offset)


def test_chunked_progress_counts_rows_and_knows_the_total_from_the_second_pass(tmp_path,
                                                                            monkeypatch):
    """The --chunk-rows bar counts data rows (not bytes or characters); the first pass learns
    their number, later passes show it as the total and end full."""
    import sfm_common.progress as prog
    from calib.data.io import CSVSource

    bars = []

    def fake(total, desc="", **kw):
        bars.append((prog.NullBar(total), kw))
        return bars[-1][0]

    monkeypatch.setattr(prog, "progress", fake)
    rows = "\n".join(f"{i},{2 * i},{3 * i}" for i in range(5000))
    p = tmp_path / "u.csv"
    p.write_text("\ufeffg1,g2,g3\n" + rows + "\n", encoding="utf-8")
    src = CSVSource(str(p), 700, progress=True)
    for _ in range(2):
        assert sum(len(b) for _, b in src.blocks()) == 5000
    (first, kw), (second, _) = bars[-2:]
    assert first.total is None and first.n == 5000
    assert second.total == second.n == 5000
    assert kw.get("unit") == "row"
