"""Helpers every package of mkv-sfm shares (``mkv_env``, ``sfm_learn`` and ``calib``).

* :mod:`sfm_common.files`: atomic file writes (temporary file, fsync, usual permissions, rename);
* :mod:`sfm_common.progress`: progress bars (tqdm when installed; quiet when not a terminal);
* :mod:`sfm_common.cli`: argparse number types, the one-line-error parser and error formatting.

Only the standard library is imported here (tqdm lazily), so any package may depend on it.
"""
