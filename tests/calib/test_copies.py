"""calib.copies: which channels are exact affine copies of another (left out of the fits)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from calib.copies import COPY_TOLERANCE, find_copies
from calib.simulate import simulate_payload_rig


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

