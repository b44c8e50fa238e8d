"""The one progress display on standard error, for every long command.

``Ticker`` is a counted line, ``label: done/total unit, rate, elapsed, ETA`` (export, render,
eval, bench). On a terminal the line is redrawn in place at most every ``REDRAW_S``, cut to
the terminal's width; in a log (not a terminal) a line is written at every tenth of the work, so logs stay short.
Nothing is written for work that finishes before ``QUIET_S``.

``StepBar`` is `mine submit`'s bar: the windows done, the failed ones, frames/s observed,
an ETA that counts the work inside windows (observe steps run well ahead of their track) and
the steps in flight. On a terminal it is a ``rich`` progress display that fits the terminal's
width; in a log, a plain line at every tenth of the work. It is drawn whenever the driver
asks (``draw``), while it is ``enabled``.
"""

from __future__ import annotations

import os
import sys
import time

FALLBACK_COLUMNS = 80  # ours: a terminal whose size the system does not tell
REDRAW_S = 0.5  # ours: a terminal line is redrawn at most this often
QUIET_S = 2.0  # ours: work shorter than this prints nothing
BAR_MIN = 10  # ours: the fewest characters of StepBar's bar on a narrow terminal
TAIL_RATIO = 3  # ours: on a wide terminal the bar takes a quarter of what is left after "windows n/m"
# mine submit's steps → what its bar calls them (the stitch runs as the ``finalize`` step)
PHASES = (("observe", "observe"), ("track", "track"), ("finalize", "stitch"))


def terminal_width(stream) -> int:
    """Columns of the terminal ``stream`` writes to (80 when it cannot be told)."""
    try:
        return os.get_terminal_size(stream.fileno()).columns or FALLBACK_COLUMNS
    except (AttributeError, OSError, ValueError):
        return FALLBACK_COLUMNS


class Ticker:
    """``tick(done)`` as work goes, ``close()`` at the end: ``label: done/total, rate, ETA``."""

    def __init__(self, label: str, total: int, unit: str = "frames", stream=None):
        self.label, self.total, self.unit = label, max(int(total), 0), unit
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.t0 = self.last = time.perf_counter()
        self.decile = 0
        self.shown = False

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def redraw(self, text: str) -> None:
        """``text`` in place of the line shown last (the terminal's carriage return), cut to
        the terminal's width: a wrapped line is not redrawn in place but stacked."""
        width = terminal_width(self.stream) - 1  # the last column left empty: no pending wrap
        self.stream.write("\r" + text[:width].ljust(width))
        self.stream.flush()

    def line(self, done: int) -> str:
        dt = self.elapsed()
        rate = done / dt if dt > 0 else 0.0
        eta = f", ETA {(self.total - done) / rate:.0f} s" if rate > 0 and done < self.total else ""
        return f"{self.label}: {done}/{self.total} {self.unit}, {rate:.2f} {self.unit}/s, {dt:.0f} s{eta}"

    def tick(self, done: int) -> None:
        now = time.perf_counter()
        if now - self.t0 < QUIET_S:
            return
        if self.tty:
            if now - self.last >= REDRAW_S:
                self.redraw(self.line(done))
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
            if self.tty:
                self.redraw(end)
            self.stream.write("\n" if self.tty else (end + "\n") if self.decile < 10 else "")
            self.stream.flush()


