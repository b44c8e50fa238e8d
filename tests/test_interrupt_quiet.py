"""After Ctrl-C, `mine submit` says one line and Ray says nothing.

Ray's driver prints the errors the cluster publishes (not only the workers' logs, which
``log_to_driver=False`` keeps away) on standard output: the calls still in flight when the
executor killed its actors came out as ``(raylet) Task Worker.run failed. There are 3
retries remaining, so the task will be retried…`` after the "interrupted" line (2 runs of 3
here). The executor now cancels those calls before it kills the actors.

A real `mine submit` on a local Ray, in a session of its own, gets SIGINT on its process
group (a terminal's Ctrl-C) while its windows' steps run.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time

import pytest
from _run import JOB_TIMEOUT_S, env, kill_session, mine_cmd

from conftest import REPO

pytestmark = pytest.mark.slow  # a `mine submit` process on a local Ray

# Full-size frames, three 10-frame windows: several seconds of steps in flight to interrupt.
JOB = ["--dataset", "synthetic", "--sequences", "0000", "--option", "n_frames=30", "--set", "window.core=10",
       "--set", "window.context_before=5", "--set", "window.context_after=5"]
IN_FLIGHT_S = 3.0  # ours: after the first step starts, the steps are well under way (the job mines ~13 s)


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)  # a shell's background job may have it ignored


def test_ctrl_c_leaves_no_ray_lines(tmp_path):
    out = tmp_path / "cat"
    with open(tmp_path / "stdout.txt", "w+") as so, open(tmp_path / "stderr.txt", "w+") as se:
        proc = subprocess.Popen(mine_cmd("submit", *JOB, "--out", str(out), "--workers", "2", "--no-progress"),
                                cwd=REPO, env=env(), stdout=so, stderr=se, start_new_session=True,
                                preexec_fn=_default_sigint)
        try:
            deadline = time.monotonic() + JOB_TIMEOUT_S
            while not (out / "_running").exists() or not any((out / "_running").rglob("*.json")):
                assert proc.poll() is None and time.monotonic() < deadline, "no window started"
                time.sleep(0.1)
            time.sleep(IN_FLIGHT_S)
            assert proc.poll() is None, "the job ended before the Ctrl-C"
            os.killpg(proc.pid, signal.SIGINT)
            rc = proc.wait(120)
            time.sleep(1.0)  # what Ray would print late has had time to arrive
        finally:
            kill_session(proc.pid)
        so.seek(0)
        se.seek(0)
        stdout, stderr = so.read(), se.read()
    assert rc == 130, stdout + stderr
    assert stdout == "", stdout
    said = [ln for ln in stderr.splitlines() if ln.strip() and "INFO worker.py" not in ln]  # Ray's "Started a local Ray"
    assert said == ["interrupted — rerun the same command to resume"], stderr
