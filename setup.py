"""Build the optional C kernel of mkv_env (everything else is in pyproject.toml).

``mkv_env._fastsim`` runs the MK-V's wheel/motor substep loop in C; without a compiler the build
skips it (``optional=True``) and mkv_env uses the pure-Python loop, which gives the same bits.
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "mkv_env._fastsim",
            ["mkv_env/_fastsim.c"],
            # same bits as the Python loop: no FMA contraction, no sin/cos -> sincos merging
            extra_compile_args=["-O2", "-ffp-contract=off", "-fno-builtin-sin",
                                "-fno-builtin-cos", "-fno-fast-math"],
            optional=True,
        )
    ]
)
