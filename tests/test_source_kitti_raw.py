"""KITTI raw source on the real drive 2011_09_26_drive_0001 and on broken copies of it."""

from __future__ import annotations

import shutil
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest

from mining.errors import InputError
from mining.sources import open_source
from mining.sources.kitti_raw import KittiRawSource, lidar_depth_image, parse_timestamp_ns

DRIVE = "2011_09_26_drive_0001_sync"


@pytest.fixture(scope="module")
def source(kitti_raw_root: Path) -> KittiRawSource:
    return open_source("kitti-raw", str(kitti_raw_root))


def test_plan_has_real_timestamps(source: KittiRawSource, kitti_raw_root: Path) -> None:
    assert source.dataset == "kitti-raw" and source.sequences() == [DRIVE]
    plan = source.plan(DRIVE)
    assert plan.frames == tuple(range(6))  # timestamps.txt lists 108 frames; 6 have images
    first = (kitti_raw_root / "2011_09_26" / DRIVE / "image_02/timestamps.txt").read_text().splitlines()[0]
    assert first == "2011-09-26 13:02:25.961661696"
    whole_s = int(datetime(2011, 9, 26, 13, 2, 25, tzinfo=timezone.utc).timestamp())
    assert plan.t_ns[0] == whole_s * 10**9 + 961_661_696  # all nine digits kept
    dt = np.diff(plan.t_ns) / 1e9
    assert np.all((dt > 0.095) & (dt < 0.11))
    assert (plan.calib.width, plan.calib.height) == (1242, 375)
    assert plan.calib.baseline_m == pytest.approx(0.5327, abs=5e-4)
    # The same plan from a date folder as root and from the date/drive name form.
    assert KittiRawSource(kitti_raw_root / "2011_09_26").plan(DRIVE).t_ns == plan.t_ns
    assert source.plan(f"2011_09_26/{DRIVE}").frames == plan.frames


def test_calibration_matches_tracking_day(source: KittiRawSource, kitti_tracking_root: Path) -> None:
    tracking = open_source("kitti", str(kitti_tracking_root)).kitti_calib("0005")
    raw = source.kitti_calib(DRIVE)
    np.testing.assert_allclose(raw.P2, tracking.P2, rtol=1e-6)
    np.testing.assert_allclose(raw.P3, tracking.P3, rtol=1e-6)
    np.testing.assert_allclose(source.velo_to_cam(DRIVE), tracking.T_rect0_velo, atol=1e-6)


def test_read_frames(source: KittiRawSource) -> None:
    frames = list(source.read(DRIVE, 4))
    assert [f.index for f in frames] == [4, 5]
    plan = source.plan(DRIVE)
    assert [f.t_ns for f in frames] == list(plan.t_ns[4:])
    for f in frames:
        assert f.left.shape == (375, 1242, 3) and f.left.dtype == np.uint8 and not np.array_equal(f.left, f.right)


def test_velodyne_and_lidar_depth(source: KittiRawSource) -> None:
    scan = source.velodyne(DRIVE, 0)
    assert scan.dtype == np.float32 and scan.shape[1] == 4 and 121_000 <= len(scan) <= 122_000
    depth = source.lidar_depth(DRIVE, 0)
    assert depth.shape == (375, 1242) and depth.dtype == np.float32
    valid = np.isfinite(depth)
    assert 17_000 < valid.sum() < 21_000  # SOURCES.md §2: about 19k points project into image_02
    assert 4.0 < depth[valid].min() < 6.0 and 70.0 < depth[valid].max() < 85.0
    # Each pixel keeps its nearest point: adding every point again 1.5× further along its
    # image_02 viewing ray (same pixel, larger depth) must leave the image unchanged.
    kc = source.kitti_calib(DRIVE)
    T = kc.T_cam2_rect0 @ kc.T_rect0_velo
    X = np.c_[scan[:, :3], np.ones(len(scan))] @ T.T
    X[:, :3] *= 1.5
    far = np.c_[(X @ np.linalg.inv(T).T)[:, :3], scan[:, 3]]
    both = lidar_depth_image(np.r_[far, scan], kc, 1242, 375)
    np.testing.assert_allclose(both[valid], depth[valid], rtol=1e-6)
    assert np.isfinite(both).sum() == valid.sum()
    # Points behind the camera are dropped, not mirrored into the image.
    behind = scan[scan[:, 0] < -2.0]
    assert len(behind) > 1000 and not np.isfinite(lidar_depth_image(behind, kc, 1242, 375)).any()


def test_oxts_poses(source: KittiRawSource) -> None:
    packets = source.oxts(DRIVE)
    assert sorted(packets) == [0, 1, 2, 3, 4] and len(packets[0]) == 30
    frames, poses = source.oxts_poses(DRIVE)
    assert frames == (0, 1, 2, 3, 4) and poses.shape == (5, 4, 4)
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-9)
    for P in poses:
        np.testing.assert_allclose(P[:3, :3] @ P[:3, :3].T, np.eye(3), atol=1e-9)
    t = poses[:, :3, 3]
    assert t[-1, 2] > 4.0 and np.all(np.abs(t[:, :2]) < 0.2)  # forward along camera z, no side step
    plan = source.plan(DRIVE)
    for i in range(1, 5):
        dt = (plan.t_ns[i] - plan.t_ns[i - 1]) / 1e9
        speed_step = 0.5 * (packets[i].vf + packets[i - 1].vf) * dt
        assert np.linalg.norm(t[i] - t[i - 1]) == pytest.approx(speed_step, rel=0.10)


