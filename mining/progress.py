"""A one-line progress report on standard error for long commands (export, eval, bench).

On a terminal the line is redrawn in place at most every ``REDRAW_S``; in a log (not a
terminal) a line is written at every tenth of the work, so logs stay short. Nothing is
written for work that finishes before ``QUIET_S``.
"""

from __future__ import annotations

import sys
import time

REDRAW_S = 0.5  # ours: a terminal line is redrawn at most this often
QUIET_S = 2.0  # ours: work shorter than this prints nothing


class Ticker:
    """``tick(done)`` as work goes, ``close()`` at the end: ``label: done/total, rate, ETA``."""

    def __init__(self, label: str, total: int, unit: str = "frames", stream=None):
        self.label, self.total, self.unit = label, max(int(total), 0), unit
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.t0 = self.last = time.perf_counter()
        self.decile = 0
        self.shown = False

    def line(self, done: int) -> str:
        dt = time.perf_counter() - self.t0
        rate = done / dt if dt > 0 else 0.0
        eta = f", ETA {(self.total - done) / rate:.0f} s" if rate > 0 and done < self.total else ""
        return f"{self.label}: {done}/{self.total} {self.unit}, {rate:.2f} {self.unit}/s, {dt:.0f} s{eta}"

    def tick(self, done: int) -> None:
        now = time.perf_counter()
        if now - self.t0 < QUIET_S:
            return
        if self.tty:
            if now - self.last >= REDRAW_S:
                self.stream.write("\r" + self.line(done) + "   ")
                self.stream.flush()
                self.last, self.shown = now, True
            return
        decile = 10 * done // max(self.total, 1)
        if decile > self.decile:
            self.decile = decile
            self.stream.write(self.line(done) + "\n")
            self.stream.flush()
            self.shown = True

    def close(self, done: int | None = None) -> None:
        if self.shown:
            end = self.line(self.total if done is None else done)
            self.stream.write(("\r" + end + "   \n") if self.tty else (end + "\n") if self.decile < 10 else "")
            self.stream.flush()
