"""calib: force/torque sensor calibration by least squares and shape from motion (with sensor bias).

Independent of the robot side: depends only on numpy and scipy (matplotlib only in
calib.simulation.plots).

Main entry points (all return a :class:`Calibration`, ``m = C (z - offset)``):

- :func:`fit_least_squares` - known loads, paper eqs. 2-3 (optionally with a bias column)
- :func:`fit_sfm` - shape from motion without bias, eqs. 7-14
- :func:`fit_bias` - shape from motion with bias, ``method="centered"`` or ``"paper"``
- :func:`fit_joint` - magnitude rows and known pairs in one weighted fit (static-pose rigs)
- :func:`fit_ft6` - 6-DOF force/torque from proof-mass rotation data plus >= 6 known loads
- :mod:`calib.simulation.simulate` - the sensor simulator and the paper's section 8 set-up
"""

from calib.data.result import Calibration, CalibrationError, CalibrationWarning
from calib.estimators.bias import fit_bias, fit_centered, fit_paper
from calib.estimators.ft6 import fit_ft6
from calib.estimators.least_squares import fit_least_squares
from calib.estimators.sfm import fit_sfm
from calib.routes.joint import choose_known_poses, fit_joint

__version__ = "0.1.0"

__all__ = [
    "Calibration",
    "CalibrationError",
    "CalibrationWarning",
    "fit_bias",
    "fit_centered",
    "fit_paper",
    "fit_ft6",
    "choose_known_poses",
    "fit_joint",
    "fit_least_squares",
    "fit_sfm",
]
