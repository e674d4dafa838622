"""A small progress bar on stderr (silent when stderr is not a terminal unless forced)."""
from __future__ import annotations

import sys
import time


class Progress:
    def __init__(self, total: float, label: str, enabled: bool | None = None, every_s: float = 0.25):
        self.total = max(total, 1e-12)
        self.label = label
        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self.every_s = every_s
        self._last = 0.0
        self._start = time.monotonic()

    def update(self, done: float, note: str = "") -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if now - self._last < self.every_s and done < self.total:
            return
        self._last = now
        frac = min(done / self.total, 1.0)
        bar = "#" * int(frac * 30)
        sys.stderr.write(f"\r{self.label} [{bar:<30}] {frac * 100:5.1f}% {now - self._start:6.1f}s {note}   ")
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            self.update(self.total)
            sys.stderr.write("\n")
            sys.stderr.flush()
