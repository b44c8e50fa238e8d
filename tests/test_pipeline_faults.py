"""Resume and faults of ``mine submit`` on a real local Ray (issue 4, item 4).

Every job here runs the real command line in its own session (``start_new_session``),
so the test can kill its driver, its Ray processes or one worker, and can always clean
up every process that session started, and only those (other Ray jobs may share the
machine). Jobs are small (30 frames, three 10-frame windows) to keep the file fast.

* a finished job resubmitted does no work and changes no file;
* a driver killed mid-job: the resubmission runs only the windows not done, and the
  catalogue equals a clean run's; ``mine status`` lists the pending windows meanwhile;
* a driver killed once its window's row is written, before it took the result: the resubmission
  sweeps the cache it left when it stitches, and ``mine status`` says nothing is left;
* a worker process killed mid-job: Ray restarts it, the job completes, no tube missing
  or duplicated;
* a truncated PNG in real KITTI frames fails only its window, named with the file and
  frame; repaired and resubmitted, only that window runs.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from mining.catalog.views import connect
from _run import JOB_TIMEOUT_S, SUMMARY, Mine, status, submit

pytestmark = pytest.mark.slow  # `mine submit` processes on local Rays, killed and resumed

pytest.importorskip("ray")

N_FRAMES = 30
WINDOWS = ["0000-0000000-0000010", "0000-0000010-0000020", "0000-0000020-0000030"]
SMALL_WINDOWS = ["--set", "window.core=10", "--set", "window.context_before=5", "--set", "window.context_after=5"]
SYNTHETIC = ["--dataset", "synthetic", "--sequences", "0000", "--option", f"n_frames={N_FRAMES}",
             "--option", "width=621", "--option", "height=188", *SMALL_WINDOWS]


# -- processes ------------------------------------------------------------------------

def summary(stdout: str) -> dict[str, int]:
    m = SUMMARY.search(stdout)
    assert m, f"no summary line in: {stdout}"
    return dict(zip(("ok", "failed", "skipped", "windows"), map(int, m.groups())))


def manifests(out: Path) -> dict[str, Path]:
    """Finished manifest rows: window → file (temporary names start with '.')."""
    return {p.stem: p for p in out.glob("manifest/*/*/*.parquet") if not p.name.startswith(".")}


def wait_for_first_manifest(job: Mine, out: Path, marker: Path) -> set[str]:
    deadline = time.monotonic() + JOB_TIMEOUT_S
    while not manifests(out):
        assert job.proc.poll() is None, "the job ended before any window was done"
        assert time.monotonic() < deadline, "no window done in time"
        time.sleep(0.05)
    assert not marker.exists(), "the job finished before the test could interrupt it"
    return set(manifests(out))


def snapshot(out: Path) -> dict[str, tuple[str, int, int]]:
    """Every file under ``out``: relative path → (content hash, size, mtime in ns)."""
    import hashlib

    return {str(p.relative_to(out)): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_size,
                                      p.stat().st_mtime_ns)
            for p in sorted(out.rglob("*")) if p.is_file() and p.name != ".mine.lock"}  # the writer's lock, not the catalogue


def catalogue(out: Path) -> dict:
    con = connect(out)
    try:
        q = lambda sql: con.sql(sql).fetchall()  # noqa: E731
        return {"tubes": sorted(r[0] for r in q("SELECT tube_id FROM tubes")),
                "selected": sorted(r[0] for r in q("SELECT tube_id FROM tubes WHERE selected")),
                "tube_frames": q("SELECT count(*) FROM tube_frames")[0][0],
                "duplicates": q("SELECT count(*) FROM (SELECT tube_id, frame FROM tube_frames "
                                "GROUP BY ALL HAVING count(*) > 1)")[0][0],
                "frames": [r[0] for r in q("SELECT frame FROM frames ORDER BY frame")],
                "windows": dict(q('SELECT "window", status FROM windows')),
                "tube_frame_frames": {r[0] for r in q("SELECT DISTINCT frame FROM tube_frames")}}
    finally:
        con.close()


def assert_same_catalogue(got: dict, want: dict) -> None:
    assert got["duplicates"] == 0, "a (tube_id, frame) appears twice in tube_frames"
    for k in ("tubes", "selected"):
        g, w = set(got[k]), set(want[k])
        assert got[k] == want[k], f"{k} differ from the clean run: only here {sorted(g - w)}, only there {sorted(w - g)}"
    assert got["tube_frames"] == want["tube_frames"]
    assert got["frames"] == want["frames"] == list(range(N_FRAMES))
    assert got["windows"] == want["windows"] == {w: "done" for w in WINDOWS}


# -- shared runs ----------------------------------------------------------------------

@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> tuple[Path, dict]:
    """The synthetic job run once, uninterrupted."""
    base = tmp_path_factory.mktemp("clean")
    rc, out, err = submit(base / "out", *SYNTHETIC, logs=base)
    assert rc == 0, out + err
    assert summary(out) == {"ok": 3, "failed": 0, "skipped": 0, "windows": 3}
    cat = catalogue(base / "out")
    assert cat["tubes"] and cat["selected"], "the clean run found no tubes: the comparisons would be empty"
    return base / "out", cat


@pytest.fixture(scope="module")
def interrupted(tmp_path_factory) -> tuple[Path, set[str]]:
    """The synthetic job with its driver and all its Ray processes SIGKILLed once a window is done."""
    base = tmp_path_factory.mktemp("interrupted")
    out = base / "out"
    job = Mine(out, *SYNTHETIC, logs=base)
    try:
        done_before = wait_for_first_manifest(job, out, out / "catalog/_sequences/dataset=synthetic/sequence=0000.json")
        os.killpg(job.proc.pid, signal.SIGKILL)  # the driver's group: driver, GCS, raylet
    finally:
        job.kill()  # and the workers, which Ray puts in process groups of their own
    assert not job.running(), "Ray processes of the killed job are left running"
    assert not (out / "catalog/_sequences").exists(), "the killed job had finished"
    assert set(manifests(out)) >= done_before
    return out, set(manifests(out))


# -- the tests ------------------------------------------------------------------------

def test_resubmitting_a_finished_job_does_nothing(clean, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(clean[0], out)
    before = snapshot(out)
    time.sleep(0.01)  # a rewrite would get a later mtime
    rc, stdout, err = submit(out, *SYNTHETIC, logs=tmp_path)
    assert rc == 0, stdout + err
    assert summary(stdout) == {"ok": 0, "failed": 0, "skipped": 3, "windows": 3}
    # Said as such, not as "0 selected … 0.00 frames/s", which read as a job that found nothing.
    assert "nothing left to mine: an earlier run did every window" in stdout, stdout
    assert "0 selected" not in stdout and "frames/s" not in stdout
    after = snapshot(out)
    assert after == before, f"changed: {sorted(k for k in after.keys() | before.keys() if after.get(k) != before.get(k))}"


def test_status_lists_pending_windows_of_an_interrupted_job(interrupted, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(interrupted[0], out)
    rc, text = status(out)
    assert rc == 0, text  # nothing failed
    done = interrupted[1]
    pending = [w for w in WINDOWS if w not in done]
    assert pending, "every window was done before the kill"
    assert f"3 windows: {len(done)} done, 0 failed, {len(pending)} pending" in text, text
    listed = re.findall(r"^pending\s+synthetic/(\S+)", text, re.M)
    assert listed == pending, text


def test_interrupted_job_resumes_only_what_is_left(clean, interrupted, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(interrupted[0], out)
    done_before = interrupted[1]
    rows_before = {w: p.read_bytes() for w, p in manifests(out).items()}
    mtimes_before = {w: p.stat().st_mtime_ns for w, p in manifests(out).items()}
    rc, stdout, err = submit(out, *SYNTHETIC, logs=tmp_path)
    assert rc == 0, stdout + err
    s = summary(stdout)
    assert s["skipped"] >= len(done_before) and s["ok"] == 3 - s["skipped"] and s["failed"] == 0, stdout
    for w in done_before:  # windows done before the kill were not run again
        p = manifests(out)[w]
        assert p.read_bytes() == rows_before[w] and p.stat().st_mtime_ns == mtimes_before[w], w
    assert_same_catalogue(catalogue(out), clean[1])
    assert status(out)[1].splitlines()[0].endswith("3 windows: 3 done, 0 failed, 0 pending")


ONE_WINDOW = SYNTHETIC[:-len(SMALL_WINDOWS)] + [
    "--set", f"window.core={N_FRAMES}", "--set", "window.context_before=0", "--set", "window.context_after=0"]
ONE = "0000-0000000-0000030"


def _tracking(out: Path) -> bool:
    """Whether the driver has handed the window's track step to a worker (its running marker)."""
    import json

    marker = out / "_running" / "dataset=synthetic" / "sequence=0000" / f"{ONE}.json"
    try:
        return json.loads(marker.read_text())["step"] == "track"
    except (OSError, ValueError, KeyError):
        return False


