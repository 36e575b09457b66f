"""The batched forward-difference Jacobian is scipy's "2-point" Jacobian (same steps)."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize._numdiff import approx_derivative

from calib.estimators.numdiff import batched_jacobian


def _fun_batch(xs, A):
    # a smooth nonlinear map R^n -> R^m, evaluated for every row of xs
    return np.tanh(xs @ A.T) + 0.1 * (xs**2) @ A.T


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 6), st.integers(1, 9))
def test_matches_scipy_two_point(seed, n, m):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(m, n))
    x = rng.normal(scale=3.0, size=n)
    x[rng.random(n) < 0.2] = 0.0  # steps away from zero, as scipy's
    J = batched_jacobian(lambda xs: _fun_batch(xs, A))(x)
    ref = approx_derivative(lambda v: _fun_batch(v[None], A)[0], x, method="2-point")
    assert J.shape == (m, n)
    # the same steps: equal up to the rounding of a batched evaluation (a few eps of |f|) over
    # the step (sqrt(eps) at least)
    eps = np.finfo(float).eps
    rounding = 16 * eps * (1 + np.abs(_fun_batch(x[None], A)).max()) / np.sqrt(eps)
    np.testing.assert_allclose(J, np.reshape(ref, (m, n)), rtol=0, atol=rounding)
    # and it is a derivative: close to the analytic one
    sech2 = 1 - np.tanh(A @ x) ** 2
    exact = sech2[:, None] * A + 0.2 * A * x[None, :]
    np.testing.assert_allclose(J, exact, rtol=1e-5, atol=1e-5 * max(1.0, np.abs(x).max()))
