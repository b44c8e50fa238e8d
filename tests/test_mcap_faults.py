"""Faults of an MCAP recording fail only what they touch, and say where (issues 11 and 19).

A corrupt MCAP chunk fails only the frames in it, naming the chunk (issue 19, item 5).
Before, one chunk with bad bytes failed the whole recording at planning ("cannot read
messages (corrupt chunk?)"), naming no chunk, time or frame. Now ``plan`` reads the file
chunk by chunk: the unreadable chunk is named (byte offset, log-time range), its frames keep
their place (their log times come from the message index records beside the chunk) and fail
on read, and every other frame reads back bit-exact. The recordings are real MCAP files
written by the mcap ROS 2 writer from real KITTI 0005 frames (one image per chunk: a
1.4 MB rgb8 image overflows the writer's 1 MB chunk size), with bytes zeroed in the middle
of one chunk.

Duplicate MCAP stamps are an error or an explicit gap, never a silent drop (issue 11, item 7):
a ROS 2 recording written from real KITTI 0005 frames where frame 2 repeats frame 1's header
stamp on both cameras. Before, pairing kept one of the two and dropped the other without a word.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from conftest import kitti_0005_stereo
from mining.errors import InputError
from mining.sources import open_source
from mining.sources.mcap import McapSource
from mining.testing.fixtures import write_stereo_mcap

N = 6
T0 = 1_700_000_000_000_000_000
PERIOD = 100_000_000
DELAY = 3_000_000  # the fixture's log time − header stamp
STAMPS = [T0, T0 + PERIOD, T0 + PERIOD, T0 + 3 * PERIOD]  # frame 2 repeats frame 1's stamp


@pytest.fixture(scope="module")
def kitti(kitti_tracking_root):
    return kitti_0005_stereo(kitti_tracking_root, N)


def _chunks(path):
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return make_reader(f).get_summary().chunk_indexes


def _corrupt_chunk_of(path, log_time: int, topic_id: int | None = None, index_too: bool = False):
    """Zero 64 bytes in the middle of the chunk holding the message logged at ``log_time``
    (on channel ``topic_id`` when given); with ``index_too`` also its message index records.
    Returns the chunk's index record."""
    hits = [c for c in _chunks(path) if c.message_start_time <= log_time <= c.message_end_time
            and (topic_id is None or topic_id in c.message_index_offsets)]
    chunk = max(hits, key=lambda c: c.chunk_length)
    data = bytearray(path.read_bytes())
    mid = chunk.chunk_start_offset + chunk.chunk_length // 2
    data[mid : mid + 64] = bytes(64)
    if index_too:
        for offset in chunk.message_index_offsets.values():
            data[offset : offset + 9] = b"\xff" * 9  # an unknown opcode with an absurd length
    path.write_bytes(bytes(data))
    return chunk


def _channel_id(path, topic: str) -> int:
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return next(c.id for c in make_reader(f).get_summary().channels.values() if c.topic == topic)


def _named(chunk) -> str:
    return f"byte offset {chunk.chunk_start_offset} (log times {chunk.message_start_time}–{chunk.message_end_time} ns)"


@pytest.mark.parametrize("side", ["left", "right"])
def test_a_corrupt_chunk_fails_only_its_frame(kitti, tmp_path, side):
    left, right, calib = kitti
    path = tmp_path / "rec.mcap"
    topics = write_stereo_mcap(path, left, right, calib, t0_ns=T0)
    assert len(_chunks(path)) >= 2 * N  # several chunks: one image each
    chunk = _corrupt_chunk_of(path, T0 + 3 * PERIOD + DELAY, _channel_id(path, topics[side]))
    src = McapSource(path)
    plan = src.plan("rec")  # before: InputError "cannot read messages (corrupt chunk?)"
    # Every frame keeps its place and its stamp (the bad one's estimated from its log time).
    assert plan.frames == tuple(range(N)) and plan.gaps == () and plan.problems == ()
    assert plan.t_ns == tuple(T0 + i * PERIOD for i in range(N))
    # The plan's source names the bad range: offset, log times, the frame in it.
    [bad] = src.damaged("rec")
    assert (bad["offset"], bad["start_ns"], bad["end_ns"]) == (
        chunk.chunk_start_offset, chunk.message_start_time, chunk.message_end_time)
    assert bad["frames"] == [3] and bad["messages_known"] and _named(chunk) in bad["message"]
    assert src.pairing("rec")["corrupt_chunks"] == 1
    for pos in (0, 2, 4, 5):  # frames in good chunks read back bit-exact
        f = src.read_frame(plan, pos)
        assert np.array_equal(f.left, left[pos]) and np.array_equal(f.right, right[pos])
    with pytest.raises(InputError) as err:
        src.read_frame(plan, 3)
    msg = str(err.value)
    assert msg.startswith(f"file {path}, frame 3: corrupt MCAP chunk at {_named(chunk)}"), msg
    assert f"this frame's {side} image" in msg
    # A range that avoids the frame plans and reads; one that holds it fails on read only.
    assert [f.index for f in src.read(plan, 0, 3)] == [0, 1, 2]
    with pytest.raises(InputError, match=re.escape(_named(chunk))):
        list(src.read(plan, 2, 5))


