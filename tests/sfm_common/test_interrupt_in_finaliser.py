"""A Ctrl-C that lands inside a finaliser (pymunk frees its spaces in cffi ``ffi.gc`` callbacks)
must still stop the command: :func:`sfm_common.cli.interrupts_not_lost`."""

import contextlib
import signal
import sys
import threading

import pytest

from sfm_common.cli import interrupts_not_lost

main_thread_only = pytest.mark.skipif(
    threading.current_thread() is not threading.main_thread(),
    reason="signal handlers are set in the main thread only")


class _InterruptedFinaliser:
    """Its finaliser raises what a SIGINT arriving during it would raise."""

    def __del__(self):
        raise KeyboardInterrupt


@contextlib.contextmanager
def _recording_hook():
    """sys.unraisablehook replaced by one that records what reaches it."""
    seen, previous = [], sys.unraisablehook
    sys.unraisablehook = lambda u: seen.append(u.exc_type)
    try:
        yield seen
    finally:
        sys.unraisablehook = previous


def _run(wrap: bool) -> bool:
    """True when the interrupt raised inside the finaliser stopped the loop after it."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with interrupts_not_lost() if wrap else contextlib.nullcontext():
            _InterruptedFinaliser()  # freed at once: its KeyboardInterrupt is "ignored"
            for _ in range(20_000_000):  # the work that goes on after it (about 0.3 s)
                pass
        return False
    except KeyboardInterrupt:
        return True
    finally:
        signal.signal(signal.SIGINT, previous)


@main_thread_only
def test_an_interrupt_inside_a_finaliser_is_delivered_again_and_not_printed():
    with _recording_hook() as seen:
        assert _run(wrap=True)
    assert seen == []  # nothing went on to the hook that prints "Exception ignored"


@main_thread_only
def test_without_it_the_interrupt_is_lost():
    # what the commands did before: the finaliser's traceback is printed and the work goes on
    with _recording_hook() as seen:
        assert not _run(wrap=False)
    assert seen == [KeyboardInterrupt]


def test_other_unraisable_exceptions_still_reach_the_previous_hook():
    class Broken:
        def __del__(self):
            raise RuntimeError("a finaliser failed")

    with _recording_hook() as seen, interrupts_not_lost():
        Broken()
    assert seen == [RuntimeError]
