"""Worker processes that die with the process that started them.

A pool's workers (``ProcessPoolExecutor`` with the forkserver or spawn start method) are not
children of the main process, so a ``kill -9`` of it used to leave them running for minutes,
still writing results. :func:`die_with` makes a worker end within a second of the main process:
on Linux the kernel sends it SIGKILL when its own parent ends (``PR_SET_PDEATHSIG``), and on every
system a daemon thread checks every half second that the main process still exists.
"""

from __future__ import annotations

import contextlib
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
    """Call in a worker (e.g. as a pool initializer): end this process when ``main_pid`` ends.
    The worker also ignores SIGINT from then on: the main process handles Ctrl-C and stops it
    (see :func:`children_ignore_sigint` for the moments before this runs)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
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


@contextlib.contextmanager
def children_ignore_sigint(ctx=None):
    """Processes started inside this block never see SIGINT.

    Ctrl-C at a terminal signals the whole process group: a pool's workers, and the forkserver
    that forks them, would each print a ``KeyboardInterrupt`` traceback (a worker still importing
    its modules has no handler yet), and a Ctrl-C that lands while a worker is being started
    leaves it half-started (its traceback: ``FileNotFoundError`` rebuilding a semaphore the main
    process has already removed). Here, while the processes start:

    - a forkserver started here starts with SIGINT ignored (an ignored disposition survives
      exec), and every worker it forks inherits that; SIGINT is also blocked in this thread
      while processes start (a ``spawn`` child may or may not keep the mask: its worker
      initializer ignores SIGINT as its first step): only the main process sees Ctrl-C, and
      stops them (one line, exit 130);
    - a Ctrl-C delivered to another thread of this process is only recorded, and raised as
      ``KeyboardInterrupt`` when the block ends (no process is left half-started).

    With ``ctx`` a forkserver context, its server is started inside the block too (every process
    it forks inherits the mask). Main thread only (signal handlers live there); elsewhere, or
    without ``pthread_sigmask``, it does nothing.
    """
    if (not hasattr(signal, "pthread_sigmask")
            or threading.current_thread() is not threading.main_thread()):
        yield
        return
    caught = []
    previous = signal.getsignal(signal.SIGINT)
    # an ignored SIGINT (a background job) stays ignored; a handler set outside Python (None)
    # cannot be put back, so it is left alone (the mask still keeps it from the children)
    record = previous not in (signal.SIG_IGN, None)
    if record:
        signal.signal(signal.SIGINT, lambda *a: caught.append(a))
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        if ctx is not None and ctx.get_start_method() == "forkserver":
            from multiprocessing import forkserver

            # started with SIGINT ignored: an ignored disposition survives exec (a mask may
            # not: measured blocked in some runs, not in others), and the server hands it on to
            # every worker it forks; a Ctrl-C in these few milliseconds is lost, not raised
            if record:
                signal.signal(signal.SIGINT, signal.SIG_IGN)
            try:
                forkserver.ensure_running()
            finally:
                if record:
                    signal.signal(signal.SIGINT, lambda *a: caught.append(a))
        yield
    finally:
        if record:
            signal.signal(signal.SIGINT, previous)
        signal.pthread_sigmask(signal.SIG_SETMASK, old)  # a pending Ctrl-C is delivered here
    if caught:  # delivered to another thread meanwhile: the handler it would have met
        if callable(previous):
            previous(signal.SIGINT, None)  # default_int_handler raises KeyboardInterrupt
        else:
            raise KeyboardInterrupt  # SIG_DFL would have ended the process
