"""A one-line progress bar on stderr, shown only when stderr is a terminal."""
from __future__ import annotations

import sys
import time


class ProgressBar:
    """Call with (done, total); redraws at most ``rate_hz`` times a second."""

    def __init__(self, label: str, stream=None, rate_hz: float = 5.0):
        self.label = label
        self.stream = stream or sys.stderr
        self.enabled = self.stream.isatty()
        self.interval = 1.0 / rate_hz
        self.started = time.perf_counter()
        self.last = 0.0

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled:
            return
        now = time.perf_counter()
        if done < total and now - self.last < self.interval:
            return
        self.last = now
        fraction = done / total if total else 1.0
        filled = int(30 * fraction)
        elapsed = now - self.started
        eta = elapsed / fraction - elapsed if fraction > 0 else float("nan")
        self.stream.write(f"\r{self.label} [{'#' * filled}{'.' * (30 - filled)}] {100 * fraction:5.1f}% "
                          f"{elapsed:6.1f}s elapsed, {eta:6.1f}s left ")
        if done >= total:
            self.stream.write("\n")
        self.stream.flush()
