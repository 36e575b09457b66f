"""Progress bars for long work, on tqdm.

``with progress(total, "record", unit="ep") as bar: bar.update(1)``; ``bar.write(line)`` prints a
line above the bar. The bar goes to stderr and is drawn only when stderr is a terminal (so logs and
CI output get no ``\\r`` redraws), unless ``enabled`` says otherwise. tqdm is an optional
dependency (the ``progress`` extra, in ``all``); without it there is no bar, and ``write`` still
prints.
"""

from __future__ import annotations

import sys

__all__ = ["progress", "NullBar"]


class NullBar:
    """What :func:`progress` returns when no bar is drawn: counts, and prints ``write`` lines."""

    def __init__(self, total: int | None = None, stream=None):
        self.total = total
        self.n = 0
        self._stream = stream

    def update(self, n: int = 1) -> None:
        self.n += n

    def write(self, line: str) -> None:
        print(line, file=self._stream if self._stream is not None else sys.stdout, flush=True)

    def close(self) -> None:
        pass

    def __enter__(self) -> NullBar:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def progress(total: int | None, desc: str = "", *, unit: str = "it", enabled: bool | None = None,
             stream=None, unit_scale: bool = False):
    """A progress bar over ``total`` units (``None``: unknown total).

    Args:
        total: expected number of ``update`` units.
        desc: the label in front of the bar.
        unit: the unit's name in the rate (``"ep"``, ``"step"``, ``"epoch"``).
        enabled: ``True`` draws, ``False`` never draws, ``None`` (default) draws only when
            ``stream`` is a terminal.
        stream: where the bar goes (default ``sys.stderr``).
        unit_scale: show counts and rates with k/M/G prefixes (for bytes: ``unit="B"``).

    Returns:
        a ``tqdm`` bar, or a :class:`NullBar` when disabled or tqdm is not installed; both are
        context managers with ``update(n)``, ``write(line)`` and ``close()``.
    """
    stream = sys.stderr if stream is None else stream
    if enabled is None:
        enabled = bool(getattr(stream, "isatty", lambda: False)())
    if not enabled:
        return NullBar(total)
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return NullBar(total)
    return tqdm(total=total, desc=desc or None, unit=unit, file=stream, dynamic_ncols=True,
                mininterval=0.1, leave=True, unit_scale=unit_scale,
                unit_divisor=1024 if unit_scale and unit == "B" else 1000)
