"""A plain progress bar on standard error (no dependency), and notes that do not break it."""

from __future__ import annotations

import sys
import time
from typing import TextIO

__all__ = ["ProgressBar", "format_seconds", "note"]

#: The bar drawn last and not closed yet (a note first ends its line).
_drawn: ProgressBar | None = None


def format_seconds(seconds: float) -> str:
    """``7s``, ``2m05s``, ``1h02m``."""
    s = int(round(max(0.0, seconds)))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{s % 3600 // 60:02d}m"


def note(text: str, stream: TextIO | None = None) -> None:
    """Print ``text`` on its own line of standard error, below a bar being drawn (which then
    continues on the next line)."""
    global _drawn
    out = stream if stream is not None else sys.stderr
    if _drawn is not None and _drawn.stream is out:
        out.write("\n")
        _drawn._drawn = False
        _drawn = None
    out.write(text + "\n")
    out.flush()


class ProgressBar:
    """``bar(done, total)`` redraws one line: label, bar, count, rate, time so far and the
    estimated time left (from the rate so far); ``close()`` ends it."""

    def __init__(
        self,
        label: str,
        unit: str = "scans",
        stream: TextIO | None = None,
        enabled: bool = True,
        width: int = 30,
    ) -> None:
        self.label = label
        self.unit = unit
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.width = width
        self.start = time.perf_counter()
        self._drawn = False

    def __call__(self, done: int, total: int) -> None:
        global _drawn
        if not self.enabled:
            return
        elapsed = time.perf_counter() - self.start
        frac = done / total if total else 1.0
        filled = int(round(frac * self.width))
        rate = done / elapsed if elapsed > 0 else 0.0
        if done >= total:
            left = "done"
        elif done > 0:
            left = f"ETA {format_seconds(elapsed / done * (total - done))}"
        else:
            left = "ETA ?"
        self.stream.write(
            f"\r{self.label} [{'#' * filled}{'.' * (self.width - filled)}] {done}/{total} "
            f"{self.unit} {rate:.1f}/s {format_seconds(elapsed)} {left}   "
        )
        self.stream.flush()
        self._drawn = True
        _drawn = self

    def close(self) -> None:
        global _drawn
        if self._drawn:
            self.stream.write("\n")
            self.stream.flush()
            self._drawn = False
        if _drawn is self:
            _drawn = None
