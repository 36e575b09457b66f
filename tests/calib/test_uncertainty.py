"""The isotropy prior only where the data support it; standard errors,
bootstrap intervals and the 'offset not identified' warning (both routes and p = r)."""

import json
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calib.cli import main
from calib.data.result import OFFSET_STDERR_MAX_FRACTION, CalibrationWarning
from calib.estimators.bias import fit_bias, fit_centered
from calib.simulation.simulate import paper_trial, random_shape, simulate


def quiet(fn, *a, **k):
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always", CalibrationWarning)
        out = fn(*a, **k)
    return out, [str(x.message) for x in w if issubclass(x.category, CalibrationWarning)]


def rel_err(cal, d):
    """Offset error as a fraction of span: mean over channels of |error_j| / (max_j - min_j)."""
    span = d.Z.max(axis=0) - d.Z.min(axis=0)
    return float(np.mean(np.abs(cal.offset - d.offset) / span))


def anisotropic(seed, cap=60):
    """The issue's study sensor (random 3 x 8 shape, SV ratio 5-10), 176 samples in a cap."""
    rng = np.random.default_rng(seed)
    S = random_shape(3, 8, rng, condition=rng.uniform(5, 10))
    z0 = rng.normal(size=8) * 20
    return simulate(S, 176, rng, magnitude=10, cap_half_angle_deg=cap, noise=0.2, offset=z0)


def test_auto_prior_never_worse_than_no_prior_on_anisotropic_sensors():
    auto, none, fixed = [], [], []
    for seed in range(20):
        d = anisotropic(seed)
        a, _ = quiet(fit_centered, d.Z, 3)
        b, _ = quiet(fit_centered, d.Z, 3, isotropy_prior=None)
        c, _ = quiet(fit_centered, d.Z, 3, isotropy_prior=0.1)
        auto.append(rel_err(a, d))
        none.append(rel_err(b, d))
        fixed.append(rel_err(c, d))
    auto, none = np.array(auto), np.array(none)
    # the held-out criterion drops the prior on these sensors: same fits as without it
    assert np.mean(auto > none * (1 + 1e-6)) <= 0.1
    assert np.median(auto) <= np.median(none) * (1 + 1e-6)
    assert np.median(fixed) > 2 * np.median(auto)  # what the always-on prior did


def p_equals_r(seed, cap=None):
    """A magnetometer-like p = r = 3 sensor: Gaussian 3 x 3 shape (often nearly flat)."""
    rng = np.random.default_rng(seed)
    S = rng.normal(size=(3, 3))
    return simulate(S, 176, rng, magnitude=1.0, cap_half_angle_deg=cap, noise=0.01,
                    noise_kind="gaussian", offset=rng.normal(size=3))


# seeds of scripts/calib_study.py's p = r case where the isotropy prior fails (>100% of span)
FLAT_SEEDS = (3, 87, 110, 117)


@pytest.mark.parametrize("seed", FLAT_SEEDS)
def test_auto_prior_drops_the_prior_when_the_data_contradict_it(seed):
    d = p_equals_r(seed)
    auto, _ = quiet(fit_centered, d.Z, 3)
    none, _ = quiet(fit_centered, d.Z, 3, isotropy_prior=None)
    fixed, _ = quiet(fit_centered, d.Z, 3, isotropy_prior=0.1)
    sel = auto.diagnostics["ellipsoid"]["prior_selection"]
    assert sel["criterion"] == "prior-data conflict" and not sel["prior_used"]
    assert sel["anisotropy"] > 3 * 0.1 * np.sqrt(6)
    assert sel["anisotropy_stderr"] < sel["anisotropy"] / 3
    assert rel_err(auto, d) == rel_err(none, d) < 0.05
    assert rel_err(fixed, d) > 1.0  # what the prior does to these sensors


def test_auto_prior_never_worse_than_no_prior_for_p_equals_r():
    for seed in range(60):
        for cap in (None, 90):
            d = p_equals_r(seed, cap)
            auto, _ = quiet(fit_centered, d.Z, 3)
            none, _ = quiet(fit_centered, d.Z, 3, isotropy_prior=None)
            assert rel_err(auto, d) <= rel_err(none, d) * 1.05 + 1e-9, (seed, cap)


def test_auto_prior_kept_for_the_near_isotropic_paper_sensor_under_partial_coverage():
    used, errs = [], []
    for seed in range(12):
        d = paper_trial(3, rng=seed, cap_half_angle_deg=60)
        # the isotropy prior is a statement about the raw channels (the paper's sensor is near
        # isotropic in its own units): the route on the raw readings, as in the paper's trials
        cal, _ = quiet(fit_bias, d.Z, 3, whiten=False)
        sel = cal.diagnostics["ellipsoid"]["prior_selection"]
        used.append(sel["prior_used"])
        errs.append(np.mean(np.abs(cal.offset - d.offset)))
    assert np.mean(used) >= 0.75
    assert max(errs) < 75


