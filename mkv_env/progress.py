"""A tiny dependency-free progress bar on stderr (the core package needs no tqdm)."""

from __future__ import annotations

import sys
import time


class Progress:
    """``with Progress(total, "record") as bar: bar.update(1)``.

    Draws ``desc [#####.....] 37/100 12.3/s ETA 5s`` on one line, redrawn at most every
    ``min_interval_s``. Disabled (draws nothing) when ``enabled`` is False, or by default when the
    stream is not a terminal; :meth:`write` prints a line above the bar either way.
    """

    def __init__(self, total: int, desc: str = "", stream=None, enabled: bool | None = None,
                 width: int = 30, min_interval_s: float = 0.1, unit: str = "it"):
        self.total = max(int(total), 0)
        self.desc = desc
        self.stream = stream if stream is not None else sys.stderr
        if enabled is None:
            enabled = bool(getattr(self.stream, "isatty", lambda: False)())
        self.enabled = enabled
        self.width = width
        self.min_interval_s = min_interval_s
        self.unit = unit
        self.n = 0
        self._start = time.perf_counter()
        self._last_draw = -1.0
        self._drawn = False

    def __enter__(self) -> Progress:
        self._draw(force=True)
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()

    def update(self, n: int = 1) -> None:
        self.n += n
        now = time.perf_counter()
        if now - self._last_draw >= self.min_interval_s or self.n >= self.total:
            self._draw(now=now)

    def write(self, line: str) -> None:
        if self._drawn:
            self.stream.write("\r\033[K")
        self.stream.write(line + "\n")
        self._draw(force=True)

    def close(self) -> None:
        if self.enabled and self._drawn:
            self._draw(force=True)
            self.stream.write("\n")
            self.stream.flush()
            self._drawn = False
        self.enabled = False

    def _draw(self, force: bool = False, now: float | None = None) -> None:
        if not self.enabled:
            return
        now = time.perf_counter() if now is None else now
        if not force and now - self._last_draw < self.min_interval_s:
            return
        self._last_draw = now
        elapsed = now - self._start
        rate = self.n / elapsed if elapsed > 0 else 0.0
        if self.total:
            frac = min(self.n / self.total, 1.0)
            fill = int(round(frac * self.width))
            bar = "#" * fill + "." * (self.width - fill)
            eta = (self.total - self.n) / rate if rate > 0 else float("nan")
            eta_s = f" ETA {eta:.0f}s" if eta == eta else ""
            text = f"{self.desc} [{bar}] {self.n}/{self.total} {rate:.1f} {self.unit}/s{eta_s}"
        else:
            text = f"{self.desc} {self.n} {rate:.1f} {self.unit}/s"
        self.stream.write("\r\033[K" + text.strip())
        self.stream.flush()
        self._drawn = True
