"""A small progress bar on stderr; when stderr is not a terminal (a log file, CI), a plain line every
``LINE_EVERY_S`` instead, so a long run is never silent for minutes and the log stays readable."""
from __future__ import annotations

import sys
import time


LINE_EVERY_S = 15.0


class Progress:
    def __init__(self, total: float, label: str, enabled: bool | None = None, every_s: float = 0.25):
        self.total = max(total, 1e-12)
        self.label = label
        self.tty = sys.stderr.isatty()
        self.enabled = True if enabled is None else enabled
        self.every_s = every_s if self.tty else LINE_EVERY_S
        self._start = time.monotonic()
        self._last = 0.0 if self.tty else self._start      # plain lines: the first one after LINE_EVERY_S

    def update(self, done: float, note: str = "") -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if now - self._last < self.every_s and (done < self.total or not self.tty):
            return
        self._last = now
        frac = min(done / self.total, 1.0)
        if self.tty:
            bar = "#" * int(frac * 30)
            sys.stderr.write(f"\r{self.label} [{bar:<30}] {frac * 100:5.1f}% {now - self._start:6.1f}s {note}   ")
        else:
            sys.stderr.write(f"{self.label}: {frac * 100:5.1f}% after {now - self._start:.0f} s {note}\n")
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled and self.tty:
            self.update(self.total)
            sys.stderr.write("\n")
            sys.stderr.flush()


def compile_kernels(who: str) -> None:
    """The identifier's kernels compiled in the foreground, with a bar, when this machine has not yet
    compiled them (``identifier.kernel_cache``): once per machine and source, instead of unseen inside a
    TCU process the plant is waiting for.  ``who`` prefixes the lines (``hil run``)."""
    from identifier import kernel_cache

    if kernel_cache.fresh():
        return
    sys.stderr.write(f"{who}: compiling the identifier's kernels (once per machine; later runs load them)\n")
    sys.stderr.flush()
    bar = Progress(1.0, f"{who}: compiling")
    t0 = time.monotonic()
    if kernel_cache.compile_all(lambda done, total, name: bar.update(done / total, name)):
        bar.close()
        sys.stderr.write(f"{who}: kernels compiled in {time.monotonic() - t0:.0f} s\n")
        sys.stderr.flush()