def test_a_resumed_job_leaves_no_cache_and_status_says_nothing_is_left(tmp_path):
    """Issue 40: a driver killed at the first manifest row, before it took the result, leaves the
    window's observation cache (4.5 MB stayed); the resubmission only stitches (the window is
    done), so no track removes it: stitching sweeps it, and `mine status` says nothing is left.
    The driver is stopped (SIGSTOP) while the worker tracks, so it never takes the result."""
    out = tmp_path / "out"
    job = Mine(out, *ONE_WINDOW, logs=tmp_path / "killed")
    try:
        deadline = time.monotonic() + JOB_TIMEOUT_S
        while not _tracking(out):
            assert job.proc.poll() is None and time.monotonic() < deadline, "the job never tracked"
            time.sleep(0.05)
        time.sleep(0.2)  # the marker is written just before the step is handed over
        assert not manifests(out), "the window was tracked before the driver could be stopped"
        os.kill(job.proc.pid, signal.SIGSTOP)  # the driver alone: the worker goes on and writes the row
        wait_for_first_manifest(job, out, out / "catalog/_sequences/dataset=synthetic/sequence=0000.json")
        os.killpg(job.proc.pid, signal.SIGKILL)
    finally:
        job.kill()
    assert list((out / "_cache").rglob("*.npz.zst")), "the killed job left no cache: nothing to sweep"
    rc, stdout, err = submit(out, *ONE_WINDOW, logs=tmp_path / "resumed")
    assert rc == 0, stdout + err
    assert summary(stdout) == {"ok": 0, "failed": 0, "skipped": 1, "windows": 1}, stdout
    left = [p for p in (out / "_cache").rglob("*") if not p.is_dir()]
    assert not left, f"the resumed job left {left}"
    rc, text = status(out)
    assert rc == 0, text
    assert [ln for ln in text.splitlines() if ln.startswith("left over: nothing")], text


