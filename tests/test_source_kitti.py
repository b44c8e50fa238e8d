"""KITTI tracking source on the real sequence 0005 and on broken copies of it."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from mining.errors import InputError
from mining.formats.kitti_calib import read_tracking_calib
from mining.sources import open_source
from mining.sources.kitti import KittiTrackingSource


@pytest.fixture(scope="module")
def source(kitti_tracking_root: Path) -> KittiTrackingSource:
    return open_source("kitti", str(kitti_tracking_root))


def test_plan_0005(source: KittiTrackingSource) -> None:
    assert isinstance(source, KittiTrackingSource) and source.dataset == "kitti"
    assert source.sequences() == [f"{i:04d}" for i in range(21)]
    plan = source.plan("0005")
    assert plan.frames == tuple(range(16))
    assert (plan.calib.width, plan.calib.height) == (1242, 375)
    assert plan.calib.fx == pytest.approx(721.5377)
    assert plan.calib.baseline_m == pytest.approx(0.5327, abs=5e-4)
    assert set(np.diff(plan.t_ns)) == {100_000_000}
    assert plan.t_ns[0] == 0 and plan.duration_s == pytest.approx(1.5)


def test_split_folder_as_root(kitti_tracking_root: Path) -> None:
    plan = KittiTrackingSource(kitti_tracking_root / "training").plan("0005")
    assert len(plan) == 16


def test_both_calibration_dialects_give_the_same_numbers(kitti_tracking_root: Path) -> None:
    calib_dir = kitti_tracking_root / "training" / "calib"
    # Make sure both dialects are really exercised: 0005 official, 0000–0013 object-detection.
    assert "R_rect " in (calib_dir / "0005.txt").read_text()
    official = read_tracking_calib(calib_dir / "0005.txt")
    for seq in [f"{i:04d}" for i in range(14) if i != 5]:
        assert "R0_rect:" in (calib_dir / f"{seq}.txt").read_text()
        other = read_tracking_calib(calib_dir / f"{seq}.txt")
        for key in ("P0", "P1", "P2", "P3", "R_rect", "Tr_velo_cam", "Tr_imu_velo"):
            np.testing.assert_array_equal(getattr(other, key), getattr(official, key), err_msg=f"{seq} {key}")


def test_calib_without_images_uses_recording_day(source: KittiTrackingSource) -> None:
    c14 = source.calib("0014")
    assert c14.fx == pytest.approx(707.0493)
    assert (c14.width, c14.height) == (1224, 370)
    c20 = source.calib("0020")
    assert (c20.width, c20.height) == (1241, 376)
    assert source.calib("0005") == source.plan("0005").calib  # from the PNG header here
    with pytest.raises(InputError, match="image folder is missing"):
        source.plan("0014")


def test_label_points_project_the_same_in_both_frames(source: KittiTrackingSource, kitti_tracking_root: Path) -> None:
    # KITTI labels are in rectified camera 0; shifting them into the image_02 frame and
    # projecting with StereoCalib must equal projecting with P2.
    kc = source.kitti_calib("0005")
    calib = source.calib("0005")
    rows = [r.split() for r in (kitti_tracking_root / "training/label_02/0005.txt").read_text().splitlines()]
    X = np.array([[float(v) for v in r[13:16]] for r in rows if r[2] == "Car"])
    assert len(X) > 10
    uvw = np.c_[X, np.ones(len(X))] @ kc.P2.T
    np.testing.assert_allclose(calib.project(kc.rect0_to_cam2(X)), uvw[:, :2] / uvw[:, 2:], atol=1e-6)
    assert np.linalg.norm(kc.t_cam2) == pytest.approx(0.06, abs=0.005)  # image_02 ~6 cm right of camera 0


def test_cam2_to_rect0_undoes_rect0_to_cam2_and_poses_move_with_the_rig(source: KittiTrackingSource) -> None:
    kc = source.kitti_calib("0005")
    X = np.array([[1.0, 2.0, 30.0], [-4.0, 1.5, 12.0]])
    np.testing.assert_allclose(kc.cam2_to_rect0(kc.rect0_to_cam2(X)), X, atol=1e-12)
    # camera 0 driving 1 m forward and turning: camera 2 makes the same motion about its own centre
    pose0 = np.eye(4)
    c, s = np.cos(0.1), np.sin(0.1)
    pose0[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    pose0[:3, 3] = [0.0, 0.0, 1.0]
    poses = kc.camera2_poses(np.stack([np.eye(4), pose0]))
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-12)
    centre2 = poses[1] @ np.r_[0.0, 0.0, 0.0, 1.0]  # camera 2's centre, in camera 2's first frame
    expected = kc.T_cam2_rect0 @ pose0 @ np.r_[-kc.t_cam2, 1.0]
    np.testing.assert_allclose(centre2, expected, atol=1e-12)


def test_read_frames_lazily_in_rgb(source: KittiTrackingSource, kitti_tracking_root: Path) -> None:
    plan = source.plan("0005")
    frames = source.read(plan, 3, 6)
    assert isinstance(frames, Iterator)
    got = list(frames)
    assert [f.index for f in got] == [3, 4, 5]
    assert [f.t_ns for f in got] == [300_000_000, 400_000_000, 500_000_000]
    for f in got:
        assert f.left.dtype == np.uint8 and f.left.shape == (375, 1242, 3) and f.right.shape == (375, 1242, 3)
        assert not np.array_equal(f.left, f.right)
        assert f.calib == plan.calib and f.dataset == "kitti" and f.sequence == "0005"
    bgr = cv2.imread(str(kitti_tracking_root / "training/image_02/0005/000004.png"), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(got[1].left, bgr[:, :, ::-1])
    assert not np.array_equal(got[1].left, bgr)  # the test would not notice a missing swap otherwise


# -- bad input, on copies of real files -------------------------------------------------


def _layout(tmp: Path, real: Path, frames: range = range(3), calib_seq: str = "0005") -> Path:
    """tmp/training/{calib/0005.txt, image_02/0005/*, image_03/0005/*} from real files."""
    split = tmp / "training"
    (split / "calib").mkdir(parents=True)
    shutil.copy(real / "training/calib" / f"{calib_seq}.txt", split / "calib/0005.txt")
    for cam in ("image_02", "image_03"):
        (split / cam / "0005").mkdir(parents=True)
        for i in frames:
            shutil.copy(real / "training" / cam / "0005" / f"{i:06d}.png", split / cam / "0005" / f"{i:06d}.png")
    return split


def _resize(path: Path, size: tuple[int, int]) -> None:
    cv2.imwrite(str(path), cv2.resize(cv2.imread(str(path)), size, interpolation=cv2.INTER_AREA))


def test_missing_right_image(tmp_path: Path, kitti_tracking_root: Path) -> None:
    split = _layout(tmp_path, kitti_tracking_root)
    (split / "image_03/0005/000001.png").unlink()
    with pytest.raises(InputError) as e:
        KittiTrackingSource(tmp_path).plan("0005")
    assert "image_03/0005/000001.png" in str(e.value) and "frame 1" in str(e.value)


def test_hole_in_frame_numbering(tmp_path: Path, kitti_tracking_root: Path) -> None:
    split = _layout(tmp_path, kitti_tracking_root, range(4))
    for cam in ("image_02", "image_03"):
        (split / cam / "0005/000002.png").unlink()
    with pytest.raises(InputError) as e:
        KittiTrackingSource(tmp_path).plan("0005")
    assert "000002.png" in str(e.value) and "frame 2" in str(e.value)


def test_truncated_png_fails_on_read(tmp_path: Path, kitti_tracking_root: Path) -> None:
    split = _layout(tmp_path, kitti_tracking_root)
    path = split / "image_02/0005/000002.png"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    src = KittiTrackingSource(tmp_path)
    plan = src.plan("0005")  # the plan reads the listing and one header only
    assert src.read_frame(plan, 1).index == 1
    with pytest.raises(InputError) as e:
        src.read_frame(plan, 2)
    assert "image_02/0005/000002.png" in str(e.value) and "frame 2" in str(e.value) and "truncated" in str(e.value)


def test_image_size_contradicting_calibration(tmp_path: Path, kitti_tracking_root: Path) -> None:
    split = _layout(tmp_path, kitti_tracking_root)
    for cam in ("image_02", "image_03"):
        _resize(split / cam / "0005/000001.png", (1224, 370))
    src = KittiTrackingSource(tmp_path)
    plan = src.plan("0005")
    with pytest.raises(InputError) as e:
        src.read_frame(plan, 1)
    msg = str(e.value)
    assert "000001.png" in msg and "frame 1" in msg and "1224×370" in msg and "1242×375" in msg


def test_left_and_right_sizes_differ(tmp_path: Path, kitti_tracking_root: Path) -> None:
    split = _layout(tmp_path, kitti_tracking_root)
    _resize(split / "image_03/0005/000000.png", (1240, 375))
    src = KittiTrackingSource(tmp_path)
    with pytest.raises(InputError) as e:
        src.read_frame(src.plan("0005"), 0)
    assert "000000.png" in str(e.value) and "frame 0" in str(e.value) and "1240×375" in str(e.value)


def test_calibration_of_another_recording_day(tmp_path: Path, kitti_tracking_root: Path) -> None:
    # 0014's calibration (a 1224×370 day) paired with 1242×375 images of 0005.
    _layout(tmp_path, kitti_tracking_root, calib_seq="0014")
    with pytest.raises(InputError) as e:
        KittiTrackingSource(tmp_path).plan("0005")
    assert "000000.png" in str(e.value) and "frame 0" in str(e.value) and "1224×370" in str(e.value)


def test_missing_calibration(tmp_path: Path, kitti_tracking_root: Path) -> None:
    split = _layout(tmp_path, kitti_tracking_root)
    (split / "calib/0005.txt").unlink()
    (split / "calib/0004.txt").write_text("")  # keeps calib/ so the split is recognised
    src = KittiTrackingSource(tmp_path)
    with pytest.raises(InputError) as e:
        src.plan("0005")
    assert "calib/0005.txt" in str(e.value) and "missing" in str(e.value)
    with pytest.raises(InputError, match="'P0' is missing"):
        src.plan("0004")


def test_calibration_value_not_a_number(tmp_path: Path, kitti_tracking_root: Path) -> None:
    split = _layout(tmp_path, kitti_tracking_root)
    path = split / "calib/0005.txt"
    path.write_text(path.read_text().replace("7.215377000000e+02", "7.21x", 1))
    with pytest.raises(InputError) as e:
        KittiTrackingSource(tmp_path).plan("0005")
    assert "0005.txt" in str(e.value) and "line 1" in str(e.value)


def test_sequence_names_with_both_splits(tmp_path: Path, kitti_tracking_root: Path) -> None:
    _layout(tmp_path, kitti_tracking_root, range(2))
    (tmp_path / "testing/calib").mkdir(parents=True)
    shutil.copy(kitti_tracking_root / "training/calib/0014.txt", tmp_path / "testing/calib/0014.txt")
    src = KittiTrackingSource(tmp_path)
    assert src.sequences() == ["training_0005", "testing_0014"]  # one path component each (mining/names.py)
    assert src.plan("training_0005").frames == src.plan("0005").frames == (0, 1)
    assert src.calib("testing_0014").width == 1224


def test_camera_pair_selects_the_projection_matrices(kitti_tracking_root: Path) -> None:
    grey = KittiTrackingSource(kitti_tracking_root, camera_pair=("image_00", "image_01")).calib("0005")
    assert grey.baseline_m == pytest.approx(0.5372, abs=5e-4)  # P0/P1, SOURCES.md §1.7
    assert (grey.width, grey.height) == (1242, 375)  # no grey images here: the day table
    with pytest.raises(InputError, match="not positive"):
        KittiTrackingSource(kitti_tracking_root, camera_pair=("image_03", "image_02")).plan("0005")
    with pytest.raises(InputError, match="camera_pair"):
        KittiTrackingSource(kitti_tracking_root, camera_pair=("left", "right"))
