"""Every file read for data is a regular file (issue 40, case 8): ``mining/files.py``.

The adversarial run put a FIFO at a frame's name in a proposals folder: the job hung until it
was killed (opening a FIFO waits for a writer), where every other non-file was refused at
once. Now every reader of a data file opens it without blocking and refuses anything but a
regular file, in one line naming the file and what it is: a FIFO proposals file fails its
window and the job completes the others; a FIFO image fails its frame; a FIFO config or
job.json is one line of ``mine submit``, ``mine query`` or ``mine status``.

Each test runs under a watchdog: should the code under test wait on a FIFO, the watchdog
opens the FIFO for writing and closes it (the waiting read ends) and the test fails, rather
than hanging the suite. Real files and FIFOs, the real pipeline, the real commands.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import socket
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from _jobs import SYNTHETIC, TINY_WINDOWS, tiny_cfg
from _run import cli, clean_error
from conftest import REPO
from mining.config import load_config
from mining.errors import InputError
from mining.files import open_regular, read_bytes, read_text
from mining.pipeline.executors import LocalExecutor
from mining.pipeline.submit import mine_job

HANG_S = 60  # far beyond any of these reads; a read that waits on a FIFO waits for ever


@contextlib.contextmanager
def no_hang(*fifos: Path) -> Iterator[None]:
    """Fail the test if the body still runs after HANG_S seconds; then, until it ends, keep
    opening each FIFO for writing and closing it, so a read waiting on one ends."""
    done, hung = threading.Event(), []

    def release() -> None:
        if done.wait(HANG_S):
            return
        hung.append(True)
        while not done.wait(0.2):
            for fifo in fifos:
                try:
                    os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
                except OSError as e:  # ENXIO: no reader waits on it right now
                    assert e.errno in (errno.ENXIO, errno.ENOENT), e

    watchdog = threading.Thread(target=release, daemon=True)
    watchdog.start()
    try:
        yield
    finally:
        done.set()
        watchdog.join()
    assert not hung, f"waited on a FIFO for more than {HANG_S} s"


def _fifo(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    os.mkfifo(path)
    return path


# -- the door ---------------------------------------------------------------------------------


def test_only_a_regular_file_opens(tmp_path):
    (tmp_path / "data.txt").write_bytes(b"a\r\nb\n")
    (tmp_path / "link").symlink_to(tmp_path / "data.txt")
    assert read_bytes(tmp_path / "link") == b"a\r\nb\n" and read_text(tmp_path / "data.txt") == "a\nb\n"
    with socket.socket(socket.AF_UNIX) as s:
        s.bind(str(tmp_path / "sock"))
        kinds = {_fifo(tmp_path / "fifo"): "a FIFO (named pipe)", tmp_path: "a directory",
                 Path("/dev/zero"): "a character device", tmp_path / "sock": "a socket"}
        with no_hang(tmp_path / "fifo"):
            for path, kind in kinds.items():
                with pytest.raises(InputError) as e:
                    open_regular(path, frame=3)
                assert str(e.value) == f"file {path}, frame 3: is {kind}, not a regular file; a data file must be one"
    with pytest.raises(FileNotFoundError):
        open_regular(tmp_path / "missing")


# -- a proposals file ---------------------------------------------------------------------------


def test_a_fifo_proposals_file_fails_its_window_and_the_job_completes_the_others(tmp_path):
    props = tmp_path / "props"
    props.mkdir()
    for frame in range(12):  # an empty list: a frame without proposals
        (props / f"{frame:06d}.json").write_text("[]")
    (props / "000001.json").unlink()
    fifo = _fifo(props / "000001.json")
    cfg = load_config(REPO / "jobs" / "synthetic.toml", [
        "source.options.n_frames=12", "source.options.width=320", "source.options.height=96",
        "source.options.fx=186.0", "window.core=6", "window.context_before=2", "window.context_after=2",
        'proposals.proposer="json"', f'proposals.json.folder="{props}"'])
    assert cfg.window == tiny_cfg().window, "the tiny job's windows"
    with no_hang(fifo):
        summary = mine_job(cfg, str(tmp_path / "out"), ["0000"], executor=LocalExecutor)
    assert summary.windows == 2 and summary.ok == 1, summary
    (window, why), = summary.failed.items()
    assert TINY_WINDOWS[0] in window, summary.failed
    assert str(fifo) in why and "FIFO" in why and "\n" not in why, why


# -- an image ---------------------------------------------------------------------------------


@pytest.mark.parametrize("dataset", ["kitti", "oxford"])
def test_a_fifo_image_fails_its_frame_naming_it(kitti_tracking_root, tmp_path, dataset):
    from _kitti_copy import kitti_copy
    from conftest import kitti_0005_stereo
    from mining.sources import open_source
    from mining.testing.fixtures import write_robotcar_fixture

    if dataset == "kitti":
        root = kitti_copy(tmp_path / "kitti", kitti_tracking_root, n_frames=4)
        sequence, image = "0005", root / "training" / "image_02" / "0005" / "000002.png"
    else:  # a RobotCar layout of the same frames: images named by their time
        root = tmp_path / "robotcar"
        write_robotcar_fixture(root, *kitti_0005_stereo(kitti_tracking_root, 4), traversal="t")
        sequence, image = "t", sorted((root / "t" / "stereo" / "left").glob("*.png"))[2]
    image.unlink()
    _fifo(image)
    source = open_source(dataset, str(root))
    plan = source.plan(sequence)
    with no_hang(image):
        assert source.read_frame(plan, 1).index == plan.frames[1]
        with pytest.raises(InputError) as e:
            source.read_frame(plan, 2)
    assert str(image) in str(e.value) and f"frame {plan.frames[2]}" in str(e.value) and "FIFO" in str(e.value)


# -- a config, a job.json -----------------------------------------------------------------------


def test_a_fifo_config_is_one_line(tmp_path, capsys):
    fifo = _fifo(tmp_path / "job.toml")
    with no_hang(fifo):
        rc, out, err = cli(capsys, "submit", "--config", str(fifo), *SYNTHETIC, "--out", str(tmp_path / "out"))
    line = clean_error(err)
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert str(fifo) in line and "FIFO" in line, line
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("command", [["status"], ["query", "SELECT count(*) FROM tubes"]], ids=["status", "query"])
def test_a_fifo_job_json_is_one_line(tmp_path, capsys, command):
    out = tmp_path / "out"
    fifo = _fifo(out / "job.json")
    with no_hang(fifo):
        rc, _, err = cli(capsys, *command, "--out", str(out))
    line = clean_error(err)
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert str(fifo) in line and "FIFO" in line, line
