"""The verdict on a fit: serial correlation of its noise along the log, its predicted held-out
error with an interval, the bootstrap, and the reliability checks that refuse a fit (exit 3).

Imports :mod:`calib.data` and :mod:`calib.estimators`.
"""
