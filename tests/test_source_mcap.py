"""MCAP adapter on ROS 2 recordings written from real KITTI frames."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import kitti_0005_stereo
from mining.errors import InputError
from mining.sources import open_source
from mining.sources.mcap import McapSource, header_stamp_ns
from mining.testing.fixtures import write_stereo_mcap

N_FRAMES = 4
T0 = 1_700_000_000_123_456_789
HZ = 10.0
PERIOD = 100_000_000


@pytest.fixture(scope="module")
def kitti(kitti_tracking_root: Path):
    return kitti_0005_stereo(kitti_tracking_root, N_FRAMES)


@pytest.mark.parametrize("compressed", [False, True], ids=["rgb8", "png"])
def test_plan_and_read_back_bit_exact(kitti, tmp_path, compressed):
    left, right, calib = kitti
    path = tmp_path / "drive_a.mcap"
    topics = write_stereo_mcap(path, left, right, calib, t0_ns=T0, hz=HZ, compressed=compressed)
    src = open_source("mcap", str(tmp_path))
    assert isinstance(src, McapSource)
    assert src.sequences() == ["drive_a"]
    plan = src.plan("drive_a")
    assert plan.dataset == "mcap" and plan.frames == tuple(range(N_FRAMES)) and plan.gaps == ()
    # Header stamps, not the (3 ms later) log times.
    assert plan.t_ns == tuple(T0 + i * PERIOD for i in range(N_FRAMES))
    assert plan.calib.baseline_m == pytest.approx(0.5327, abs=1e-4)
    assert plan.calib.baseline_m == pytest.approx(calib.baseline_m, abs=1e-9)
    assert (plan.calib.fx, plan.calib.fy, plan.calib.cx, plan.calib.cy) == (calib.fx, calib.fy, calib.cx, calib.cy)
    assert (plan.calib.width, plan.calib.height) == (1242, 375)
    assert src.pairing("drive_a")["left_topic"] == topics["left"]
    assert src.pairing("drive_a")["right_info"] == topics["right_info"]
    for pos in (2, 0, 3):  # out of order: each read seeks by itself
        f = src.read_frame(plan, pos)
        assert f.index == pos and f.t_ns == plan.t_ns[pos]
        assert np.array_equal(f.left, left[pos]) and np.array_equal(f.right, right[pos])
    # A single file as the root works too.
    assert McapSource(path).sequences() == ["drive_a"]


@pytest.mark.parametrize("encoding", ["bgr8", "mono8", "bayer_rggb8", "bayer_gbrg8", "bayer_bggr8", "bayer_grbg8"])
def test_other_raw_encodings(kitti, tmp_path, encoding):
    left, right, calib = kitti
    write_stereo_mcap(tmp_path / "e.mcap", left[:1], right[:1], calib, encoding=encoding)
    src = McapSource(tmp_path / "e.mcap")
    f = src.read_frame(src.plan("e"), 0)
    if encoding == "bgr8":
        assert np.array_equal(f.left, left[0])
    elif encoding == "mono8":
        grey = cv2.cvtColor(left[0], cv2.COLOR_RGB2GRAY)
        assert np.array_equal(f.left, np.stack([grey] * 3, axis=-1))
    else:
        # Demosaicing loses detail but the right pattern keeps the colours (~29 dB);
        # a wrong pattern swaps or shifts them (< 21 dB, see the Oxford tests).
        err = np.mean((f.left[4:-4, 4:-4].astype(float) - left[0][4:-4, 4:-4]) ** 2)
        assert 10 * np.log10(255**2 / err) > 27.0


def test_pairing_with_offset_and_missing_partner(kitti, tmp_path):
    left, right, calib = kitti
    path = tmp_path / "offset.mcap"
    write_stereo_mcap(path, left, right, calib, t0_ns=T0, right_offset_ns=2_000_000, skip_right=(1,))
    src = McapSource(path)
    plan = src.plan("offset")
    # Right is 2 ms late: paired within the 5 ms default; frame 1 has no right image.
    assert plan.frames == (0, 2, 3) and plan.gaps == (1,)
    assert src.pairing("offset")["unpaired_left"] == 1 and src.pairing("offset")["unpaired_right"] == 0
    f = src.read_frame(plan, 1)
    assert f.index == 2 and np.array_equal(f.left, left[2]) and np.array_equal(f.right, right[2])
    # A tighter tolerance than the offset leaves nothing to pair.
    with pytest.raises(InputError, match="no left/right pair"):
        McapSource(path, max_pair_dt_ns=1_000_000).plan("offset")


def test_log_time_option_and_explicit_topics(kitti, tmp_path):
    left, right, calib = kitti
    path = tmp_path / "cams.mcap"
    topics = write_stereo_mcap(path, left[:2], right[:2], calib, t0_ns=T0, namespace="/cam_front")
    # "/cam_front/left/..." auto-detects; explicit topics give the same, log times are 3 ms later.
    src = McapSource(path, left_topic=topics["left"], right_topic=topics["right"], time_source="log")
    plan = src.plan("cams")
    assert plan.t_ns == (T0 + 3_000_000, T0 + 3_000_000 + PERIOD)
    assert np.array_equal(src.read_frame(plan, 1).right, right[1])
    with pytest.raises(InputError, match="/nope"):
        McapSource(path, left_topic="/nope").plan("cams")
    # Log-time planning reads the message indexes only; they agree with a full scan.
    from mcap.reader import make_reader

    from mining.sources.mcap import _log_times_from_index

    with open(path, "rb") as f:
        reader = make_reader(f)
        indexed = _log_times_from_index(f, reader.get_summary(), [topics["left"], topics["right"]])
        scanned = {topics["left"]: [], topics["right"]: []}
        for _, ch, m in reader.iter_messages(topics=list(scanned)):
            scanned[ch.topic].append((m.log_time, m.log_time))
    assert indexed == scanned and len(indexed[topics["left"]]) == 2


def test_header_stamp_reader_matches_decoder(kitti, tmp_path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    left, right, calib = kitti
    path = tmp_path / "s.mcap"
    write_stereo_mcap(path, left[:2], right[:2], calib, t0_ns=T0)
    with open(path, "rb") as f:
        for d in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            st = d.decoded_message.header.stamp
            assert header_stamp_ns(d.message.data) == st.sec * 1_000_000_000 + st.nanosec


# -- bad input ------------------------------------------------------------------------------


def test_truncated_file_fails_to_plan(kitti, tmp_path):
    left, right, calib = kitti
    path = tmp_path / "cut.mcap"
    write_stereo_mcap(path, left, right, calib)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    # Decision: without the footer and summary the file is refused (with a pointer to
    # `mcap recover`), rather than guessing which frames are intact.
    with pytest.raises(InputError, match="truncated") as err:
        McapSource(tmp_path).plan("cut")
    assert str(path) in str(err.value)


def test_file_truncated_after_planning_fails_on_read_naming_frame(kitti, tmp_path):
    left, right, calib = kitti
    path = tmp_path / "later.mcap"
    write_stereo_mcap(path, left, right, calib)
    src = McapSource(path)
    plan = src.plan("later")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError) as err:
        src.read_frame(plan, 3)
    assert str(path) in str(err.value) and "frame 3" in str(err.value)


def test_missing_camera_info(kitti, tmp_path):
    left, right, calib = kitti
    path = tmp_path / "noinfo.mcap"
    write_stereo_mcap(path, left[:2], right[:2], calib, with_camera_info=False)
    with pytest.raises(InputError, match="CameraInfo") as err:
        McapSource(path).plan("noinfo")
    assert str(path) in str(err.value)


def test_ambiguous_topics_need_explicit_choice(kitti, tmp_path):
    from mcap_ros2.writer import Writer

    from mining.testing.fixtures import IMAGE_MSGDEF, image_message

    left, _, _ = kitti
    path = tmp_path / "ambiguous.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        schema = w.register_msgdef("sensor_msgs/msg/Image", IMAGE_MSGDEF)
        for topic in ("/a/image", "/b/image"):
            w.write_message(topic, schema, image_message(left[0], T0, "x"), log_time=T0)
        w.finish()
    with pytest.raises(InputError, match="left_topic"):
        McapSource(path).plan("ambiguous")


def test_corrupt_chunk_is_named_by_file_and_frame(kitti, tmp_path):
    from mcap.reader import make_reader

    left, right, calib = kitti
    path = tmp_path / "flip.mcap"
    write_stereo_mcap(path, left, right, calib, t0_ns=T0)
    src = McapSource(path)
    plan = src.plan("flip")
    # Zero some bytes inside the chunk that holds frame 2's left image (log time = stamp + 3 ms).
    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    t2 = plan.t_ns[2] + 3_000_000
    chunk = max((c for c in chunks if c.message_start_time <= t2 <= c.message_end_time), key=lambda c: c.chunk_length)
    data = bytearray(path.read_bytes())
    mid = chunk.chunk_start_offset + chunk.chunk_length // 2
    data[mid : mid + 64] = bytes(64)
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match="frame 2") as err:
        src.read_frame(plan, 2)
    assert str(path) in str(err.value) and "corrupt" in str(err.value)
    assert np.array_equal(src.read_frame(plan, 3).left, left[3])  # other chunks are intact
    # Planned afresh, the file still plans (issue 19): the bad chunk's frame keeps its place
    # and fails on read, naming the chunk (tests/test_mcap_faults.py).
    fresh = McapSource(path)
    assert fresh.plan("flip").frames == plan.frames
    assert [d["offset"] for d in fresh.damaged("flip")] == [chunk.chunk_start_offset]
    with pytest.raises(InputError, match=f"byte offset {chunk.chunk_start_offset}"):
        fresh.read_frame(plan, 2)


def test_plan_survives_pickling(kitti, tmp_path):
    import pickle

    left, right, calib = kitti
    path = tmp_path / "p.mcap"
    write_stereo_mcap(path, left[:2], right[:2], calib)
    src = McapSource(tmp_path)
    plan = src.plan("p")
    worker = pickle.loads(pickle.dumps(src))  # as shipped to a Ray worker: the index travels
    assert np.array_equal(worker.read_frame(plan, 1).right, right[1])
    fresh = McapSource(tmp_path)  # a source that never planned re-indexes on first read
    assert np.array_equal(fresh.read_frame(plan, 0).left, left[0])
