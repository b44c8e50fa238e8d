"""Stitching when something failed: around a failed window, and a stitch that fails.

* A window whose track step fails (e.g. its parts could not be written: a full disk) leaves
  its observation cache behind, so its neighbours' tubes run through its core frames as
  context. Its own frames rows are missing, so the stitch must leave those context rows
  out; before, ``stitch_sequence`` looked up their positions and raised ``KeyError``.
* A failed stitch is a row of the manifest that ``mine status`` shows (issue 11, item 6):
  a finished tiny job; then one window's tube part is damaged (its Parquet footer
  overwritten, the size unchanged) and the sequence's "stitched" marker removed, as a
  driver killed between tracking and stitching leaves it: the resubmission must stitch
  again, and that stitch fails. Before, the summary said ``system failure: ray::...``, no
  row recorded it, and ``mine status`` exited 0 over an empty catalogue. Now the summary
  names the damaged file, ``mine submit`` and ``mine status`` exit 1, and the manifest
  holds a ``stitch`` row with the error; once the part is recomputed, the next stitch
  succeeds and removes that row.
"""

from __future__ import annotations

import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from _jobs import TINY, TINY_WINDOWS
from _run import ANSI, status, submit
from _stitch_reference import reference_stitch

from mining.catalog.layout import part_path
from mining.catalog.store import Store
from mining.config import load_config
from mining.pipeline.executors import LocalExecutor
from mining.pipeline.stitch import stitch_sequence
from mining.pipeline.submit import mine_job
from mining.sources.synthetic import SyntheticSource
from mining.catalog.rows import RunInfo
from mining.types import plan_windows

from conftest import REPO

pytestmark = pytest.mark.slow  # a 24-frame job in this process; three `mine submit` runs on local Rays

SEQ = "dataset=synthetic/sequence=0000"


def test_the_stitch_leaves_out_a_failed_windows_core(tmp_path):
    cfg = load_config(REPO / "jobs" / "synthetic.toml", [
        "source.options.n_frames=24", "source.options.width=621", "source.options.height=188",
        "source.options.fx=360.77", "window.core=8", "window.context_before=4", "window.context_after=4"])
    out = tmp_path / "catalog"
    assert mine_job(cfg, str(out), ["0000"], executor=LocalExecutor).ok == 3
    plan = SyntheticSource(**cfg.source.options).plan("0000")
    windows = plan_windows(plan, 8, 4, 4)
    assert len(windows) == 3
    store = Store(str(out))
    parts = {t: [store.read_table(part_path(t, "synthetic", "0000", w.name)) for w in windows]
             for t in ("tubes", "tube_frames", "frames")}
    middle = windows[1]
    reach = [r["frame"] for k in (0, 2) for r in parts["tube_frames"][k].select(["frame"]).to_pylist()
             if middle.core[0] <= r["frame"] < middle.core[1]]
    assert reach, "no neighbour's tube runs into the middle core: nothing to test"

    # The middle window failed: only its neighbours' parts are stitched.
    kept = [windows[0], windows[2]]
    tables = {t: pa.concat_tables([parts[t][0], parts[t][2]]) for t in parts}
    result = stitch_sequence(kept, tables["tubes"], tables["tube_frames"], tables["frames"], cfg,
                             RunInfo("synthetic", "0000", "run", cfg.params_hash))
    frames = set(result["tube_frames"].column("frame").to_pylist())
    assert frames & set(range(*windows[0].core)) and frames & set(range(*windows[2].core))
    assert not frames & set(range(*middle.core)), "tube frames in the failed window's core"
    run = RunInfo("synthetic", "0000", "run", cfg.params_hash)
    for ws in (kept, windows):  # the streaming stitch writes what the batch stitch wrote (test_stitch_stream.py)
        t = {k: pa.concat_tables([parts[k][windows.index(w)] for w in ws]) for k in parts}
        ref = reference_stitch(ws, t["tubes"], t["tube_frames"], t["frames"], cfg, run)
        got = stitch_sequence(ws, t["tubes"], t["tube_frames"], t["frames"], cfg, run)
        assert all(ref[k].equals(got[k]) and ref[k].schema.equals(got[k].schema, check_metadata=True) for k in ref)


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


def test_a_part_of_another_schema_fails_the_stitch_alone_naming_the_file_and_the_column(base_catalogue, tmp_path,
                                                                                          capsys):
    """A window's tube_frames part whose ``frame`` column is int64 (another writer's, or planted;
    its integrity record made to match, so resume trusts it) and the sequence's marker gone:
    the resubmission stitches again, and that stitch fails. The summary counts the stitch apart
    from the windows (before: ``windows: 0 ok, 1 failed, 2 already done (of 2)``) and names the
    part file and the column (before: ``ArrowInvalid: Schema at index 1 was different``), as
    does ``mine status``."""
    from _jobs import copy_of, mine
    from _run import cli_status

    from mining.catalog.integrity import window_files
    from mining.catalog.layout import done_path
    from mining.catalog.records import JobRecord

    out = copy_of(base_catalogue, tmp_path / "cat")
    store = Store(str(out))
    window = JobRecord.load(store).windows[1]
    rel = part_path("tube_frames", window.dataset, window.sequence, window.name)
    part = pq.read_table(out / rel)
    i = part.schema.get_field_index("frame")
    pq.write_table(part.set_column(i, pa.field("frame", pa.int64(), False), part.column(i).cast(pa.int64())), out / rel)
    window_files(store, window).save(store)  # the record vouches for the new file: only the stitch can see it
    store.remove(done_path(window.dataset, window.sequence))

    s = mine(out)
    lines = s.lines()
    assert lines[0] == "windows: 0 ok, 0 failed, 2 already done (of 2); stitch: 1 failed", lines
    assert not s.failed and list(s.stitch_failed) == ["synthetic/0000"], lines
    failed = [ln for ln in lines if ln.startswith("FAILED")]
    assert len(failed) == 1 and failed[0].startswith(
        f"FAILED synthetic/0000 (stitching): finalize step raised InputError: file {store.full(rel)}: "), failed
    assert "column frame is int64 here, int32 there" in failed[0] and "ArrowInvalid" not in failed[0], failed

    rc, shown = cli_status(capsys, out)
    assert rc == 1, shown
    assert "2 windows: 2 done, 0 failed, 0 pending" in shown and "0 stitched, 1 failed to stitch" in shown, shown
    stitch = [ln for ln in shown.splitlines() if "stitching" in ln]
    assert len(stitch) == 1 and store.full(rel) in stitch[0] and "column frame is int64" in stitch[0], shown
