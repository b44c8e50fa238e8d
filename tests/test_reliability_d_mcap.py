"""Duplicate MCAP stamps are an error or an explicit gap, never a silent drop (issue 11, item 7).

A ROS 2 recording written from real KITTI 0005 frames where frame 2 repeats frame 1's
header stamp on both cameras. Before, pairing kept one of the two and dropped the
other without a word."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import kitti_0005_stereo
from mining.errors import InputError
from mining.sources import open_source
from mining.testing.fixtures import write_stereo_mcap

T0 = 1_700_000_000_000_000_000
PERIOD = 100_000_000
STAMPS = [T0, T0 + PERIOD, T0 + PERIOD, T0 + 3 * PERIOD]  # frame 2 repeats frame 1's stamp


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