def test_parse_timestamp() -> None:
    assert parse_timestamp_ns("1970-01-01 00:00:01.000000001") == 1_000_000_001
    assert parse_timestamp_ns("1970-01-01 00:00:00.5") == 500_000_000
    assert parse_timestamp_ns("1970-01-01 00:00:00.1234567890") is None
    assert parse_timestamp_ns("not a time") is None


# -- bad input, on copies of real files -------------------------------------------------


def _layout(tmp: Path, real: Path, frames: range = range(3)) -> Path:
    """tmp/2011_09_26/{calib_*.txt, DRIVE/image_0[23]/{data/*.png,timestamps.txt}}."""
    src_date, date = real / "2011_09_26", tmp / "2011_09_26"
    date.mkdir()
    for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt"):
        shutil.copy(src_date / name, date / name)
    for cam in ("image_02", "image_03"):
        (date / DRIVE / cam / "data").mkdir(parents=True)
        shutil.copy(src_date / DRIVE / cam / "timestamps.txt", date / DRIVE / cam / "timestamps.txt")
        for i in frames:
            name = f"{i:010d}.png"
            shutil.copy(src_date / DRIVE / cam / "data" / name, date / DRIVE / cam / "data" / name)
    return date / DRIVE


def test_non_monotonic_timestamps(tmp_path: Path, kitti_raw_root: Path) -> None:
    drive = _layout(tmp_path, kitti_raw_root)
    path = drive / "image_02/timestamps.txt"
    lines = path.read_text().splitlines()
    lines[1], lines[2] = lines[2], lines[1]
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError) as e:
        KittiRawSource(tmp_path).plan(DRIVE)
    assert "image_02/timestamps.txt" in str(e.value) and "frame 2" in str(e.value)


def test_timestamps_shorter_than_frames(tmp_path: Path, kitti_raw_root: Path) -> None:
    drive = _layout(tmp_path, kitti_raw_root)
    path = drive / "image_02/timestamps.txt"
    path.write_text("\n".join(path.read_text().splitlines()[:2]) + "\n")
    with pytest.raises(InputError) as e:
        KittiRawSource(tmp_path).plan(DRIVE)
    assert "timestamps.txt" in str(e.value) and "frame 2" in str(e.value)


def test_missing_calibration_file(tmp_path: Path, kitti_raw_root: Path) -> None:
    drive = _layout(tmp_path, kitti_raw_root)
    (drive.parent / "calib_velo_to_cam.txt").unlink()
    with pytest.raises(InputError) as e:
        KittiRawSource(tmp_path).plan(DRIVE)
    assert "calib_velo_to_cam.txt" in str(e.value) and "missing" in str(e.value)


def test_missing_right_image(tmp_path: Path, kitti_raw_root: Path) -> None:
    drive = _layout(tmp_path, kitti_raw_root)
    (drive / "image_03/data/0000000002.png").unlink()
    with pytest.raises(InputError) as e:
        KittiRawSource(tmp_path).plan(DRIVE)
    assert "image_03/data/0000000002.png" in str(e.value) and "frame 2" in str(e.value)


def test_truncated_png_fails_on_read(tmp_path: Path, kitti_raw_root: Path) -> None:
    drive = _layout(tmp_path, kitti_raw_root)
    path = drive / "image_03/data/0000000001.png"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    src = KittiRawSource(tmp_path)
    plan = src.plan(DRIVE)
    with pytest.raises(InputError) as e:
        src.read_frame(plan, 1)
    assert "image_03/data/0000000001.png" in str(e.value) and "frame 1" in str(e.value)


def test_image_size_contradicting_calibration(tmp_path: Path, kitti_raw_root: Path) -> None:
    import cv2

    drive = _layout(tmp_path, kitti_raw_root)
    for cam in ("image_02", "image_03"):
        path = drive / cam / "data/0000000000.png"
        cv2.imwrite(str(path), cv2.resize(cv2.imread(str(path)), (1224, 370), interpolation=cv2.INTER_AREA))
    with pytest.raises(InputError) as e:
        KittiRawSource(tmp_path).plan(DRIVE)
    msg = str(e.value)
    assert "0000000000.png" in msg and "frame 0" in msg and "1224×370" in msg and "1242×375" in msg


def test_velodyne_size_not_a_multiple_of_16(tmp_path: Path, kitti_raw_root: Path) -> None:
    drive = _layout(tmp_path, kitti_raw_root)
    (drive / "velodyne_points/data").mkdir(parents=True)
    real = kitti_raw_root / "2011_09_26" / DRIVE / "velodyne_points/data/0000000003.bin"
    (drive / "velodyne_points/data/0000000003.bin").write_bytes(real.read_bytes()[:-4])
    with pytest.raises(InputError) as e:
        KittiRawSource(tmp_path).velodyne(DRIVE, 3)
    assert "0000000003.bin" in str(e.value) and "frame 3" in str(e.value)
