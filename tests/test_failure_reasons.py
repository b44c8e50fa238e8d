"""A failure says why, in one line, without Ray's noise (issue 11, item 6).

* A 0-byte RobotCar PNG is an InputError naming the file and the frame. Before,
  ``cv2.imdecode`` raised a bare ``cv2.error`` on the empty buffer, and the user saw
  ``system failure: ray::Worker.run() (pid=…)`` in terminal colours. Now the reader says
  what is wrong and where, the window fails alone, and the run summary, ``mine status``
  and the manifest's error column all say it in their first line.
* A bad ``geometry.stereo.num_disparities=95`` says why: the disparity stage raises
  ValueError on a search range that is not a multiple of 16. Before, the window's error was
  ``system failure: ray::Worker.run() (pid=…)`` in terminal colours, the reason 1.5 kB deep
  in the manifest. Now either the driver refuses the config before Ray starts (a
  preflight), or every window fails with the step, the exception type and the message in
  its first line — in the summary, in ``mine status`` and in the manifest's error column —
  and ``mine submit`` exits non-zero.
"""

from __future__ import annotations

from pathlib import Path

import pyarrow.parquet as pq
import pytest
from _jobs import TINY, TINY_WINDOWS
from _run import ANSI, status, submit
from conftest import kitti_0005_stereo

from mining.errors import InputError
from mining.sources.oxford import OxfordSource
from mining.testing.fixtures import write_robotcar_fixture

N_FRAMES = 6
EMPTY = 4  # the frame whose left image is emptied (not the first: planning reads that one's header)
WINDOWS = ["t-0000000-0000003", "t-0000003-0000006"]
REASON = "num_disparities must be a positive multiple of 16, got 95"


@pytest.fixture(scope="module")
def robotcar_empty_png(kitti_tracking_root, tmp_path_factory) -> tuple[Path, Path]:
    """A 6-frame RobotCar traversal of real KITTI frames whose frame 4 left PNG has 0 bytes."""
    left, right, calib = kitti_0005_stereo(kitti_tracking_root, N_FRAMES)
    root = tmp_path_factory.mktemp("robotcar_empty")
    trav = write_robotcar_fixture(root, left, right, calib, traversal="t")
    png = sorted((trav / "stereo" / "left").glob("*.png"))[EMPTY]
    png.write_bytes(b"")
    return root, png


def test_the_reader_names_the_empty_file_and_its_frame(robotcar_empty_png):
    root, png = robotcar_empty_png
    src = OxfordSource(root)
    plan = src.plan("t")
    src.read_frame(plan, EMPTY - 1)  # its neighbour reads
    with pytest.raises(InputError) as e:
        src.read_frame(plan, EMPTY)
    assert e.value.path == str(png) and e.value.frame == EMPTY
    assert "0 bytes" in str(e.value)


@pytest.mark.slow
def test_a_submit_reports_the_empty_png_in_the_summary_status_and_manifest(robotcar_empty_png, tmp_path):
    root, png = robotcar_empty_png
    out = tmp_path / "cat"
    rc, stdout, stderr = submit(out, "--dataset", "oxford", "--root", str(root), "--set", "window.core=3",
                                "--set", "window.context_before=1", "--set", "window.context_after=1",
                                logs=tmp_path / "logs")
    assert rc == 1, stdout + stderr
    why = f"file {png}, frame {EMPTY}: stereo image is empty (0 bytes)"
    failed = [ln for ln in stdout.splitlines() if ln.startswith("FAILED")]
    assert failed == [f"FAILED {WINDOWS[1]}: {why}: an incomplete download or copy"], stdout
    assert ANSI not in stdout + stderr and "ray::" not in stdout + stderr
    rc, shown = status(out)
    assert rc == 1
    assert f"failed   oxford/{WINDOWS[1]}  attempts 1  {why}" in shown, shown
    assert "1 done, 1 failed, 0 pending" in shown
    row = pq.read_table(out / "manifest" / "dataset=oxford" / "sequence=t" / f"{WINDOWS[1]}.parquet").to_pylist()[0]
    assert row["status"] == "failed" and row["error"].splitlines()[0].startswith(why)


@pytest.mark.slow  # a `mine submit` on a local Ray
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
