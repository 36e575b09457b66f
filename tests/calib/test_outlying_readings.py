"""Readings far from the fitted model in a log of single readings: a spike, a glitch,
a known load stated for another reading.

Found on payload rigs with one reading of all channels 30 noise standard deviations off: on one
of the 4 known readings the fit measured up to 8.8x least squares on the same readings (4 of 20
beyond 3x, each written with exit 0 and the direction test's "not linear" warning, the wrong
cause); on an unknown reading up to 1.9x, with no warning.
:func:`calib.estimators.forward.misfit.outlying_readings`
flags such readings (a robust chi-square test, Bonferroni over the log); ``fit_joint`` names
them, refuses the fit where a flagged known reading moves it by more than its own predicted
error (``calib.verdict.reliability.KNOWN_INFLUENCE_MAX``), and with ``robust=True`` leaves them out.
"""

import functools
import json
import warnings

import numpy as np
import pytest

from calib import fit_joint, fit_least_squares
from calib.cli import main
from calib.data.io import write_csv
from calib.routes.joint import choose_known_poses
from calib.simulation.simulate import simulate_payload_rig
from calib.verdict.reliability import assess


def rms(a):
    return float(np.sqrt(np.mean(np.sum(a**2, axis=1))))


def _rig(seed, where=None, amp=30.0, **kw):
    """The payload study's default protocol with one reading of all channels ``amp`` noise
    standard deviations off (``where``: "known", "unknown" or None): (training readings, their
    stated loads, known rows, test rows' readings and loads, the spiked row, the rig)."""
    rig = simulate_payload_rig(seed, poses=80, **kw)
    tr, te = rig.split("poses")
    Z, Mt = rig.Z[tr].copy(), rig.stated_loads[rig.pose][tr]
    kn = choose_known_poses(Mt / np.linalg.norm(Mt, axis=1, keepdims=True), 4)
    rng = np.random.default_rng(seed + 1)
    row = None
    if where is not None:
        pool = kn if where == "known" else np.setdiff1d(np.arange(len(Z)), kn)
        row = int(rng.choice(pool))
        Z[row] += amp * np.sqrt(np.diag(rig.noise_cov)) * rng.choice([-1, 1], size=Z.shape[1])
    return Z, Mt, kn, rig.Z[te], rig.stated_loads[rig.pose][te], row


