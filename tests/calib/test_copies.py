"""calib.data.copies: which channels are exact affine copies of another (left out of the fits)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from calib.data.copies import (
    COMBINATION_MIN_DOF,
    COMBINATION_ROWS,
    COPY_TOLERANCE,
    find_combinations,
    find_copies,
    fit_without_copies,
)
from calib.simulation.simulate import simulate_payload_rig, simulate_rig


@settings(max_examples=200, deadline=None)
@given(Z=arrays(np.float64, st.tuples(st.integers(0, 12), st.integers(0, 6)),
                elements=st.floats(allow_nan=True, allow_infinity=True)))
def test_any_array_gives_a_clean_answer(Z):
    """Whatever the values (NaN, infinities, 1e308), no exception and only valid pairs."""
    for d, c, b, s in find_copies(Z):
        assert 0 <= c < d < Z.shape[1] and np.isfinite(b) and b != 0 and np.isfinite(s)


def test_copies_are_found_and_distinct_channels_are_not():
    """A copy in other units and with an offset is found, its original the earlier channel;
    the closest distinct channels of wrench sensors (a torque follows a force closely) leave
    more than 1e6 times the tolerance of their variance and are not."""
    rig = simulate_payload_rig(10_003, poses=80, wrench=True)
    Z = rig.Z
    assert find_copies(Z) == []
    Zc = Z - Z.mean(axis=0)
    closest = min(
        np.sum((Zc[:, d] - (Zc[:, c] @ Zc[:, d]) / (Zc[:, c] @ Zc[:, c]) * Zc[:, c]) ** 2)
        / np.sum(Zc[:, d] ** 2) for d in range(6) for c in range(6) if c != d)
    assert closest > 1e6 * COPY_TOLERANCE
    Z2 = np.column_stack([Z[:, :3], -250.0 * Z[:, 1] + 7.0, Z[:, 3:], Z[:, 1]])
    found = find_copies(Z2)
    assert [(d, c) for d, c, _, _ in found] == [(3, 1), (7, 1)]
    assert found[0][2] == pytest.approx(-250.0) and found[0][3] == pytest.approx(7.0)



@settings(max_examples=200, deadline=None)
@given(Z=arrays(np.float64, st.tuples(st.integers(0, 40), st.integers(0, 7)),
                elements=st.floats(allow_nan=True, allow_infinity=True)))
def test_any_array_gives_a_clean_combination_answer(Z):
    """Whatever the values, find_combinations raises nothing and names only earlier, kept
    channels with finite coefficients."""
    found = find_combinations(Z)
    dropped = set()
    for d, cs, bs, s in found:
        assert all(0 <= c < d for c in cs) and not dropped & set(cs) or len(cs) == 1
        assert np.all(np.isfinite(bs)) and np.isfinite(s)
        dropped.add(d)


def _payload(**kw):
    return simulate_payload_rig(10_004, **({"poses": 80} | kw)).Z


@pytest.mark.parametrize("kw", [{}, {"wrench": True}, {"wrench": True, "gauges": 8},
                                {"p": 12, "noise": (0.01, 0.05)}, {"sweep": True, "poses": 400}])
def test_distinct_channels_are_no_combination(kw):
    """Once the earlier channels read the whole load, a distinct channel leaves its noise: at
    least 9.4e-6 of its variance over these cases (10 rigs each), 1e7 times the tolerance."""
    assert find_combinations(_payload(**kw)) == []
    assert find_combinations(simulate_rig(3).Z) == []


def test_combinations_are_found_in_any_units():
    """A sum channel of 2 or 3 earlier channels, in other units and with an offset, is found
    and named by the channels it combines; a copy is found as before; the same combination
    with noise of one part in 1e5 of its spread (a precise sensor's own channel) is not."""
    Z = _payload()
    rng = np.random.default_rng(1)
    sd = Z.std(axis=0)
    for cs in ((1, 4), (0, 2, 7)):
        b = rng.normal(size=len(cs)) * 1e3 / sd[list(cs)]
        Z2 = np.column_stack([Z, Z[:, list(cs)] @ b + 12.5])
        found = find_combinations(Z2)
        assert len(found) == 1 and found[0][0] == 8
        d, kept, coef, shift = found[0]
        assert kept == tuple(range(8))
        coef = np.array(coef)
        assert coef[list(cs)] == pytest.approx(b, rel=1e-6)
        assert np.all(np.abs(np.delete(coef, list(cs))) * np.delete(sd, list(cs))
                      < 1e-6 * np.abs(coef[list(cs)] * sd[list(cs)]).max())
        assert shift == pytest.approx(12.5, abs=1e-6 * np.abs(Z2[:, 8]).max())
        noisy = Z2.copy()
        noisy[:, 8] += rng.normal(size=len(Z)) * 1e-5 * np.ptp(Z2[:, 8])
        assert find_combinations(noisy) == []
    Z3 = np.column_stack([Z, 3 * Z[:, 5] - 1.0])
    assert [(d, cs) for d, cs, _, _ in find_combinations(Z3)] == [(8, (5,))]


def test_a_noise_free_log_is_fitted_as_it_is():
    """Noise-free readings of a 3-D load: every channel after the first three is their exact
    combination, which would leave fewer than dof + 1 channels: nothing is left out."""
    rng = np.random.default_rng(0)
    M = rng.normal(size=(60, 3))
    Z = M @ rng.normal(size=(3, 8)) + rng.normal(size=8)
    assert [d for d, _, _, _ in find_combinations(Z)] == [3, 4, 5, 6, 7]
    assert fit_without_copies(Z, None, lambda *a: pytest.fail("fitted"), 3) is None


def test_too_few_rows_for_the_regression_find_no_combination():
    """With fewer than COMBINATION_MIN_DOF rows beyond its parameters any channel is a
    combination of the others: not tested there."""
    rng = np.random.default_rng(2)
    Z = rng.normal(size=(8 + COMBINATION_MIN_DOF, 8))
    assert find_combinations(Z) == []


def test_a_long_log_is_searched_on_strided_rows_and_confirmed_on_all():
    """Beyond COMBINATION_ROWS rows the search strides them; what it finds there holds on
    every row or is not a combination."""
    rng = np.random.default_rng(4)
    n = 3 * COMBINATION_ROWS + 7
    M = rng.normal(size=(n, 3))
    Z = M @ rng.normal(size=(3, 6)) + 0.01 * rng.normal(size=(n, 6))
    Z7 = np.column_stack([Z, Z[:, 0] - 4 * Z[:, 3] + 1.0])
    assert [(d, cs) for d, cs, _, _ in find_combinations(Z7)] == [(6, tuple(range(6)))]
    off = Z7.copy()
    off[1::3, 6] += 0.01 * rng.normal(size=len(off[1::3]))  # rows the search does not see
    assert find_combinations(off) == []


def _copies_pair_by_pair(Z):
    """The copy search without its screen: every pair tested exactly, in order (the reference
    the screened search must agree with)."""
    from calib.data.copies import _holds, _search

    search = _search(np.asarray(Z, float))
    if search is None:
        return []
    fin, mu, Sc, ss, full = search
    found, copied = [], set()
    for d in range(Sc.shape[1]):
        if not ss[d] > 0:
            continue
        for c in range(d):
            if c in copied or not ss[c] > 0:
                continue
            with np.errstate(all="ignore"):
                b = float(Sc[:, c] @ Sc[:, d]) / float(ss[c])
                left = Sc[:, d] - b * Sc[:, c]
                rest = float(left @ left)
            if (np.isfinite(b) and b != 0 and rest <= COPY_TOLERANCE * float(ss[d])
                    and (full or _holds(Z, fin, d, (c,), (b,), COPY_TOLERANCE))):
                found.append((d, c, b, float(mu[d] - b * mu[c])))
                copied.add(d)
                break
    return found


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000), p=st.integers(2, 40), n=st.integers(3, 60),
       copies=st.integers(0, 6), log_scale=st.floats(-150, 150), near=st.booleans())
