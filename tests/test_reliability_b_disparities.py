"""Issue 11 item 6: a bad ``geometry.stereo.num_disparities=95`` says why, without Ray's noise.

The disparity stage raises ValueError on a search range that is not a multiple of 16.
Before, the window's error was ``system failure: ray::Worker.run() (pid=…)`` in terminal
colours, the reason 1.5 kB deep in the manifest. Now either the driver refuses the
config before Ray starts (a preflight), or every window fails with the step, the
exception type and the message in its first line — in the summary, in ``mine status``
and in the manifest's error column — and ``mine submit`` exits non-zero.
"""

from __future__ import annotations

import pyarrow.parquet as pq
import pytest
from _reliability_b import ANSI, TINY, TINY_WINDOWS, status, submit

pytestmark = pytest.mark.slow  # a `mine submit` on a local Ray

REASON = "num_disparities must be a positive multiple of 16, got 95"


def test_num_disparities_95_fails_with_its_reason(tmp_path):
    out = tmp_path / "cat"
    rc, stdout, stderr = submit(out, *TINY, "--set", "geometry.stereo.num_disparities=95", logs=tmp_path / "logs")
    assert rc != 0, stdout + stderr
    assert ANSI not in stdout + stderr and "ray::" not in stdout + stderr and "Traceback" not in stderr
    if not (out / "manifest").exists():  # refused before any window ran (a preflight)
        assert "num_disparities" in stderr, stderr
        return
    failed = sorted(ln for ln in stdout.splitlines() if ln.startswith("FAILED"))
    assert failed == [f"FAILED {w}: observe step raised ValueError: {REASON}" for w in TINY_WINDOWS], stdout
    rc, shown = status(out)
    assert rc == 1 and "0 done, 2 failed, 0 pending" in shown, shown
    for w in TINY_WINDOWS:
        assert f"failed   synthetic/{w}  attempts 1  observe step raised ValueError: {REASON}" in shown, shown
        row = pq.read_table(out / "manifest" / "dataset=synthetic" / "sequence=0000" / f"{w}.parquet").to_pylist()[0]
        first, *detail = row["error"].splitlines()
        assert first == f"observe step raised ValueError: {REASON}" and ANSI not in row["error"]
        assert any("disparity" in ln for ln in detail), row["error"]  # the end of the worker's traceback follows
