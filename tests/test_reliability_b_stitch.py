"""Issue 11 item 6: a failed stitch is a row of the manifest that ``mine status`` shows.

A finished tiny job; then one window's tube part is damaged (its Parquet footer
overwritten, the size unchanged) and the sequence's "stitched" marker removed, as a
driver killed between tracking and stitching leaves it: the resubmission must stitch
again, and that stitch fails. Before, the summary said ``system failure: ray::...``, no
row recorded it, and ``mine status`` exited 0 over an empty catalogue. Now the summary
names the damaged file, ``mine submit`` and ``mine status`` exit 1, and the manifest
holds a ``stitch`` row with the error; once the part is recomputed, the next stitch
succeeds and removes that row.
"""

from __future__ import annotations

import pyarrow.parquet as pq
import pytest
from _reliability_b import ANSI, TINY, TINY_WINDOWS, status, submit

pytestmark = pytest.mark.slow  # three `mine submit` runs on local Rays

SEQ = "dataset=synthetic/sequence=0000"


def test_a_failed_stitch_is_a_manifest_row_that_status_shows(tmp_path):
    out = tmp_path / "cat"
    rc, stdout, stderr = submit(out, *TINY, logs=tmp_path / "logs1")
    assert rc == 0, stdout + stderr
    part = out / "_parts" / "tubes" / SEQ / f"{TINY_WINDOWS[1]}.part"
    data = bytearray(part.read_bytes())
    data[-4:] = b"XXXX"  # Parquet's closing magic: an unreadable file of the same size
    part.write_bytes(bytes(data))
    (out / "catalog" / "_sequences" / "dataset=synthetic" / "sequence=0000.json").unlink()

    rc, stdout, stderr = submit(out, *TINY, logs=tmp_path / "logs2")
    assert rc == 1, stdout + stderr
    failed = [ln for ln in stdout.splitlines() if ln.startswith("FAILED")]
    assert len(failed) == 1 and failed[0].startswith("FAILED synthetic/0000 (stitching): finalize step raised "
                                                     f"InputError: file {part}: cannot read Parquet file"), stdout
    assert ANSI not in stdout + stderr and "ray::" not in stdout + stderr
    rc, shown = status(out)
    assert rc == 1, shown
    assert "2 windows: 2 done, 0 failed, 0 pending" in shown and "0 stitched, 1 failed to stitch" in shown, shown
    assert f"failed   synthetic/0000 stitching  attempts 1  finalize step raised InputError: file {part}" in shown
    row = pq.read_table(out / "manifest" / SEQ / "stitch.parquet").to_pylist()[0]
    assert (row["window"], row["status"], row["core_start"], row["core_end"]) == ("stitch", "failed", 0, 12)
    assert row["error"].startswith(f"finalize step raised InputError: file {part}") and ANSI not in row["error"]

    # Repaired: the damaged part removed, its window runs again, the stitch succeeds and its row goes.
    part.unlink()
    rc, stdout, stderr = submit(out, *TINY, logs=tmp_path / "logs3")
    assert rc == 0, stdout + stderr
    assert not (out / "manifest" / SEQ / "stitch.parquet").exists()
    rc, shown = status(out)
    assert rc == 0 and "1 stitched, 0 failed to stitch" in shown, shown
