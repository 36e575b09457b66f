"""Build the optional C kernel of mkv_env (everything else is in pyproject.toml).

``mkv_env._fastsim`` runs the MK-V's wheel/motor substep loop and the whole step kernel in C;
without a compiler the build skips it (``optional=True``) and mkv_env uses the pure-Python
reference, which gives the same bits. When numpy is importable at build time (it is a build
requirement in pyproject.toml) the kernel links numpy's random library (``libnpyrandom``) and
draws the sensor noise itself, on the worker threads, and makes a vector env's result arrays
with numpy's array API (``Batch.collect``); mkv_env checks at import that those draws
are ``Generator.standard_normal``'s (``mkv_env.kernel.NOISE_IN_C``) and otherwise draws in Python.
"""

import glob
import os

from setuptools import Extension, setup

# _fastsim.c is a unity build: it #includes every file of mkv_env/_native (one translation unit)
_NATIVE = sorted(glob.glob(os.path.join("mkv_env", "_native", "*.[ch]")))


def _npyrandom() -> dict:
    """Compiler/linker settings for numpy's random C library, or {} when numpy is not there."""
    try:
        import numpy as np
    except ImportError:
        return {}
    lib = os.path.join(os.path.dirname(np.__file__), "random", "lib")
    header = os.path.join(np.get_include(), "numpy", "random", "distributions.h")
    if not (os.path.isdir(lib) and os.path.isfile(header)):
        return {}
    return {"include_dirs": [np.get_include()], "library_dirs": [lib],
            "libraries": ["npyrandom"],
            "define_macros": [("MKV_NPYRANDOM", "1"), ("MKV_NUMPY", "1")]}


setup(
    ext_modules=[
        Extension(
            "mkv_env._fastsim",
            ["mkv_env/_fastsim.c"],
            depends=_NATIVE,
            # same bits as the Python loop: no FMA contraction, no sin/cos -> sincos merging
            extra_compile_args=["-O2", "-ffp-contract=off", "-fno-builtin-sin",
                                "-fno-builtin-cos", "-fno-fast-math"],
            optional=True,
            **_npyrandom(),
        )
    ]
)
