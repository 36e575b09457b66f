"""The ``mkv`` and ``calib`` console scripts' launchers.

A console script imports its ``main`` before calling it, and the command packages take a few
tenths of a second to import (numpy, scipy, gymnasium): a Ctrl-C in that window used to end in
a ``KeyboardInterrupt`` traceback from inside scipy's import. These launchers import the command
package while a Ctrl-C is already answered the commands' way (one line, exit 130, nothing
written: nothing has started), including one that an extension module's initialisation turns into
``ImportError("initialization failed")`` (scipy's pybind11 modules do, e.g. in ``mkv demo``).
They live outside the packages because importing any module of ``calib`` or ``sfm_learn`` runs
that package's heavy ``__init__`` first; they import only the standard library and
``sfm_common.cli`` (itself the standard library only).
"""

from __future__ import annotations

import importlib
import sys

from sfm_common.cli import caused_by_interrupt  # the standard library only: ~4 ms

EXIT_INTERRUPTED = 130


def _launch(module: str, prog: str) -> int:
    try:
        main = importlib.import_module(module).main
    except Exception as e:  # a Ctrl-C inside an extension module's initialisation
        if not caused_by_interrupt(e):  # arrives as ImportError("initialization failed") from it
            raise
        print(f"{prog}: interrupted; no output written", file=sys.stderr)
        return EXIT_INTERRUPTED
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; no output written", file=sys.stderr)
        return EXIT_INTERRUPTED
    return main()


def mkv() -> int:
    """The ``mkv`` command (:func:`sfm_learn.cli.main`)."""
    return _launch("sfm_learn.cli", "mkv")


def calib() -> int:
    """The ``calib`` command (:func:`calib.cli.main`)."""
    return _launch("calib.cli", "calib")
