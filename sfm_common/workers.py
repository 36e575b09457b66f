"""Worker processes that die with the process that started them.

A pool's workers (``ProcessPoolExecutor`` with the forkserver or spawn start method) are not
children of the main process, so a ``kill -9`` of it used to leave them running for minutes,
still writing results. :func:`die_with` makes a worker end within a second of the main process:
on Linux the kernel sends it SIGKILL when its own parent ends (``PR_SET_PDEATHSIG``), and on every
system a daemon thread checks every half second that the main process still exists.
"""

from __future__ import annotations

import os
import signal
import sys
import threading

POLL_S = 0.5


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else (a recycled pid): not ours
        return False
    return True


def die_with(main_pid: int) -> None:
    """Call in a worker (e.g. as a pool initializer): end this process when ``main_pid`` ends."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            PR_SET_PDEATHSIG = 1
            libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):  # pragma: no cover - no prctl: the thread still works
            pass
    parent = os.getppid()

    def watch():
        while True:
            if not _alive(main_pid) or os.getppid() != parent:
                os._exit(1)  # nobody will read our results: stop writing them
            threading.Event().wait(POLL_S)

    threading.Thread(target=watch, name="die-with-main", daemon=True).start()
