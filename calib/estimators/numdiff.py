"""Forward-difference Jacobians evaluated as one batch.

The fits here have a dozen parameters and residual functions made of small numpy operations, so
scipy's finite differences (one Python call of the residual function per column) spend their
time in call overhead. :func:`batched_jacobian` takes a function of a *batch* of parameter
vectors and evaluates every column in one call, with scipy's own step (``"2-point"``: relative
step sqrt(eps), away from zero), so results match scipy's to rounding.
"""

from __future__ import annotations

import numpy as np

#: Decision: docs/calib_design.md D10.
_REL_STEP = np.finfo(float).eps ** 0.5


def batched_jacobian(batch):
    """A ``jac(x)`` for :func:`scipy.optimize.least_squares`: ``batch(xs)`` maps parameter rows
    (b, n) to residual rows (b, m); the Jacobian (m, n) is formed from one call on ``x`` and its
    n forward steps."""

    def jac(x):
        x = np.asarray(x, float)
        h = _REL_STEP * np.where(x >= 0, 1.0, -1.0) * np.maximum(1.0, np.abs(x))
        dx = (x + h) - x
        F = batch(np.vstack([x, x + np.diag(dx)]))
        return ((F[1:] - F[0]) / dx[:, None]).T

    return jac
