"""`mine submit`'s progress bar as a person sees it: on an 80-column terminal no line is wider
than the terminal (a wider line wraps, and every redraw then stacks a copy), and in a log
there are a few plain lines, no carriage returns, with a frames/s from the first frames.

Each test runs a real `mine submit` of the tiny synthetic job on a local Ray, in a process
(and session) of its own: once on a pseudo-terminal of 80 columns, once into a file.
"""

from __future__ import annotations

import fcntl
import os
import pty
import re
import struct
import subprocess
import termios
import time

import pytest
from _jobs import TINY
from _run import JOB_TIMEOUT_S, env, kill_session, mine_cmd

from conftest import REPO

pytestmark = pytest.mark.slow  # `mine submit` processes on local Rays

CSI = re.compile(r"\x1b\[[0-9;?]*[ -/]*[@-~]")  # a terminal control sequence (cursor, colour, erase)
COLUMNS = 80
MAX_LOG_LINES = 12  # the bound: a line per tenth of the work, and the end
RATE = re.compile(r"([0-9.]+) frames/s")


def _env() -> dict[str, str]:
    e = env()
    for k in ("COLUMNS", "LINES", "NO_COLOR"):  # the terminal's own size must decide
        e.pop(k, None)
    return e | {"TERM": "xterm-256color"}


def test_the_bar_fits_an_80_column_terminal(tmp_path):
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, COLUMNS, 0, 0))
    proc = subprocess.Popen(mine_cmd("submit", *TINY, "--out", str(tmp_path / "cat"), "--workers", "2"), cwd=REPO,
                            env=_env(), stdin=slave, stdout=slave, stderr=slave, start_new_session=True)
    os.close(slave)
    shown = bytearray()
    deadline = time.monotonic() + JOB_TIMEOUT_S
    try:
        while time.monotonic() < deadline:
            try:
                chunk = os.read(master, 65536)
            except OSError:  # EIO: every writer has closed the terminal
                break
            if not chunk:
                break
            shown += chunk
        rc = proc.wait(60)
    finally:
        kill_session(proc.pid)
        os.close(master)
    text = CSI.sub("", shown.decode("utf-8", "replace"))
    assert rc == 0, text
    # every redraw of the bar, as the terminal got it (the summary's plain lines may wrap: printed once)
    bars = [ln for ln in re.split(r"[\r\n]", text) if ln.startswith("windows ")]
    assert bars and any(ln.startswith("windows 2/2 (0 failed)") for ln in bars), text
    wide = [ln for ln in bars if len(ln.rstrip()) > COLUMNS]
    assert not wide, wide
    (tmp_path / "bars.txt").write_text("\n".join(bars))
    assert any(c in shown.decode() for c in ("━", "╸")), text  # the bar itself was drawn


def test_a_log_gets_a_few_plain_lines_with_a_rate_from_the_first_frames(tmp_path):
    log = tmp_path / "stderr.txt"
    with open(log, "wb") as err, open(tmp_path / "stdout.txt", "wb") as out:
        proc = subprocess.Popen(mine_cmd("submit", *TINY, "--out", str(tmp_path / "cat"), "--workers", "2"),
                                cwd=REPO, env=_env(), stdout=out, stderr=err, start_new_session=True)
        try:
            rc = proc.wait(JOB_TIMEOUT_S)
        finally:
            kill_session(proc.pid)
    raw = log.read_bytes().decode()
    assert rc == 0, raw
    assert "\r" not in raw and "\x1b[" not in raw, raw
    bars = [ln for ln in raw.splitlines() if ln.startswith("windows ")]
    assert 2 <= len(bars) <= MAX_LOG_LINES, raw
    assert bars[-1].startswith("windows 2/2 (0 failed)"), raw
    # every line is written once frames were observed: the rate is never 0.00 (it was until a window was tracked)
    rates = [float(RATE.search(ln).group(1)) for ln in bars]
    assert all(r > 0 for r in rates), bars
