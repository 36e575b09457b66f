"""Build the optional C kernel of mkv_env (everything else is in pyproject.toml).

``mkv_env._fastsim`` runs the MK-V's wheel/motor substep loop and the whole step kernel in C;
without a compiler the build skips it (``optional=True``) and mkv_env uses the pure-Python
reference, which gives the same bits. The kernel links numpy's random library (``libnpyrandom``,
numpy is a build requirement in pyproject.toml) and draws the sensor noise itself, on the worker
threads, and makes a vector env's result arrays with numpy's array API (``Batch.collect``); where
numpy's library or headers are missing, the extension is not built at all (two paths only: the
whole kernel or the reference). mkv_env checks at import that the kernel's draws are
``Generator.standard_normal``'s (``mkv_env.kernel._noise_in_c``) and turns it off if not.
"""

import glob
import os

from setuptools import Extension, setup

# _fastsim.c is a unity build: it #includes every file of mkv_env/_native (one translation unit)
_NATIVE = sorted(glob.glob(os.path.join("mkv_env", "_native", "*.[ch]")))


def _npyrandom() -> dict | None:
    """Compiler/linker settings for numpy's array API and random C library, or None when they
    are not there: then no extension is built and the envs run the Python reference (one of the
    two paths; the kernel has no half-built variant)."""
    try:
        import numpy as np
    except ImportError:
        return None
    lib = os.path.join(os.path.dirname(np.__file__), "random", "lib")
    header = os.path.join(np.get_include(), "numpy", "random", "distributions.h")
    if not (os.path.isdir(lib) and os.path.isfile(header)):
        return None
    return {"include_dirs": [np.get_include()], "library_dirs": [lib],
            "libraries": ["npyrandom"]}


_NUMPY = _npyrandom()


setup(
    ext_modules=[] if _NUMPY is None else [
        Extension(
            "mkv_env._fastsim",
            ["mkv_env/_fastsim.c"],
            depends=_NATIVE,
            # same bits as the Python loop: no FMA contraction, no sin/cos -> sincos merging
            extra_compile_args=["-O2", "-ffp-contract=off", "-fno-builtin-sin",
                                "-fno-builtin-cos", "-fno-fast-math"],
            optional=True,
            **_NUMPY,
        )
    ]
)
