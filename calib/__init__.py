"""calib: force/torque sensor calibration by least squares and shape from motion (with sensor bias).

Independent of the robot side: depends only on numpy and scipy.
"""

__version__ = "0.1.0"