def test_time_source_log_names_the_chunk_on_read(kitti, tmp_path):
    left, right, calib = kitti
    path = tmp_path / "log.mcap"
    topics = write_stereo_mcap(path, left, right, calib, t0_ns=T0)
    chunk = _corrupt_chunk_of(path, T0 + 2 * PERIOD + DELAY, _channel_id(path, topics["left"]))
    src = McapSource(path, time_source="log")
    plan = src.plan("log")  # from the message indexes: the chunk is not opened at planning
    assert plan.frames == tuple(range(N))
    assert np.array_equal(src.read_frame(plan, 1).left, left[1])
    with pytest.raises(InputError, match=re.escape(f"frame 2: corrupt MCAP chunk at {_named(chunk)}")):
        src.read_frame(plan, 2)


def test_a_chunk_corrupted_after_planning_is_named_on_read(kitti, tmp_path):
    left, right, calib = kitti
    path = tmp_path / "late.mcap"
    topics = write_stereo_mcap(path, left, right, calib, t0_ns=T0)
    src = McapSource(path)
    plan = src.plan("late")
    chunk = _corrupt_chunk_of(path, T0 + 4 * PERIOD + DELAY, _channel_id(path, topics["right"]))
    with pytest.raises(InputError, match=re.escape(f"frame 4: corrupt MCAP chunk at {_named(chunk)}")):
        src.read_frame(plan, 4)
    assert np.array_equal(src.read_frame(plan, 5).right, right[5])


def test_a_chunk_whose_message_indexes_are_lost_too_is_a_named_gap(kitti, tmp_path):
    left, right, calib = kitti
    path = tmp_path / "lost.mcap"
    topics = write_stereo_mcap(path, left, right, calib, t0_ns=T0)
    chunk = _corrupt_chunk_of(path, T0 + 3 * PERIOD + DELAY, _channel_id(path, topics["left"]), index_too=True)
    src = McapSource(path)
    plan = src.plan("lost")
    # Its messages are unknown: frame 3 cannot be placed, so it is a recording gap (the
    # right image of frame 3 found no partner; frame indices count the left messages known),
    # and the chunk is still named.
    assert plan.frames == (0, 1, 2, 3, 4) and plan.gaps == (3,)
    assert plan.t_ns == tuple(T0 + i * PERIOD for i in (0, 1, 2, 4, 5))
    [bad] = src.damaged("lost")
    assert bad["offset"] == chunk.chunk_start_offset and not bad["messages_known"] and bad["frames"] == []
    assert src.pairing("lost")["unpaired_right"] == 1
    assert np.array_equal(src.read_frame(plan, 3).left, left[4])


def test_a_corrupt_chunk_holding_the_first_camera_info_is_skipped(kitti, tmp_path):
    left, right, calib = kitti
    path = tmp_path / "info.mcap"
    topics = write_stereo_mcap(path, left, right, calib, t0_ns=T0)
    # Frame 0's left chunk holds the first left CameraInfo too: the next one is used.
    _corrupt_chunk_of(path, T0 + DELAY, _channel_id(path, topics["left"]))
    src = McapSource(path)
    plan = src.plan("info")
    assert plan.calib.fx == pytest.approx(calib.fx) and plan.frames == tuple(range(N))
    with pytest.raises(InputError, match="frame 0: corrupt MCAP chunk"):
        src.read_frame(plan, 0)


