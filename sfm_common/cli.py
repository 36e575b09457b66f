"""Command-line plumbing shared by ``mkv`` and ``calib``: argparse number types, a parser whose
errors are one line, and one-line error text.

Every ``type=`` function here turns a bad value into one line such as
``argument --episodes: expected a positive integer, got '-3'``.
"""

from __future__ import annotations

import _thread
import argparse
import contextlib
import math
import sys
import threading

__all__ = [
    "UsageError", "OneLineParser", "one_line", "positive_int", "non_negative_int", "seed",
    "positive_float", "non_negative_float", "fraction", "SEED_LIMIT", "int_in_range",
    "interrupts_not_lost",
]

#: Seeds are accepted in [0, SEED_LIMIT): numpy's SeedSequence takes any, but episode seeds
#: ``seed + i`` must stay within a signed 64-bit integer.
SEED_LIMIT = 2**62


@contextlib.contextmanager
def interrupts_not_lost(delay: float = 0.01):
    """A Ctrl-C whose ``KeyboardInterrupt`` is raised inside a finaliser (a cffi ``ffi.gc``
    callback such as pymunk's space free, a ``__del__``) is "ignored" there: Python prints a
    traceback and goes on, and the command would run to its end and exit 0. While this block
    runs, such an interrupt is delivered again to the main thread ``delay`` seconds later (a
    timer thread calls ``_thread.interrupt_main``: raised from the hook itself it would be
    ignored again), and its traceback is not printed; one still pending when the block ends is
    raised there. Other unraisable exceptions go to the previous hook."""
    previous = sys.unraisablehook
    timer = []

    def hook(unraisable):
        if unraisable.exc_type is not None and issubclass(unraisable.exc_type, KeyboardInterrupt):
            if not timer:
                t = threading.Timer(delay, lambda: (timer.clear(), _thread.interrupt_main()))
                t.daemon = True
                timer.append(t)
                t.start()
            return
        previous(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    except BaseException:
        for t in timer:
            t.cancel()
        raise
    else:
        if timer:
            timer[0].cancel()
            raise KeyboardInterrupt
    finally:
        sys.unraisablehook = previous


class UsageError(Exception):
    """A command-line mistake found by the parser; ``prog`` names the (sub)command."""

    def __init__(self, prog: str, message: str):
        super().__init__(message)
        self.prog = prog


class OneLineParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` that raises :class:`UsageError` with one line instead of printing
    the usage block and exiting."""

    def error(self, message):
        raise UsageError(self.prog, f"{message} (see {self.prog} --help)")


def caused_by_interrupt(e: BaseException) -> bool:
    """Whether a Ctrl-C lies under an exception: Python wraps a ``KeyboardInterrupt`` raised in
    some hooks (a descriptor's ``__set_name__`` while a class is created, e.g. during torch's
    lazy imports) in a ``RuntimeError`` whose cause it is."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


def one_line(e: BaseException) -> str:
    """The first line of an exception's text (its type name if it has none)."""
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


def _number(text: str, cast, ok, expected: str):
    try:
        v = cast(text)
    except (ValueError, OverflowError):
        v = None
    if v is None or not ok(v):
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    return v


def positive_int(text: str) -> int:
    return _number(text, int, lambda v: v >= 1, "a positive integer")


def non_negative_int(text: str) -> int:
    return _number(text, int, lambda v: v >= 0, "an integer >= 0")


def seed(text: str) -> int:
    return _number(text, int, lambda v: 0 <= v < SEED_LIMIT,
                   "a non-negative integer below 2**62")


def positive_float(text: str) -> float:
    return _number(text, float, lambda v: math.isfinite(v) and v > 0, "a positive number")


def non_negative_float(text: str) -> float:
    return _number(text, float, lambda v: math.isfinite(v) and v >= 0, "a number >= 0")


def fraction(text: str) -> float:
    return _number(text, float, lambda v: 0.0 <= v < 1.0, "a fraction in [0, 1)")


def int_in_range(low: int, high: int):
    """An argparse type accepting integers in ``[low, high]`` (inclusive), e.g. a stated maximum
    of episodes or timesteps, so a typo of extra zeros is an error, not a week of computing."""
    def parse(text: str) -> int:
        expected = (f"a positive integer (at most {high:_})" if low == 1
                    else f"an integer in [{low}, {high:_}]")
        return _number(text, int, lambda v: low <= v <= high, expected)

    parse.__name__ = f"int_in_[{low},{high}]"
    return parse
