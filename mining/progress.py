"""The one progress display on standard error, for every long command.

``Ticker`` is a counted line, ``label: done/total unit, rate, elapsed, ETA`` (export, render,
eval, bench). On a terminal the line is redrawn in place at most every ``REDRAW_S``; in a
log (not a terminal) a line is written at every tenth of the work, so logs stay short.
Nothing is written for work that finishes before ``QUIET_S``.

``StepBar`` is the same display as `mine submit`'s bar: a bar of the windows done, the
failed ones, the steps in flight, frames/s and an ETA that counts the work inside windows
(observe steps run well ahead of their track). It is redrawn in place whenever the driver
asks (``draw``), while it is ``enabled``.
"""

from __future__ import annotations

import sys
import time

REDRAW_S = 0.5  # ours: a terminal line is redrawn at most this often
QUIET_S = 2.0  # ours: work shorter than this prints nothing
BAR_WIDTH = 30  # ours: characters of StepBar's bar
# mine submit's steps → what its bar calls them (the stitch runs as the ``finalize`` step)
PHASES = (("observe", "observe"), ("track", "track"), ("finalize", "stitch"))


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
        """``text`` in place of the line shown last (the terminal's carriage return)."""
        self.stream.write("\r" + text + "   ")
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
            self.stream.write(("\r" + end + "   \n") if self.tty else (end + "\n") if self.decile < 10 else "")
            self.stream.flush()


class StepBar(Ticker):
    """The bar of ``mine submit``: windows done, the phase of every step in flight, frames/s
    and an ETA. Frames/s is the one definition the summary uses too: core frames of the
    windows tracked this run over the mining time (``run_job``'s, from its first step).

    The ETA counts the work inside windows too, since a window's observation (most of its
    cost) runs well ahead of its track: each step's seconds per core frame, measured on the
    steps finished so far, weigh the frames observed (finished observe steps and what running
    ones report) and tracked; the elapsed time over the work done so far gives the time
    left. Until a track step has finished its cost is unknown and the estimate counts
    observation alone (``ETA ≈``)."""

    def __init__(self, total: int, enabled: bool, total_frames: int = 0, stream=None):
        super().__init__("windows", total, "windows", stream)
        self.enabled = enabled
        self.total_frames = total_frames
        self.done = self.failed = self.frames = 0
        self.phases: dict[str, int] = {}
        self.observing = 0  # core frames the observe steps in flight have reported (steps.observed_so_far)
        self.step_frames = {"observe": 0, "track": 0}  # core frames and seconds of the windows' finished steps
        self.step_seconds = {"observe": 0.0, "track": 0.0}

    def rate(self) -> float:
        return self.frames / max(self.elapsed(), 1e-9)

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
        seen = min(self.step_frames["observe"] + self.observing, self.total_frames)
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

    def line(self, done: int) -> str:
        dt = self.elapsed()
        n = BAR_WIDTH * done // max(self.total, 1)
        phase = " · ".join(f"{label} {k}" + (f" ({self.observing} frames in)" if label == "observe" and self.observing
                                               else "") for label, k in self.phases.items() if k) or "waiting"
        return (f"[{'#' * n}{'.' * (BAR_WIDTH - n)}] windows {done}/{self.total} ({self.failed} failed)  "
                f"{phase}  {self.rate():.2f} frames/s  {dt:.0f} s  {self.eta()}")

    def draw(self) -> None:
        if self.enabled:
            self.redraw(self.line(self.done))

    def close(self, done: int | None = None) -> None:
        if self.enabled:
            self.stream.write("\n")