def _recording_with_a_bad_chunk(kitti, tmp_path: Path):
    """A source folder holding ``rec.mcap`` with frame 3's left chunk corrupted: (folder, that chunk)."""
    left, right, calib = kitti
    root = tmp_path / "mcap"
    root.mkdir()
    path = root / "rec.mcap"
    topics = write_stereo_mcap(path, left, right, calib, t0_ns=T0)
    return root, _corrupt_chunk_of(path, T0 + 3 * PERIOD + DELAY, _channel_id(path, topics["left"]))


def _mined_frames(out: Path) -> list[int]:
    from mining.catalog.views import connect

    con = connect(str(out))
    try:
        return sorted(f for (f,) in con.sql("SELECT frame FROM frames WHERE sequence = 'rec'").fetchall())
    finally:
        con.close()


@pytest.mark.slow  # a whole job, in this process (~12 s on two cores)
def test_a_job_mines_the_good_windows_and_names_the_chunk_in_the_failed_one(kitti, tmp_path):
    from mining.config import load_config
    from mining.pipeline.executors import LocalExecutor
    from mining.pipeline.submit import mine_job

    root, chunk = _recording_with_a_bad_chunk(kitti, tmp_path)
    cfg = load_config(overrides=['source.dataset="mcap"', f'source.root="{root}"', "window.core=2",
                                 "window.context_before=0", "window.context_after=0"])
    out = tmp_path / "out"
    summary = mine_job(cfg, str(out), ["rec"], (0, N), executor=LocalExecutor)
    assert (summary.windows, summary.ok, summary.unplanned) == (3, 2, {}), summary.lines()
    [(window, error)] = summary.failed.items()
    assert window == "rec-0000002-0000004" and _named(chunk) in error and "frame 3" in error, error
    assert _mined_frames(out) == [0, 1, 4, 5]


@pytest.mark.slow  # `mine submit` on a local Ray
def test_submit_exits_1_mines_the_good_windows_and_names_the_chunk(kitti, tmp_path):
    from _run import submit

    root, chunk = _recording_with_a_bad_chunk(kitti, tmp_path)
    out = tmp_path / "out"
    rc, stdout, stderr = submit(out, "--dataset", "mcap", "--root", str(root), "--sequences", "rec", "--frames", "0:6",
                                "--set", "window.core=2", "--set", "window.context_before=0",
                                "--set", "window.context_after=0", workers=1)
    assert rc == 1, (rc, stdout, stderr)
    assert "Traceback" not in stderr
    assert "windows: 2 ok, 1 failed, 0 already done (of 3)" in stdout, stdout
    assert _named(chunk) in stdout and "rec-0000002-0000004" in stdout, stdout
    assert _mined_frames(out) == [0, 1, 4, 5]


# -- duplicate stamps --------------------------------------------------------------------


@pytest.fixture(scope="module")
def recording(tmp_path_factory, kitti_tracking_root):
    left, right, calib = kitti_0005_stereo(kitti_tracking_root, len(STAMPS))
    root = tmp_path_factory.mktemp("mcap")
    topics = write_stereo_mcap(root / "dup.mcap", left, right, calib, t0_ns=T0, stamps_ns=STAMPS)
    return root, topics, left, right


def test_duplicate_stamps_are_an_error_naming_topic_and_stamp(recording):
    root, topics, _, _ = recording
    with pytest.raises(InputError) as e:
        open_source("mcap", str(root)).plan("dup")
    msg = str(e.value)
    assert str(root / "dup.mcap") in msg and topics["left"] in msg and f"stamp {T0 + PERIOD} ns" in msg
    assert "duplicate_stamps='gap'" in msg


def test_duplicate_stamps_as_gaps_are_explicit(recording):
    root, _, left, right = recording
    src = open_source("mcap", str(root), duplicate_stamps="gap")
    plan = src.plan("dup")
    assert plan.frames == (0, 1, 3) and plan.gaps == (2,)  # the repeat is a recording gap
    pairing = src.pairing("dup")
    assert (pairing["repeated_left"], pairing["repeated_right"], pairing["pairs"]) == (1, 1, 3)
    for pos, k in enumerate((0, 1, 3)):  # the first message of a stamp is the one kept
        f = src.read_frame(plan, pos)
        assert np.array_equal(f.left, left[k]) and np.array_equal(f.right, right[k])


def test_duplicate_stamps_option_is_checked(recording):
    from mining.errors import ConfigError

    root, _, _, _ = recording
    with pytest.raises(ConfigError, match="duplicate_stamps"):
        open_source("mcap", str(root), duplicate_stamps="drop")