def test_prior_choice_is_recorded_and_explicit_values_still_work():
    d = anisotropic(0, cap=None)
    cal, _ = quiet(fit_centered, d.Z, 3)
    sel = cal.diagnostics["ellipsoid"]["prior_selection"]
    # a fully covered anisotropic sensor: its shape contradicts the prior outright
    assert sel["criterion"] == "prior-data conflict" and not sel["prior_used"]
    assert {"anisotropy", "anisotropy_stderr"} <= set(sel)
    near, _ = quiet(fit_bias, paper_trial(3, rng=0, cap_half_angle_deg=60).Z, 3)
    sel = near.diagnostics["ellipsoid"]["prior_selection"]  # no conflict: cross-validated
    assert sel["criterion"].startswith("5-fold")
    assert {"cost_with_prior", "cost_without_prior", "prior_used", "anisotropy"} <= set(sel)
    full, _ = quiet(fit_bias, paper_trial(3, rng=0, n=20_000).Z, 3)
    sel = full.diagnostics["ellipsoid"]["prior_selection"]  # full sphere, many rows
    assert sel["criterion"] == "data dominate the prior" and not sel["prior_used"]
    assert sel["anisotropy_stderr"] < 0.1 * 0.1
    fixed, _ = quiet(fit_centered, d.Z, 3, isotropy_prior=0.1)
    assert "prior_selection" not in fixed.diagnostics["ellipsoid"]
    assert fixed.diagnostics["ellipsoid"]["isotropy_prior"] == 0.1


@pytest.mark.parametrize("method", ["centered", "paper"])
def test_standard_errors_match_the_spread_of_the_errors(method):
    # full sphere: (error / stderr) over seeds and channels has rms near 1
    z, zc = [], []
    for seed in range(30):
        rng = np.random.default_rng(seed)
        S = random_shape(3, 8, rng, condition=rng.uniform(1, 10))
        z0 = rng.normal(size=8) * 20
        d = simulate(S, 300, rng, magnitude=10, noise=0.2, offset=z0, noise_kind="gaussian")
        cal, w = quiet(fit_bias, d.Z, 3, method=method, magnitude=10)
        dg = cal.diagnostics
        assert dg["offset_stderr"].shape == (8,) and dg["C_stderr"].shape == (3, 8)
        assert dg["offset_identified"] and not w
        z.append((cal.offset - z0) / dg["offset_stderr"])
        # C is in a canonical frame: compare the magnitude error of its rows' norms
        zc.append(np.all(np.isfinite(dg["C_stderr"])) and np.all(dg["C_stderr"] > 0))
    rms = float(np.sqrt(np.mean(np.square(z))))
    assert 0.75 < rms < 1.35, rms
    assert all(zc)


def test_c_stderr_matches_c_spread_in_a_fixed_frame():
    # with the frame fixed by exact known pairs, C's scatter over seeds vs its standard error
    rng0 = np.random.default_rng(99)
    S = random_shape(3, 6, rng0, condition=3)
    z0 = rng0.normal(size=6) * 5
    Mk = np.eye(3) * 10
    Cs, ses = [], []
    for seed in range(40):
        rng = np.random.default_rng(seed)
        d = simulate(S, 400, rng, magnitude=10, noise=0.05, offset=z0, noise_kind="gaussian")
        cal, _ = quiet(fit_bias, d.Z, 3, known_Z=Mk @ S + z0, known_M=Mk)
        Cs.append(cal.C)
        ses.append(cal.diagnostics["C_stderr"])
    ratio = np.std(Cs, axis=0) / np.median(ses, axis=0)
    # the alignment's own error is not in C_stderr, so only a loose check of the scale
    assert 0.5 < float(np.median(ratio)) < 2.5, np.median(ratio)


def test_p_equals_r_gross_failures_all_warn():
    # magnetometer-like: p = r = 3, Gaussian random shapes (some with condition numbers of
    # hundreds), full sphere and 90 degree cap; the fits whose offset error exceeds 20 % of span
    # must all warn
    gross = silent_over_5 = 0
    for seed, cap in [(s, c) for s in range(60) for c in (None, 90)]:
        rng = np.random.default_rng(seed)
        S = rng.normal(size=(3, 3))
        z0 = rng.normal(size=3)
        d = simulate(S, 176, rng, magnitude=1, noise=0.01, offset=z0, noise_kind="gaussian",
                     cap_half_angle_deg=cap)
        cal, w = quiet(fit_bias, d.Z, 3)
        err = np.max(np.abs(cal.offset - z0) / cal.diagnostics["span"])
        if err > 0.2:
            gross += 1
            assert w, (seed, err)
            assert not cal.diagnostics["offset_identified"]
        if not w:
            silent_over_5 += err > 0.05
    assert gross >= 2  # the case is exercised
    # known limit: a first-order standard error cannot see the bias of a few nearly flat
    # ellipsoids seen over a hemisphere (seed 37 at 90 degrees: 15% of span, stderr 2%)
    assert silent_over_5 <= 2


