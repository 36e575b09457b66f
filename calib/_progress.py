"""A tiny dependency-free progress bar on stderr (silent when disabled)."""

from __future__ import annotations

import sys
import time


class Progress:
    """``with Progress(total, "label") as bar: bar.update()``; draws ``label [####....]
    k/total``."""

    def __init__(
        self, total: int, label: str = "", enabled: bool = True, stream=None, width: int = 30
    ):
        self.total = max(int(total), 1)
        self.label = label
        self.enabled = enabled
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self.count = 0
        self._last = 0.0
        self._t0 = time.monotonic()

    def __enter__(self):
        self._draw(force=True)
        return self

    def __exit__(self, *exc):
        self.count = min(self.count, self.total)
        self._draw(force=True)
        if self.enabled:
            self.stream.write("\n")
            self.stream.flush()
        return False

    def update(self, k: int = 1) -> None:
        self.count += k
        self._draw()

    def _draw(self, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if not force and now - self._last < 0.1 and self.count < self.total:
            return
        self._last = now
        frac = min(self.count / self.total, 1.0)
        filled = int(round(frac * self.width))
        bar = "#" * filled + "." * (self.width - filled)
        elapsed = now - self._t0
        self.stream.write(f"\r{self.label} [{bar}] {self.count}/{self.total} {elapsed:5.1f}s")
        self.stream.flush()