def _fit(Z, Mt, kn, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cal = fit_joint(Z, Z[kn], Mt[kn], 3, known_samples=1, **kw)
    return cal, [str(w.message) for w in caught]


@functools.cache
def _spiked(seed, where, robust=False):
    """``_rig(seed, where)`` and ``_fit`` of it (with ``robust``), computed once for the tests
    that read the same spiked rig: (the ``_rig`` tuple, the calibration, its warnings)."""
    r = _rig(seed, where)
    Z, Mt, kn = r[:3]
    return r, *_fit(Z, Mt, kn, robust=robust)


def _fit_argv(tmp_path, Z, Mt, kn):
    """``calib fit --method joint`` on ``Z`` written as a CSV, the rows ``kn`` its known loads."""
    ch = [f"g{i}" for i in range(Z.shape[1])]
    write_csv(tmp_path / "log.csv", ch, Z)
    write_csv(tmp_path / "known.csv", ch + ["Fx", "Fy", "Fz"], np.hstack([Z[kn], Mt[kn]]))
    return ["fit", str(tmp_path / "log.csv"), "--dof", "3", "--method", "joint", "--known",
            str(tmp_path / "known.csv"), "--known-samples", "1", "--out",
            str(tmp_path / "cal.json")]


@pytest.mark.parametrize("kw", [{}, {"wrench": True, "gauges": 8}, {"nonlinearity": 0.05},
                                {"poses": 2000, "sweep": True}])
def test_no_reading_of_a_clean_log_is_flagged(kw):
    """Independent or gauge-mixed noise, a 5 % nonlinear sensor, a sweep: nothing flagged, no
    warning of it (measured on 180 rigs of these and other cases: none)."""
    kw = {"poses": 80, **kw}
    for seed in (33_000, 33_001):
        rig = simulate_payload_rig(seed, **kw)
        tr, _ = rig.split("poses")
        Mt = rig.stated_loads[rig.pose][tr]
        kn = choose_known_poses(Mt / np.linalg.norm(Mt, axis=1, keepdims=True), 4)
        cal, said = _fit(rig.Z[tr], Mt, kn)
        o = cal.diagnostics["joint"]["outlying_readings"]
        assert o is not None and len(o["log_rows"]) == 0 and len(o["known"]) == 0, (seed, o)
        assert not any("far from the fitted model" in s for s in said)


def test_a_spike_on_a_known_reading_is_never_written_far_beyond_least_squares():
    """Six new rigs, a 30-sd spike on one known reading: every fit is refused or within 3x least
    squares on the same readings (before: up to 8.8x, written). The reading is flagged and named
    on at least 5 (measured 5 here: the one it missed, the fit took up the spike at 1.96x; 20 of
    20 on the development rigs); where it is, ``robust=True`` leaves it out and the fit is
    within 1.5x of least squares (measured 0.85-1.32x)."""
    named = 0
    for seed in range(33_010, 33_016):
        (Z, Mt, kn, Zte, Mte, row), cal, said = _spiked(seed, "known")
        ls = fit_least_squares(Z, Mt, bias=True)
        ratio = rms(cal.apply(Zte) - Mte) / rms(ls.apply(Zte) - Mte)
        o = cal.diagnostics["joint"]["outlying_readings"]
        k = int(np.flatnonzero(kn == row)[0])
        if list(o["known"]) == [k]:
            named += 1
            assert any(f"known load(s) {k} (counted from 0)" in s for s in said)
        assert assess(cal, Z[kn], Mt[kn]) or ratio <= 3.0, (seed, ratio)
        if list(o["known"]) == [k]:
            _, rob, _ = _spiked(seed, "known", robust=True)
            assert rms(rob.apply(Zte) - Mte) <= 1.5 * rms(ls.apply(Zte) - Mte), seed
            assert rob.diagnostics["joint"]["outlier_known_rejected"] == [k]
            assert rob.diagnostics["joint"]["n_known"] == 3
    assert named >= 5


def test_a_known_reading_that_barely_moves_the_fit_is_told_not_refused(monkeypatch):
    """A flagged known reading whose removal moves the loads by less than the fit's predicted
    error (heavy-tailed noise's tail draws measured 0.4-0.8x) is told and the fit kept: here the
    limit is raised past the measured influence, and the same fit passes."""
    import calib.verdict.reliability as reliability

    (Z, Mt, kn, *_), cal, _ = _spiked(33_010, "known")
    infl = cal.diagnostics["joint"]["outlying_readings"]["known_influence"]
    assert infl > reliability.KNOWN_INFLUENCE_MAX
    assert any("known load" in r for r in assess(cal, Z[kn], Mt[kn]))
    monkeypatch.setattr(reliability, "KNOWN_INFLUENCE_MAX", 2 * infl)
    assert not any("known load" in r for r in assess(cal, Z[kn], Mt[kn]))


def test_a_spike_on_an_unknown_reading_is_named_by_its_row_and_left_out_when_asked():
    (Z, Mt, kn, Zte, Mte, row), cal, said = _spiked(33_020, "unknown")
    o = cal.diagnostics["joint"]["outlying_readings"]
    assert list(o["rows"]) == [row] and len(o["known"]) == 0
    assert any(f"row(s) {row}, counted from 0" in s for s in said)
    assert not assess(cal, Z[kn], Mt[kn])  # told, not refused: an unknown reading moves it less
    rob, _ = _fit(Z, Mt, kn, robust=True)
    assert rob.diagnostics["joint"]["outlier_rows_rejected"] == [row]
    clean, _ = _fit(np.delete(Z, row, axis=0), Mt[np.setdiff1d(np.arange(len(Z)), row)],
                    kn - (kn > row))
    np.testing.assert_allclose(rob.apply(Zte), clean.apply(Zte), rtol=1e-6, atol=1e-9)


def test_the_flag_is_unit_free_order_free_and_offset_free():
    Z, Mt, kn, _, _, row = _rig(33_021, "unknown")
    rng = np.random.default_rng(5)
    scale = 10.0 ** rng.uniform(-4, 4, Z.shape[1])
    perm = rng.permutation(Z.shape[1])
    shift = rng.normal(size=Z.shape[1]) * 1e3 * scale
    for Zx in (Z, (Z * scale + shift)[:, perm]):
        cal, _ = _fit(Zx, Mt, kn)
        o = cal.diagnostics["joint"]["outlying_readings"]
        assert list(o["rows"]) == [row], o


def test_rows_are_the_logs_own_where_a_long_log_is_strided(monkeypatch):
    """A log longer than the forward fit's rows is fitted on strided rows: the row named is the
    user's row, not the strided subset's index (the limit lowered to 2,000 rows here)."""
    import calib.routes.forward_rows as forward_rows

    monkeypatch.setattr(forward_rows, "FORWARD_MAX_ROWS", 2_000)
    rig = simulate_payload_rig(33_030, poses=6_000, sweep=True)
    Z = rig.Z.copy()
    M = rig.stated_loads[rig.pose]
    kn = choose_known_poses(M / np.linalg.norm(M, axis=1, keepdims=True), 4)
    step = forward_rows._forward_step(len(Z))
    assert step > 1
    row = step * 1_001  # a row the strided fit sees, not a known one
    assert row not in kn
    Z[row] += 30 * np.sqrt(np.diag(rig.noise_cov))
    cal, said = _fit(Z, M, kn)
    assert row in list(cal.diagnostics["joint"]["outlying_readings"]["rows"])
    assert any(f"{row}" in s and "far from the fitted model" in s for s in said)


def test_calib_fit_refuses_with_the_known_reading_named(tmp_path, capsys):
    Z, Mt, kn, *_ = _rig(33_010, "known")
    argv = _fit_argv(tmp_path, Z, Mt, kn)
    assert main(argv) == 3
    err = capsys.readouterr().err
    assert "calib: unreliable:" in err and "lies far from the fitted model" in err
    assert not (tmp_path / "cal.json").exists()
    assert main(argv + ["--robust"]) == 0, capsys.readouterr().err
    saved = json.loads((tmp_path / "cal.json").read_text())
    assert len(saved["diagnostics"]["joint"]["outlier_known_rejected"]) == 1


def test_a_sweep_with_spikes_is_fitted_as_a_sweep_and_its_spikes_named():
    """1 % of a 1,000-reading sweep's readings 20 noise levels off: before, the spikes chopped
    the sweep into runs that read as static poses (8 of them), and the rig fit refused the log
    (too few poses for the affine model, exit 2). Now the pose finding leaves isolated spikes out
    without splitting the run, the log is fitted as a sweep, the fit names the spikes, and
    ``robust=True`` leaves them out (measured on 4 rigs: 0.88-0.97x least squares, against
    1.06-1.22x with them)."""
    from calib.estimators.rig.poses import find_poses

    rig = simulate_payload_rig(36_000, poses=2000, sweep=True)
    tr, te = rig.split("poses")
    M = rig.stated_loads[rig.pose]
    Z = rig.Z[tr].copy()
    kn = choose_known_poses(M[tr] / np.linalg.norm(M[tr], axis=1, keepdims=True), 4)
    rng = np.random.default_rng(36_001)
    rows = rng.choice(np.setdiff1d(np.arange(len(Z)), kn), size=len(Z) // 100, replace=False)
    Z[rows] += 20 * np.sqrt(np.diag(rig.noise_cov)) * rng.choice([-1, 1], size=(len(rows), 8))
    assert find_poses(rig.Z[tr]) is None and find_poses(Z) is None
    cal, said = _fit(Z, M[tr], kn)
    assert sorted(cal.diagnostics["joint"]["outlying_readings"]["rows"]) == sorted(rows)
    assert any("far from the fitted model" in s for s in said)
    rob, _ = _fit(Z, M[tr], kn, robust=True)
    assert sorted(rob.diagnostics["joint"]["outlier_rows_rejected"]) == sorted(rows)
    ls = fit_least_squares(Z, M[tr], bias=True)
    assert rms(rob.apply(rig.Z[te]) - M[te]) < rms(ls.apply(rig.Z[te]) - M[te])


def test_where_readings_are_flagged_the_error_has_no_stated_upper_end(tmp_path, capsys):
    """The predicted error counts noise, not spikes: where unknown readings are flagged its upper
    end is withdrawn (the interval held 1 of 4 spiked sweeps) and the lower end kept, and
    ``calib fit`` says why; with ``--robust`` the interval is stated again."""
    (Z, Mt, kn, Zte, Mte, row), cal, _ = _spiked(33_020, "unknown")
    pe = cal.diagnostics["joint"]["predicted_error"]
    assert pe["upper_bounded"] is False and pe["interval"][1] == np.inf
    assert pe["no_upper_end_because"] == "readings far from the model"
    assert rms(cal.apply(Zte) - Mte) >= pe["interval"][0]
    argv = _fit_argv(tmp_path, Z, Mt, kn)
    assert main(argv) == 0
    out, err = capsys.readouterr()
    assert f"row(s) {row}, counted from 0" in err
    assert "no upper end: some readings lie far from the fitted model" in out
    assert out.rstrip().endswith("reliable as far as the readings named in the warning are "
                                 "noise: its error has no stated upper end (--robust leaves "
                                 "them out)")
    assert main(argv + ["--robust"]) == 0
    out = capsys.readouterr().out
    assert "no upper end" not in out and out.rstrip().endswith("; reliable")
    pe = json.loads((tmp_path / "cal.json").read_text())["diagnostics"]["joint"]["predicted_error"]
    assert pe["upper_bounded"] is True


def test_a_flagged_known_reading_with_no_known_load_to_spare_refuses(tmp_path):
    """3 known loads, one of them spiked: it cannot be left out (the fit needs 3), so there is
    nothing to weigh it against: refused, with robust or not, and no endless refitting."""
    (Z, Mt, kn4, *_), cal4, _ = _spiked(33_010, "known")
    k = int(cal4.diagnostics["joint"]["outlying_readings"]["known"][0])
    kn = np.r_[kn4[k], np.delete(kn4, k)[:2]]  # the spiked one and two others
    for robust in (False, True):
        cal, said = _fit(Z, Mt, kn, robust=robust)
        o = cal.diagnostics["joint"]["outlying_readings"]
        assert list(o["known"]) == [0] and o["known_influence"] is None, robust
        assert any("lies far from the fitted model" in r for r in assess(cal, Z[kn], Mt[kn]))
