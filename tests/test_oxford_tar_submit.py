"""``mine submit --dataset oxford`` on RobotCar as it is downloaded (issue 42, item 3): the tar
chunks, read in place on local disk and from a local S3-compatible server, mine the catalogue
of their extracted copy; a chunk missing for one camera fails the windows holding its frames,
named by chunk, and the job mines the others; a stride is reported."""

from __future__ import annotations

from pathlib import Path

import pyarrow.parquet as pq
import pytest
from _run import submit
from _s3 import s3_folder
from conftest import kitti_0005_stereo

from mining.config import load_config
from mining.pipeline.executors import LocalExecutor
from mining.pipeline.submit import mine_job
from mining.testing.fixtures import robotcar_as_downloaded, write_robotcar_fixture

N_FRAMES = 8  # KITTI 0005 frames 0-7, chunks of 2: chunk ids 1-4
TRAV = "t"
# 4-frame windows with a frame of context: tubes cross windows and are stitched
WINDOWS = ["--set", "window.core=4", "--set", "window.context_before=1", "--set", "window.context_after=1"]
# without context a window holds exactly the frames of two chunks (1-2, 3-4)
ALONE = ["--set", "window.context_before=0", "--set", "window.context_after=0"]
# Columns that say when and by which run a row was written, not what was mined.
RUN_COLUMNS = {"run_id", "written_at", "created_at", "mined_at"}


@pytest.fixture(scope="module")
def extracted(kitti_tracking_root, tmp_path_factory) -> Path:
    left, right, calib = kitti_0005_stereo(kitti_tracking_root, N_FRAMES)
    root = tmp_path_factory.mktemp("extracted")
    write_robotcar_fixture(root, left, right, calib, traversal=TRAV)
    return root


@pytest.fixture
def s3_chunks(extracted, tmp_path, monkeypatch):
    """(the local chunks, the URI of their copy on a local S3-compatible server)."""
    chunks = robotcar_as_downloaded(extracted, tmp_path / "chunks", TRAV)
    with s3_folder(chunks, monkeypatch) as uri:
        yield chunks, uri


def _table(out: Path, name: str) -> list[dict]:
    t = pq.read_table(out / "catalog" / name)
    rows = [{k: v for k, v in r.items() if k not in RUN_COLUMNS} for r in t.to_pylist()]
    return sorted(rows, key=repr)


def _proposals(shared_data: Path) -> list[str]:
    # The frame numbers are the timestamp lines, i.e. KITTI 0005's: its shared 4D-GVT proposals fit.
    folder = shared_data / "proposals_4dgvt_format" / "kitti_tracking_0005" / "top20"
    return ["--set", 'proposals.proposer="json"', "--set", f'proposals.json.folder="{folder}"']


def _mine(out: Path, root: str, shared_data: Path, *extra: str) -> tuple[int, str]:
    rc, stdout, stderr = submit(out, "--dataset", "oxford", "--root", root, *WINDOWS, *_proposals(shared_data),
                                *extra)
    return rc, stdout + stderr


@pytest.mark.slow  # three `mine submit`s on a local Ray
def test_chunks_local_and_on_s3_mine_the_catalogue_of_the_extracted_copy(extracted, tmp_path, s3_chunks,
                                                                        shared_data):
    chunks, uri = s3_chunks
    rc, shown = _mine(tmp_path / "extracted", str(extracted), shared_data)
    assert rc == 0, shown
    tubes = _table(tmp_path / "extracted", "tubes")
    assert tubes, "the extracted copy mines tubes"
    for name, root in (("chunks", str(chunks)), ("s3", uri)):
        out = tmp_path / f"out-{name}"  # never the chunks' own folder: that is the source's root
        rc, shown = _mine(out, root, shared_data)
        assert rc == 0, shown
        assert "windows: 2 ok, 0 failed" in shown, shown
        assert _table(out, "tubes") == tubes, name
        assert _table(out, "tube_frames") == _table(tmp_path / "extracted", "tube_frames"), name


@pytest.mark.slow  # a `mine submit` on a local Ray
def test_a_missing_chunk_fails_its_window_alone_named(extracted, tmp_path, shared_data):
    chunks = robotcar_as_downloaded(extracted, tmp_path / "chunks", TRAV)
    gone = chunks / f"{TRAV}_stereo_right_03.tar"  # frames 4 and 5
    gone.unlink()
    rc, shown = _mine(tmp_path / "out", str(chunks), shared_data, *ALONE)
    assert rc == 1, shown
    failed = [ln for ln in shown.splitlines() if ln.startswith("FAILED")]
    assert len(failed) == 1 and failed[0].startswith(f"FAILED {TRAV}-0000004-0000008: frame 4: chunk {gone}: missing"), shown
    assert "windows: 1 ok, 1 failed" in shown, shown
    frames = {r["frame"] for r in pq.read_table(tmp_path / "out" / "catalog" / "frames").to_pylist()}
    assert frames == {0, 1, 2, 3}  # the other window's frames are all written


def test_stride_is_reported_in_the_summary(extracted, tmp_path):
    chunks = robotcar_as_downloaded(extracted, tmp_path / "chunks", TRAV)
    cfg = load_config(None, ['source.dataset="oxford"', f'source.root="{chunks}"', "source.options.stride=4",
                             "window.core=2", "window.context_before=0", "window.context_after=0"])
    summary = mine_job(cfg, str(tmp_path / "out"), executor=LocalExecutor)
    assert not summary.failed and summary.ok == 1
    assert f"sequence {TRAV}: stride 4: 3 of every 4 frames skipped (6 of 8); 2 frames read" in summary.lines()
    frames = {r["frame"] for r in pq.read_table(tmp_path / "out" / "catalog" / "frames").to_pylist()}
    assert frames == {0, 4}
