"""Low signal: shape from motion with bias at a shortest-axis signal-to-noise ratio of
20-50 over a 60 degree cap, 4 known pairs (scripts/calib_low_signal.py's generator, seeds it
does not use for its published table). The default route with known pairs (joint: the forward
maximum-likelihood fit) against the Cramer-Rao bound: its p95 offset error within 1.5x the
bound's, its stated standard errors covering the true errors at about their nominal rate, no fit
with a channel more than 20 % of span off accepted without a warning naming it, and warnings on
few fits (on 200 sensors: p95 0.87x the bound, coverage 94.8 %, 0 silent, 2 % warned)."""

import numpy as np
import pytest


@pytest.fixture(scope="module")
def sensors(load_script):
    """The script and its ``one`` of the 24 sensors (seeds 1000-1023) both tests below read,
    every route fitted once."""
    mod = load_script("calib_low_signal")
    return mod, [mod.one(seed) for seed in range(1000, 1024)]


def test_joint_reaches_the_bound_and_states_its_errors(sensors):
    _, res = sensors
    bound = np.concatenate([r["bound"] for r in res])
    fits = [r["joint"] for r in res if r["joint"] is not None]
    assert len(fits) == len(res)
    off = np.array([f["offset"] for f in fits])
    assert np.percentile(off, 95) < 1.5 * np.percentile(bound, 95)
    covered = np.concatenate([f["covered"] for f in fits])
    assert 0.88 <= covered.mean() <= 0.99, covered.mean()  # nominal 95 %
    assert not any(f["silent_bad"] for f in fits)
    assert np.mean([f["warned"] for f in fits]) <= 0.25


def test_the_table_reports_every_route(sensors):
    mod, res = sensors
    text = mod.table(res)
    for name in ("Cramer-Rao bound", "joint", "centered", "paper"):
        assert f"| {name} |" in text


def _paper_and_centered(mod, seed, cap):
    import warnings

    from calib.data.result import CalibrationError, CalibrationWarning
    from calib.estimators.bias import fit_bias
    from calib.verdict.reliability import assess

    S, z0, g, U, Z, sd = mod.make_sensor(seed, cap=cap)
    Zk, Mk = Z[:4], g * U[:4]
    out = {}
    for route in ("paper", "centered"):
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always", CalibrationWarning)
            try:
                cal = fit_bias(Z, 3, method=route, known_Z=Zk, known_M=Mk)
            except CalibrationError:
                continue
        se = np.asarray(cal.diagnostics["offset_stderr"], float)
        out[route] = {"poor": cal.diagnostics["excitation_poor"],
                      "problems": assess(cal, Zk, Mk),
                      "warnings": [str(x.message) for x in w],
                      "covered": np.abs(cal.offset - z0) <= 1.96 * se}
    return out


def test_the_paper_route_is_refused_where_its_errors_miss_the_poor_excitation(load_script):
    """Under poor excitation the paper route's standard errors leave out the error of the
    subspace its plane and cylinder are fitted in (they covered 49 % of the true offsets at a
    60 degree cap on 100 sensors, nominal 95 %): every such fit is refused, and its warning
    agrees. With the whole sphere no fit warns and the rule does not fire, and the stated
    errors cover the offsets at about their nominal rate (94 % on 100 sensors)."""
    mod = load_script("calib_low_signal")
    cap60 = [_paper_and_centered(mod, seed, 60.0) for seed in range(1200, 1212)]
    papers = [r["paper"] for r in cap60 if "paper" in r]
    assert len(papers) >= 10
    assert all(f["poor"] for f in papers)
    assert all(any("paper route's offset is not identified" in p for p in f["problems"])
               for f in papers)
    assert np.concatenate([f["covered"] for f in papers]).mean() < 0.8  # why: not nominal
    # the centered route's standard errors carry the cap: its warning does not call the
    # offset unreliable, and the verdict is left to the offset rule
    for r in cap60:
        if "centered" in r:
            warned = [m for m in r["centered"]["warnings"] if m.startswith("poor excitation")]
            assert warned and all("unreliable" not in m for m in warned)
            assert not any("paper route" in p for p in r["centered"]["problems"])
    sphere = [_paper_and_centered(mod, seed, 180.0)["paper"] for seed in range(1200, 1212)]
    assert not any(f["poor"] for f in sphere)
    assert not any("paper route" in p for f in sphere for p in f["problems"])
    assert np.concatenate([f["covered"] for f in sphere]).mean() >= 0.85
