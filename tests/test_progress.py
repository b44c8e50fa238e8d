"""``mining.progress.Ticker``: a log gets a line per tenth of the work, short work prints nothing."""

from __future__ import annotations

import io

import mining.progress as progress
from mining.progress import Ticker


def test_a_log_gets_a_line_per_tenth_and_short_work_nothing(monkeypatch):
    log = io.StringIO()
    quick = Ticker("quick", 10, stream=log)
    for k in range(10):
        quick.tick(k)
    quick.close()
    assert log.getvalue() == ""  # finished before QUIET_S
    monkeypatch.setattr(progress, "QUIET_S", 0.0)
    slow = Ticker("export", 100, stream=log)
    for k in range(1, 101):
        slow.tick(k)
    slow.close()
    lines = log.getvalue().splitlines()
    assert len(lines) == 10 and lines[0].startswith("export: 10/100 frames") and lines[-1].startswith("export: 100/100")
    assert all("frames/s" in line for line in lines)


def test_submits_bar_in_a_log_is_a_line_per_tenth_and_counts_observed_frames():
    """`mine submit`'s bar off a terminal: at most a line per tenth of the work (frames observed
    and tracked) and one at the end, no carriage return; the rate is there before any window
    is tracked (it counts observed frames)."""
    from mining.progress import StepBar

    log = io.StringIO()
    bar = StepBar(10, True, total_frames=1000, stream=log)
    bar.t0 -= 10.0
    bar.running(["observe", "observe"])
    assert log.getvalue() == ""  # nothing observed yet
    for k in range(1, 1001):  # frames reported one by one, every redraw asked for
        bar.observing = k % 100
        if k % 100 == 0:
            bar.step_finished("observe", 100, 5.0)
        bar.draw()
    first = log.getvalue().splitlines()[0]
    assert first.startswith("windows 0/10 (0 failed)") and float(first.split()[4]) > 0, first
    for _ in range(10):
        bar.step_finished("track", 100, 1.0)
        bar.update(True, 100)
    bar.close()
    lines = log.getvalue().splitlines()
    assert "\r" not in log.getvalue() and len(lines) == 11, lines
    assert lines[-1].startswith("windows 10/10 (0 failed)")
