"""A full disk is one clear line, and nothing already written is lost (issue 19, the disk-full case).

The adversarial run left 8 KB free on the disk of ``--out``: ``mine submit`` died with a raw
traceback (``OSError: [Errno 28]`` writing ``job.json``), exit status 1. Now every write
under ``--out`` that fails raises ``safe_files.WriteError``: ``mine: error: file
OUT/job.json: cannot be written: no space left on device (free some space and run the
command again)``, exit status 2; the temporary file is removed and the file it would have
replaced (an earlier job.json, a part, a compacted file) is untouched.

The disk is a real small tmpfs mounted for the test (root only; elsewhere those tests skip,
saying so). The same path is exercised without root by a file-size limit
(``RLIMIT_FSIZE``), under which a write fails with EFBIG ("file too large") instead.
"""

from __future__ import annotations

import os
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from mining.catalog.safe_files import WriteError
from _reliability_c import CLI_SMALL, REPO, copy_of, mine, tables

pytest_plugins = ["_reliability_c_fixtures"]  # base_catalogue: the small job over frames 0:16, mined once

TINY = ["--dataset", "synthetic", "--sequences", "0000", "--option", "n_frames=8", "--option", "width=621",
        "--option", "height=188", "--workers", "1", "--no-progress"]


@pytest.fixture
def small_disk(tmp_path):
    """A 4 MB tmpfs of this test's own."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    try:
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(mnt)], capture_output=True,
                              text=True, timeout=30)
        why = done.stderr.strip() if done.returncode else ""
    except FileNotFoundError:
        why = "no mount command"
    if why:
        pytest.skip(f"a small tmpfs cannot be mounted here ({why}; it needs root): the file-size-limit test covers "
                    "a failing write without it")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True, timeout=30)


def fill(disk: Path, free: int) -> Path:
    """Fill ``disk`` until the system says it is full, then free ``free`` bytes of it."""
    filler = disk / "filler"
    with open(filler, "wb", buffering=0) as f:
        try:
            while True:
                f.write(b"\0" * 65536)
        except OSError as e:
            assert e.errno == 28, e
    os.truncate(filler, filler.stat().st_size - free)
    return filler


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO), "RAY_USAGE_STATS_ENABLED": "0"}


def _files(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*"))
            if p.is_file() and p.name != ".mine.lock"}


@pytest.mark.slow  # a `mine submit` process (it fails before Ray starts)
def test_mine_submit_with_8_kb_free_says_no_space_left_in_one_line(small_disk):
    out = small_disk / "out"
    fill(small_disk, 8 * 1024)
    done = subprocess.run([sys.executable, "-m", "mining.cli", "submit", *TINY, "--out", str(out)], cwd=REPO,
                          env=_env(), capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stdout + done.stderr
    err = done.stderr.strip().splitlines()
    assert err == [f"mine: error: file {out}/job.json: cannot be written: no space left on device (free some space "
                   "and run the command again)"], done.stderr
    assert sorted(p.name for p in out.iterdir()) == [".mine.lock"], "no job.json, no temporary file left behind"


def test_a_full_disk_while_rewriting_job_json_keeps_the_old_one(base_catalogue, small_disk):
    """``--extend`` rewrites job.json: on a full disk it fails naming the file, and the
    catalogue (job.json included) is as it was, byte for byte."""
    out = copy_of(base_catalogue, small_disk / "out")
    before = _files(out)
    fill(small_disk, 8 * 1024)
    with pytest.raises(WriteError) as e:
        mine(out, (0, 24), mode="extend")
    assert str(e.value) == (f"file {out}/job.json: cannot be written: no space left on device (free some space and "
                            "run the command again)")
    assert _files(out) == before


@pytest.mark.slow  # mines (and fails) a window
def test_a_full_disk_while_writing_a_window_fails_naming_the_file_and_keeps_the_catalogue(base_catalogue, small_disk):
    """A window whose parts are gone is recomputed on resubmission; with 40 KB free its
    observation cache does not fit. The failure names the file and the reason, and the
    catalogue's tables and job.json are unchanged."""
    out = copy_of(base_catalogue, small_disk / "out")
    for table in ("tubes", "tube_frames", "frames"):
        (out / "_parts" / table / "dataset=synthetic" / "sequence=0000" / "0000-0000008-0000016.part").unlink()
    before_tables, job = tables(out), (out / "job.json").read_bytes()
    fill(small_disk, 40 * 1024)
    try:
        s = mine(out)
        said = "\n".join(s.lines())
        assert s.failed, said
    except WriteError as e:  # the driver's own write hit the full disk first
        said = str(e)
    assert "cannot be written: no space left on device" in said and f"file {out}/" in said, said
    assert "Traceback" not in said
    (small_disk / "filler").unlink()
    assert tables(out) == before_tables and (out / "job.json").read_bytes() == job


def _limit_file_size(limit: int):
    def preexec() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return preexec


@pytest.mark.slow  # a `mine submit` process (it fails before Ray starts)
def test_mine_submit_under_a_file_size_limit_says_file_too_large_in_one_line(tmp_path):
    """No root needed: RLIMIT_FSIZE of 8 KB, job.json (≈ 17 KB) does not fit (EFBIG; Python
    ignores SIGXFSZ, so the write returns the error)."""
    out = tmp_path / "out"
    done = subprocess.run([sys.executable, "-m", "mining.cli", "submit", *TINY, "--out", str(out)], cwd=REPO,
                          env=_env(), capture_output=True, text=True, timeout=300, preexec_fn=_limit_file_size(8192))
    assert done.returncode == 2, done.stdout + done.stderr
    err = done.stderr.strip().splitlines()
    assert err == [f"mine: error: file {out}/job.json: cannot be written: file too large (the file exceeds the size "
                   "limit of this process or filesystem)"], done.stderr
    assert sorted(p.name for p in out.iterdir()) == [".mine.lock"]


@pytest.mark.slow  # a `mine submit` process (it fails before Ray starts)
def test_an_existing_job_json_survives_a_failed_rewrite_under_a_file_size_limit(base_catalogue, tmp_path):
    out = copy_of(base_catalogue, tmp_path / "out")
    before = _files(out)
    done = subprocess.run([sys.executable, "-m", "mining.cli", "submit", *CLI_SMALL, "--frames", "0:24", "--extend",
                           "--out", str(out), "--workers", "1", "--no-progress"], cwd=REPO, env=_env(),
                          capture_output=True, text=True, timeout=300, preexec_fn=_limit_file_size(8192))
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr.strip().splitlines() == [f"mine: error: file {out}/job.json: cannot be written: file too large "
                                                "(the file exceeds the size limit of this process or filesystem)"]
    assert _files(out) == before
    shutil.rmtree(out)