class StepBar:
    """The bar of ``mine submit``: windows done, the phase of every step in flight, frames/s
    and an ETA.

    Frames/s counts frames *observed* (finished observe steps and what running ones report)
    over the time since the job's first step: observation is most of a window's cost and
    runs well ahead of its track, so the rate is there from the first frames a worker
    finishes instead of 0.00 until a whole window is tracked. At the end it is the summary's
    rate (every core frame observed and tracked).

    The ETA counts the work inside windows too: each step's seconds per core frame, measured
    on the steps finished so far, weigh the frames observed and tracked; the elapsed time
    over the work done so far gives the time left. Until a track step has finished its cost
    is unknown and the estimate counts observation alone (``ETA ≈``).

    On a terminal the bar is a ``rich`` progress display, redrawn in place and never wider
    than the terminal (the phase text is cut with an ellipsis first). Elsewhere (a log, a
    pipe) it is one plain line at each tenth of the work (frames observed and tracked) and
    one at the end: at most 11 lines, and never a carriage return."""

    def __init__(self, total: int, enabled: bool, total_frames: int = 0, stream=None):
        self.total, self.enabled, self.total_frames = max(int(total), 0), enabled, total_frames
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.t0 = self.last = time.perf_counter()
        self.done = self.failed = self.frames = 0
        self.phases: dict[str, int] = {}
        self.observing = 0  # core frames the observe steps in flight have reported (steps.observed_so_far)
        self.step_frames = {"observe": 0, "track": 0}  # core frames and seconds of the windows' finished steps
        self.step_seconds = {"observe": 0.0, "track": 0.0}
        self.decile = 0  # tenths of the work written so far (not a terminal)
        self.lines = 0  # plain lines written (not a terminal)
        self._live = None  # the rich display, made at the first draw on a terminal

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def observed(self) -> int:
        """Core frames observed so far: finished observe steps and what running ones report."""
        return min(self.step_frames["observe"] + self.observing, self.total_frames)

    def rate(self) -> float:
        return self.observed() / max(self.elapsed(), 1e-9)

    def fraction(self) -> float:
        """The work done, 0 to 1: frames observed and tracked, each half of it (windows done
        when there are no frames to count)."""
        if self.total_frames <= 0:
            return self.done / max(self.total, 1)
        return min((self.observed() + min(self.step_frames["track"], self.total_frames)) / (2 * self.total_frames), 1.0)

    def update(self, ok: bool, frames: int) -> None:
        self.done += 1
        self.failed += not ok
        self.frames += frames
        self.draw()

    def step_finished(self, step: str, core_frames: int, seconds: float) -> None:
        """A window's observe or track step ended after ``seconds`` (ok or not)."""
        self.step_frames[step] += core_frames
        self.step_seconds[step] += seconds

    def running(self, steps: list[str]) -> None:
        """The steps in flight now (their names), for the phase display."""
        self.phases = {label: steps.count(step) for step, label in PHASES}
        self.draw()

    def _cost(self, step: str) -> float | None:
        n = self.step_frames[step]
        return self.step_seconds[step] / n if n else None

    def eta(self) -> str:
        tracked = self.step_frames["track"]
        if tracked >= self.total_frames:
            return "stitching" if self.phases.get("stitch") else ""
        seen = self.observed()
        c_obs, c_trk = self._cost("observe"), self._cost("track")
        if c_obs is None and seen:  # the first observe steps still running: their reports alone
            c_obs = 1.0
        if c_obs is None:
            return "ETA —"
        approx = c_trk is None
        c_trk = c_trk or 0.0
        done = seen * c_obs + tracked * c_trk
        if done <= 0:
            return "ETA —"
        left = (self.total_frames - seen) * c_obs + (self.total_frames - tracked) * c_trk
        dt = max(self.elapsed(), 1e-9)
        return f"ETA {'≈ ' if approx else ''}{dt * left / done:.0f} s"

    def head(self) -> str:
        return f"windows {self.done}/{self.total} ({self.failed} failed)"

    def tail(self) -> str:
        """Frames/s, elapsed, ETA, then the steps in flight (cut first where the width is short)."""
        phase = " · ".join(f"{label} {k}" + (f" ({self.observing} frames in)" if label == "observe" and self.observing
                                               else "") for label, k in self.phases.items() if k) or "waiting"
        rate = f"{self.rate():.2f}" if self.observed() else "—"  # no frame yet: no rate, rather than 0.00
        return "  ".join(x for x in (f"{rate} frames/s", f"{self.elapsed():.0f} s", self.eta(), phase) if x)

    def line(self) -> str:
        """The plain line of a log."""
        return f"{self.head()}  {self.tail()}"

    def _start_live(self):
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TextColumn
        from rich.table import Column

        console = Console(file=self.stream, highlight=False)
        live = Progress(TextColumn("{task.description}", table_column=Column(no_wrap=True)),
                        BarColumn(bar_width=None, table_column=Column(min_width=BAR_MIN, ratio=1)),
                        TextColumn("{task.fields[tail]}", table_column=Column(no_wrap=True, overflow="ellipsis",
                                                                               ratio=TAIL_RATIO)),
                        console=console, auto_refresh=False, expand=True)
        live.add_task(self.head(), total=max(self.total, 1), tail=self.tail())
        live.start()
        return live

    def draw(self) -> None:
        if not self.enabled:
            return
        if self.tty:
            if self._live is None:
                self._live = self._start_live()
            task = self._live.task_ids[0]
            self._live.update(task, description=self.head(), completed=self.done, tail=self.tail(), refresh=True)
            return
        decile = int(10 * self.fraction())
        if decile > self.decile:
            self.decile = decile
            self._write(self.line())

    def _write(self, text: str) -> None:
        self.stream.write(text + "\n")
        self.stream.flush()
        self.lines += 1

    def close(self) -> None:
        if not self.enabled:
            return
        if self._live is not None:
            self.draw()
            self._live.stop()  # the last state stays on screen; the cursor is shown again
            self._live = None
        elif not self.tty:
            self._write(self.line())
