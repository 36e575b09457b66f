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
