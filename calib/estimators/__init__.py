"""Models and estimators: least squares, shape from motion (with and without bias), the
ellipsoid fits, 6-DOF, the forward maximum-likelihood fit and the static-pose rig fit.

Imports only :mod:`calib.data`.
"""