@pytest.mark.parametrize("method", ["centered", "paper"])
def test_90_degree_cap_always_warns(method):
    for seed in range(20):
        d = paper_trial(2, rng=seed, cap_half_angle_deg=90)
        _, w = quiet(fit_bias, d.Z, 3, method=method)
        assert w, seed


def test_offset_not_identified_warning_names_the_fraction():
    d = anisotropic(3, cap=30)
    cal, w = quiet(fit_bias, d.Z, 3, method="paper")
    assert cal.diagnostics["offset_stderr_max_rel_span"] > OFFSET_STDERR_MAX_FRACTION
    assert any("offset is not identified" in m and "5%" in m for m in w)


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 10_000), st.sampled_from(["centered", "paper"]), st.floats(0.01, 100))
def test_standard_errors_scale_with_units(seed, method, k):
    rng = np.random.default_rng(seed)
    S = random_shape(3, 6, rng)
    d = simulate(S, 150, rng, magnitude=4.0, offset=rng.normal(size=6) * 3, noise=0.05,
                 noise_kind="gaussian")
    a, _ = quiet(fit_bias, d.Z, 3, method=method)
    b, _ = quiet(fit_bias, k * d.Z, 3, method=method)
    assert np.allclose(b.diagnostics["offset_stderr"], k * a.diagnostics["offset_stderr"],
                       rtol=1e-4)
    assert np.allclose(b.diagnostics["offset_stderr_rel_span"],
                       a.diagnostics["offset_stderr_rel_span"], rtol=1e-4)


def test_cli_writes_stderrs_and_seeded_bootstrap(tmp_path):
    d = paper_trial(2, rng=0)
    raw = tmp_path / "raw.csv"
    raw.write_text("\n".join([",".join(f"c{j}" for j in range(8))]
                             + [",".join(repr(float(x)) for x in row) for row in d.Z]) + "\n")
    outs = []
    for name in ("a.json", "b.json"):
        out = tmp_path / name
        assert main(["fit", str(raw), "--dof", "3", "--bias", "--bootstrap", "20", "--seed",
                     "7", "--quiet", "--out", str(out)]) == 0
        outs.append(json.loads(out.read_text()))
    a, b = outs
    assert a["diagnostics"]["bootstrap"] == b["diagnostics"]["bootstrap"]  # seeded
    bs = a["diagnostics"]["bootstrap"]
    assert bs["n_boot"] == 20 and bs["seed"] == 7
    lo, hi = np.array(bs["offset_low"]), np.array(bs["offset_high"])
    off = np.array(a["offset"])
    assert np.all(lo <= off) and np.all(off <= hi)
    assert np.all(hi - lo < 2.0)  # Trial 2 noise: offsets known to about 0.1 count
    assert np.array(bs["C_low"]).shape == (3, 8)
    assert len(a["diagnostics"]["offset_stderr"]) == 8
    assert np.array(a["diagnostics"]["C_stderr"]).shape == (3, 8)


def test_cli_bootstrap_bad_count_is_one_line(tmp_path, capsys):
    d = paper_trial(2, rng=0)
    raw = tmp_path / "raw.csv"
    raw.write_text("a,b,c,d,e,f,g,h\n" + "\n".join(",".join(map(str, r)) for r in d.Z) + "\n")
    assert main(["fit", str(raw), "--dof", "3", "--bias", "--bootstrap", "1", "--out",
                 str(tmp_path / "o.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "calib: error" in err


def test_whitening_term_of_a_rank_deficient_c_is_infinite_not_an_error():
    # the study met a degenerate centered fit whose C had lower rank than its rows: the weights'
    # term of C_stderr cannot be formed there; it is infinite, and fit_bias does not crash
    from calib.data.result import Calibration
    from calib.estimators.bias import _unwhiten

    C = np.zeros((3, 8))
    C[0, 0] = C[1, 1] = 1.0  # rank 2 of 3 rows
    cal = Calibration(C=C, offset=np.zeros(8), dof=3, method="centered",
                      diagnostics={"C_stderr": np.ones((3, 8)), "offset_stderr": np.ones(8)})
    out = _unwhiten(cal, np.ones(8), "factor analysis", np.eye(8) * 0.01)
    assert np.all(np.isinf(out.diagnostics["C_stderr"]))
    square = Calibration(C=np.eye(3), offset=np.zeros(3), dof=3, method="centered",
                         diagnostics={"C_stderr": np.ones((3, 3))})
    assert np.allclose(_unwhiten(square, np.ones(3), "channel spread",
                                 np.eye(3) * 0.01).diagnostics["C_stderr"], 1.0)
