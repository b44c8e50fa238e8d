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