def test_killed_worker_is_retried_and_the_catalogue_is_complete(clean, tmp_path):
    out = tmp_path / "out"
    job = Mine(out, *SYNTHETIC, logs=tmp_path)
    try:
        wait_for_first_manifest(job, out, out / "catalog/_sequences/dataset=synthetic/sequence=0000.json")
        workers = {pid: a for pid, a in job.running().items() if a.startswith("ray::Worker")}
        busy = [pid for pid, a in workers.items() if a.startswith("ray::Worker.run")]
        assert busy, f"no worker actor busy after the first window: {workers}"
        os.kill(busy[0], signal.SIGKILL)
        # The killed actor's call cannot finish until Ray restarts the actor in a new process.
        restarted = set()
        while not restarted and job.proc.poll() is None:
            restarted = {p for p, a in job.running().items() if a.startswith("ray::Worker")} - set(workers)
            time.sleep(0.05)
        assert restarted, "the job ended without restarting the killed worker"
        rc, stdout, err = job.finish()
    finally:
        job.kill()
    assert rc == 0, stdout + err
    assert summary(stdout) == {"ok": 3, "failed": 0, "skipped": 0, "windows": 3}, stdout
    assert_same_catalogue(catalogue(out), clean[1])


# -- bad input: real KITTI frames with one truncated PNG -----------------------------

KITTI_FRAMES = 16  # all the real 0005 frames there are (SOURCES.md)
KITTI_CORE, KITTI_CONTEXT = 6, 3
CORES = [(0, 6), (6, 12), (12, 16)]
KITTI_WINDOWS = [f"0005-{a:07d}-{b:07d}" for a, b in CORES]
BAD_FRAME = 8
BAD_WINDOW = KITTI_WINDOWS[1]  # core [6, 12) holds frame 8


