"""Data in and out: the Calibration type and its errors, input checks, CSV and CAL.json files,
streamed sources of rows, and channels that copy or combine others.

The lowest layer of calib: it imports nothing else of the package.
"""