def test_the_screened_copy_search_finds_what_every_pair_finds(seed, p, n, copies, log_scale,
                                                              near):
    """Copies planted anywhere, in any units (scales 1e-150..1e150), some copies of copies, some
    only nearly copies (a perturbation of 1e-6 or 1e-4 of the spread, either side of the
    tolerance, both inside the screen): the screened search returns exactly what the exact test
    of every pair returns."""
    rng = np.random.default_rng(seed)
    Z = rng.normal(size=(n, p)) * 10.0 ** rng.uniform(-3, 3, p) * 10.0 ** log_scale
    for _ in range(copies):
        d, c = sorted(rng.choice(p, 2, replace=False))[::-1] if p > 1 else (0, 0)
        Z[:, d] = rng.uniform(-5, 5) * Z[:, c] + rng.normal() * 10.0 ** log_scale
        if near:
            Z[:, d] += rng.choice([1e-6, 1e-4]) * rng.normal(size=n) * Z[:, c].std()
    assert find_copies(Z) == _copies_pair_by_pair(Z)


def test_a_log_with_fewer_rows_than_channels_is_refused_before_any_copy_search(monkeypatch):
    """20 readings of 1,000 channels (a transposed log): the fit's one-line shape refusal, and
    the copy search (which costs p^2 pairs) never runs."""
    import calib.data.copies as copies
    from calib import CalibrationError, fit_bias, fit_joint

    def searched(*a, **k):
        raise AssertionError("the copy search ran on a log with fewer rows than channels")

    monkeypatch.setattr(copies, "find_combinations", searched)
    Z = np.random.default_rng(0).normal(size=(20, 1_000))
    for fit in (lambda: fit_bias(Z, 3), lambda: fit_joint(Z, Z[:4], np.eye(3)[[0, 1, 2, 0]], 3)):
        with pytest.raises(CalibrationError, match="at least as many samples as channels"):
            fit()
