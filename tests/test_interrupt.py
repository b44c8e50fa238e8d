"""Issue 11 item 6: Ctrl-C ends `mine submit` with one line, and status tells running from pending.

A real `mine submit` on a local Ray, in a session of its own. While it runs, ``mine
status`` shows the windows under way as ``running``, with the driver's pid. Then the
test sends SIGINT to the job's process group, as a terminal's Ctrl-C does: the driver
prints the single line "interrupted — rerun the same command to resume" (before: 30
lines of Ray traceback) and exits 130; nothing is left "running", the unfinished
windows are pending, and the same command finishes the job.
"""

from __future__ import annotations

import os
import re
import signal
import time

import pytest
from _run import JOB_TIMEOUT_S, Mine, status, submit

pytestmark = pytest.mark.slow  # `mine submit` processes on local Rays, interrupted and resumed

# Full 1242×375 frames: at half size the 3 windows mined in ~7 s, and a loaded machine's `mine status`
# before the Ctrl-C took long enough that the job had finished (rc 0) when the signal came.
JOB = ["--dataset", "synthetic", "--sequences", "0000", "--option", "n_frames=30", "--set", "window.core=10",
       "--set", "window.context_before=5", "--set", "window.context_after=5"]
COUNTS = re.compile(r"(\d+) windows: (\d+) done, (\d+) failed, (\d+) pending(?:, (\d+) running)?$", re.M)


def counts(shown: str) -> dict[str, int]:
    m = COUNTS.search(shown)
    assert m, shown
    return dict(zip(("windows", "done", "failed", "pending", "running"), (int(g or 0) for g in m.groups())))


def test_ctrl_c_prints_one_line_and_exits_130_and_status_tells_running_from_pending(tmp_path):
    out = tmp_path / "cat"
    job = Mine(out, *JOB, logs=tmp_path / "logs1")
    try:
        deadline = time.monotonic() + JOB_TIMEOUT_S
        while not (out / "_running").exists() or not any((out / "_running").rglob("*.json")):
            assert job.proc.poll() is None, "the job ended before any window started"
            assert time.monotonic() < deadline, "no window started in time"
            time.sleep(0.1)
        rc, shown = status(out)
        now = counts(shown)
        assert rc == 0 and now["running"] >= 1 and now["done"] < 3, shown
        assert re.search(rf"running  synthetic/0000-\d+-\d+  attempts 0  (observe|track) step, driver pid "
                         rf"{job.proc.pid} on \S+, since ", shown), shown
        os.killpg(job.sid, signal.SIGINT)  # what a terminal's Ctrl-C does: the whole foreground group
        rc = job.proc.wait(120)
    finally:
        _, stdout, stderr = job.finish()
    assert rc == 130, stdout + stderr
    said = [ln for ln in stderr.splitlines() if ln.strip() and "INFO worker.py" not in ln]  # Ray's "Started a local Ray"
    assert said == ["interrupted — rerun the same command to resume"], stderr
    assert "Traceback" not in stdout + stderr
    assert "will be retried" not in stdout + stderr and "(raylet)" not in stdout + stderr, stdout + stderr

    rc, shown = status(out)
    after = counts(shown)
    assert rc == 0 and after["running"] == 0 and after["pending"] >= 1, shown
    assert after["done"] + after["pending"] == 3, shown

    rc, stdout, stderr = submit(out, *JOB, logs=tmp_path / "logs2")
    assert rc == 0, stdout + stderr
    rc, shown = status(out)
    assert rc == 0 and counts(shown)["done"] == 3 and "1 stitched" in shown, shown