def _kitti_copy(src: Path, dst: Path) -> Path:
    """The first KITTI_FRAMES stereo pairs and the calibration of 0005, in the tracking layout."""
    for cam in ("image_02", "image_03"):
        (dst / "training" / cam / "0005").mkdir(parents=True)
        for i in range(KITTI_FRAMES):
            shutil.copyfile(src / "training" / cam / "0005" / f"{i:06d}.png", dst / "training" / cam / "0005" / f"{i:06d}.png")
    (dst / "training" / "calib").mkdir()
    shutil.copyfile(src / "training" / "calib" / "0005.txt", dst / "training" / "calib" / "0005.txt")
    return dst


def test_truncated_frame_fails_only_its_window(kitti_tracking_root, tmp_path):
    root = _kitti_copy(kitti_tracking_root, tmp_path / "kitti")
    bad = root / "training" / "image_02" / "0005" / f"{BAD_FRAME:06d}.png"
    good = bad.read_bytes()
    bad.write_bytes(good[: len(good) // 2])  # a PNG cut off mid-stream: the header still reads
    out = tmp_path / "out"
    args = ["--dataset", "kitti", "--root", str(root), "--sequences", "0005", "--set", 'proposals.proposer="stereo"',
            "--set", f"window.core={KITTI_CORE}", "--set", f"window.context_before={KITTI_CONTEXT}",
            "--set", f"window.context_after={KITTI_CONTEXT}"]

    rc, stdout, err = submit(out, *args, logs=tmp_path / "run1")
    assert rc != 0, stdout + err
    assert summary(stdout) == {"ok": 2, "failed": 1, "skipped": 0, "windows": 3}, stdout
    failed = [line for line in stdout.splitlines() if line.startswith("FAILED")]
    assert len(failed) == 1 and failed[0].startswith(f"FAILED {BAD_WINDOW}:"), stdout
    assert str(bad) in failed[0] and f"frame {BAD_FRAME}" in failed[0], failed[0]

    rc, text = status(out)
    assert rc != 0, text
    assert "3 windows: 2 done, 1 failed, 0 pending" in text, text
    line = next(ln for ln in text.splitlines() if BAD_WINDOW in ln)
    assert line.startswith("failed") and str(bad) in line and f"frame {BAD_FRAME}" in line, text

    cat = catalogue(out)
    assert cat["windows"] == {KITTI_WINDOWS[0]: "done", BAD_WINDOW: "failed", KITTI_WINDOWS[2]: "done"}
    assert cat["duplicates"] == 0
    seen = cat["tube_frame_frames"]
    assert seen & set(range(*CORES[0])) and seen & set(range(*CORES[2])), "tubes of the windows that worked are missing"
    assert not seen & set(range(*CORES[1])), "tube frames in the failed window's core"
    assert cat["frames"] == list(range(*CORES[0])) + list(range(*CORES[2]))

    bad.write_bytes(good)  # repaired: resubmitting runs the failed window, and re-tracks its
    # neighbours, which were tracked without its frames in their context
    rc, stdout, err = submit(out, *args, logs=tmp_path / "run2")
    assert rc == 0, stdout + err
    assert summary(stdout) == {"ok": 3, "failed": 0, "skipped": 0, "windows": 3}, stdout
    rows = {r["window"]: r for r in pq.read_table(out / "catalog" / "windows").to_pylist()}
    assert {w: r["attempts"] for w, r in rows.items()} == {w: 2 for w in KITTI_WINDOWS}
    assert all(r["context_complete"] for r in rows.values())
    rc, text = status(out)
    assert rc == 0 and "3 windows: 3 done, 0 failed, 0 pending" in text, text
    cat = catalogue(out)
    assert cat["windows"] == {w: "done" for w in KITTI_WINDOWS}
    assert cat["tube_frame_frames"] & set(range(*CORES[1])), "no tubes in the repaired window"
    assert cat["frames"] == list(range(KITTI_FRAMES)) and cat["duplicates"] == 0
