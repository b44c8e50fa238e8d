"""RobotCar adapter on traversals built from real KITTI frames (Bayer GBRG + known distortion)."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import kitti_0005_stereo
from mining.errors import InputError
from mining.sources import open_source
from mining.sources.oxford import (
    BAYER_GBRG_TO_RGB,
    OxfordSource,
    load_camera_model,
    load_lut,
    stereo_calib,
)
from mining.testing.fixtures import bayer_mosaic, write_robotcar_fixture

N_FRAMES = 6
MARGIN = 20  # px left out at the borders, where interpolation sees the black outside


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    a = a[MARGIN:-MARGIN, MARGIN:-MARGIN].astype(np.float64)
    b = b[MARGIN:-MARGIN, MARGIN:-MARGIN].astype(np.float64)
    return float(10 * np.log10(255.0**2 / np.mean((a - b) ** 2)))


@pytest.fixture(scope="module")
def kitti(kitti_tracking_root: Path):
    return kitti_0005_stereo(kitti_tracking_root, N_FRAMES)


@pytest.fixture(scope="module")
def robotcar(kitti, tmp_path_factory) -> Path:
    """A 6-frame wide-pair traversal, chunks of 2 frames, all downloaded."""
    left, right, calib = kitti
    root = tmp_path_factory.mktemp("robotcar")
    write_robotcar_fixture(root, left, right, calib, traversal="2014-12-09-13-21-02")
    return root


@pytest.fixture
def robotcar_copy(robotcar: Path, tmp_path: Path) -> Path:
    root = tmp_path / "robotcar"
    shutil.copytree(robotcar, root)
    return root


def test_plan_reads_timestamps_and_calibration_from_files(robotcar, kitti):
    src = open_source("oxford", str(robotcar))
    assert isinstance(src, OxfordSource)
    assert src.sequences() == ["2014-12-09-13-21-02"]
    plan = src.plan("2014-12-09-13-21-02")
    calib = kitti[2]
    assert plan.dataset == "oxford" and plan.frames == tuple(range(N_FRAMES)) and plan.gaps == ()
    assert np.allclose(np.diff(plan.t_ns), 62_500_000)  # 16 Hz, µs → ns
    # The fixture models carry KITTI's 0.5327 m, not RobotCar's 0.24 m: read, not assumed.
    assert plan.calib.baseline_m == pytest.approx(0.5327, abs=1e-4)
    assert plan.calib.baseline_m == pytest.approx(calib.baseline_m, abs=1e-6)
    assert (plan.calib.fx, plan.calib.cx, plan.calib.cy) == pytest.approx((calib.fx, calib.cx, calib.cy), abs=1e-5)
    assert (plan.calib.width, plan.calib.height) == (1242, 375)


def test_demosaic_and_undistortion_recover_the_original_frames(robotcar, kitti):
    left, right, _ = kitti
    src = OxfordSource(robotcar)
    plan = src.plan("2014-12-09-13-21-02")
    frames = list(src.read(plan, 0, 3))
    assert [f.index for f in frames] == [0, 1, 2]
    for f in frames:
        assert f.left.shape == (375, 1242, 3) and f.left.dtype == np.uint8
        # Measured: 29.0–30.3 dB; demosaicing the undistorted original alone gives ~29.4 dB.
        assert _psnr(f.left, left[f.index]) > 27.0
        assert _psnr(f.right, right[f.index]) > 27.0

    # The same raw frame through each wrong Bayer code, or without the LUT, is clearly worse.
    raw_path = robotcar / plan.sequence / "stereo" / "left" / f"{plan.t_ns[0] // 1000}.png"
    raw = cv2.imread(str(raw_path), cv2.IMREAD_UNCHANGED)
    models = robotcar / "models"
    map_x, map_y = load_lut(models / "stereo_wide_left_distortion_lut.bin", 1242, 375)
    good = _psnr(frames[0].left, left[0])
    for code in (cv2.COLOR_BayerGB2RGB, cv2.COLOR_BayerRG2RGB, cv2.COLOR_BayerBG2RGB):
        assert code != BAYER_GBRG_TO_RGB
        wrong = cv2.remap(cv2.cvtColor(raw, code), map_x, map_y, cv2.INTER_LINEAR)
        assert _psnr(wrong, left[0]) < good - 5.0
    assert _psnr(cv2.cvtColor(raw, BAYER_GBRG_TO_RGB), left[0]) < good - 5.0
    swapped = cv2.remap(cv2.cvtColor(raw, BAYER_GBRG_TO_RGB), map_y * 1242 / 375, map_x * 375 / 1242, cv2.INTER_LINEAR)
    assert _psnr(swapped, left[0]) < good - 5.0


def test_mosaic_samples_gbrg_sites(kitti):
    rgb = kitti[0][0]
    raw = bayer_mosaic(rgb, "gbrg")
    assert np.array_equal(raw[0::2, 0::2], rgb[0::2, 0::2, 1])  # G
    assert np.array_equal(raw[0::2, 1::2], rgb[0::2, 1::2, 2])  # B
    assert np.array_equal(raw[1::2, 0::2], rgb[1::2, 0::2, 0])  # R
    assert np.array_equal(raw[1::2, 1::2], rgb[1::2, 1::2, 1])  # G


def test_real_sdk_models_wide_and_narrow_baselines(oxford_data):
    models = oxford_data / "sdk_models"
    wide = stereo_calib(load_camera_model(models, "stereo_wide_left"), load_camera_model(models, "stereo_wide_right"), 1280, 960)
    narrow = stereo_calib(
        load_camera_model(models, "stereo_narrow_left"), load_camera_model(models, "stereo_narrow_right"), 1280, 960
    )
    assert wide.baseline_m == pytest.approx(0.239983, abs=1e-6)
    assert narrow.baseline_m == pytest.approx(0.119997, abs=1e-6)
    assert (wide.fx, wide.cx, wide.cy) == pytest.approx((983.044006, 643.646973, 493.378998))
    assert (narrow.fx, narrow.cx, narrow.cy) == pytest.approx((964.828979, 643.788025, 484.407990))
    # Mixing cameras of different pairs is not a rectified pair.
    with pytest.raises(InputError, match="stereo_wide_right"):
        stereo_calib(load_camera_model(models, "stereo_narrow_left"), load_camera_model(models, "stereo_wide_right"), 1280, 960)


@pytest.mark.parametrize("pair,baseline,fx", [("wide", 0.239983, 983.044006), ("narrow", 0.119997, 964.828979)])
def test_real_models_without_lut_need_explicit_opt_in(oxford_data, kitti, tmp_path, pair, baseline, fx):
    left, right, calib = kitti
    write_robotcar_fixture(tmp_path, left[:2], right[:2], calib, traversal="t", pair=pair, write_lut=False)
    models = oxford_data / "sdk_models"
    # The shared models have no LUT: refuse by default, naming the missing file.
    with pytest.raises(InputError, match=f"stereo_{pair}_left_distortion_lut.bin"):
        OxfordSource(tmp_path, pair=pair, models_dir=models).plan("t")
    src = OxfordSource(tmp_path, pair=pair, models_dir=models, allow_missing_lut=True)
    plan = src.plan("t")
    assert plan.calib.baseline_m == pytest.approx(baseline, abs=1e-6)
    assert plan.calib.fx == pytest.approx(fx)
    assert (plan.calib.width, plan.calib.height) == (1242, 375)  # from the image, not the model
    frame = src.read_frame(plan, 1)
    assert _psnr(frame.left, left[1]) > 27.0  # demosaic only; no distortion was applied


@pytest.mark.parametrize("list_missing", [True, False])
def test_missing_chunk_is_a_gap(kitti, tmp_path, list_missing):
    left, right, calib = kitti
    write_robotcar_fixture(tmp_path, left, right, calib, traversal="t", missing_chunks=(2,), list_missing=list_missing)
    src = OxfordSource(tmp_path)
    plan = src.plan("t")
    # Chunk 2 held frames 2 and 3 (lines 2, 3 when listed); they are dropped, not an error.
    assert plan.frames == ((0, 1, 4, 5) if list_missing else (0, 1, 2, 3))
    assert plan.gaps == (2,)
    dt = np.diff(plan.t_ns)
    assert dt[1] == 3 * 62_500_000 and dt[0] == dt[2] == 62_500_000
    frame = src.read_frame(plan, 2)
    assert frame.t_ns == plan.t_ns[2]
    assert _psnr(frame.left, left[4]) > 27.0


def test_vo_relative_poses(robotcar):
    trav = robotcar / "2014-12-09-13-21-02"
    (trav / "vo").mkdir(exist_ok=True)
    t0, t1, t2 = 1_000_000, 1_062_500, 1_125_000
    # Hand-written rows: the vehicle moves 1 m forward (base x), then yaws 0.1 rad to the right (base z down).
    (trav / "vo" / "vo.csv").write_text(
        "source_timestamp,destination_timestamp,x,y,z,roll,pitch,yaw\n"
        f"{t1},{t0},1.0,0.0,0.0,0.0,0.0,0.0\n"
        f"{t2},{t1},0.0,0.0,0.0,0.0,0.0,0.1\n"
    )
    steps = OxfordSource(robotcar).vo("2014-12-09-13-21-02")
    assert [(s.t_prev_ns, s.t_cur_ns) for s in steps] == [(t0 * 1000, t1 * 1000), (t1 * 1000, t2 * 1000)]
    # A static point 10 m ahead of the previous camera is 9 m ahead after driving 1 m forward.
    p = steps[0].T_cur_prev @ np.array([0.0, 0.0, 10.0, 1.0])
    assert p[:3] == pytest.approx([0.0, 0.0, 9.0], abs=1e-9)
    # After turning right, what was straight ahead appears to the left (x < 0), same depth-ish.
    q = steps[1].T_cur_prev @ np.array([0.0, 0.0, 10.0, 1.0])
    assert q[0] == pytest.approx(-10 * np.sin(0.1), abs=1e-9) and q[1] == pytest.approx(0.0, abs=1e-12)
    assert q[2] == pytest.approx(10 * np.cos(0.1), abs=1e-9)


# -- bad input ------------------------------------------------------------------------------


def _image(root: Path, cam: str, plan, pos: int) -> Path:
    return root / plan.sequence / "stereo" / cam / f"{plan.t_ns[pos] // 1000}.png"


def test_missing_right_image_in_present_chunk(robotcar_copy):
    src = OxfordSource(robotcar_copy)
    plan = src.plan("2014-12-09-13-21-02")
    victim = _image(robotcar_copy, "right", plan, 3)
    victim.unlink()
    with pytest.raises(InputError, match="frame 3") as err:
        OxfordSource(robotcar_copy).plan("2014-12-09-13-21-02")
    assert str(victim) in str(err.value)
    # A plan made before the file vanished fails on reading, naming file and frame.
    with pytest.raises(InputError, match="frame 3") as err:
        src.read_frame(plan, 3)
    assert str(victim) in str(err.value)


def test_truncated_png(robotcar_copy):
    src = OxfordSource(robotcar_copy)
    plan = src.plan("2014-12-09-13-21-02")
    victim = _image(robotcar_copy, "left", plan, 2)
    data = victim.read_bytes()
    victim.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="truncated or corrupt") as err:
        src.read_frame(plan, 2)
    assert str(victim) in str(err.value) and "frame 2" in str(err.value)
    src.read_frame(plan, 1)  # the neighbours still read


def test_non_monotonic_timestamps(robotcar_copy):
    path = robotcar_copy / "2014-12-09-13-21-02" / "stereo.timestamps"
    lines = path.read_text().splitlines()
    lines[2], lines[3] = lines[3], lines[2]
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="line 4") as err:
        OxfordSource(robotcar_copy).plan("2014-12-09-13-21-02")
    assert str(path) in str(err.value) and "frame 3" in str(err.value)


def test_image_size_contradicting_lut(robotcar_copy):
    src = OxfordSource(robotcar_copy)
    plan = src.plan("2014-12-09-13-21-02")
    # A later frame of another size: caught when read, naming file and frame.
    victim = _image(robotcar_copy, "right", plan, 4)
    cv2.imwrite(str(victim), cv2.imread(str(victim), cv2.IMREAD_UNCHANGED)[:-2])
    with pytest.raises(InputError, match="frame 4") as err:
        src.read_frame(plan, 4)
    assert str(victim) in str(err.value) and "1242x373" in str(err.value)
    # A LUT of the wrong size: caught when planning, naming the LUT.
    lut = robotcar_copy / "models" / "stereo_wide_right_distortion_lut.bin"
    np.zeros(2 * 640 * 480).tofile(lut)
    with pytest.raises(InputError, match="stereo_wide_right_distortion_lut.bin"):
        OxfordSource(robotcar_copy).plan("2014-12-09-13-21-02")


def test_missing_model_file(robotcar_copy):
    (robotcar_copy / "models" / "stereo_wide_right.txt").unlink()
    with pytest.raises(InputError, match="stereo_wide_right.txt"):
        OxfordSource(robotcar_copy).plan("2014-12-09-13-21-02")


def test_colour_image_instead_of_raw_bayer(robotcar_copy, kitti):
    src = OxfordSource(robotcar_copy)
    plan = src.plan("2014-12-09-13-21-02")
    victim = _image(robotcar_copy, "left", plan, 1)
    cv2.imwrite(str(victim), kitti[0][1])
    with pytest.raises(InputError, match="single-channel") as err:
        src.read_frame(plan, 1)
    assert "frame 1" in str(err.value)


def test_source_pickles_without_lut_maps_and_reads_after(robotcar, kitti):
    import pickle

    src = OxfordSource(robotcar)
    plan = src.plan("2014-12-09-13-21-02")
    clone = pickle.loads(pickle.dumps(src))
    assert clone._cameras == {}
    assert np.array_equal(clone.read_frame(plan, 5).left, src.read_frame(plan, 5).left)


def test_unknown_pair_is_a_config_error(robotcar):
    from mining.errors import ConfigError

    with pytest.raises(ConfigError, match="ultra"):
        OxfordSource(robotcar, pair="ultra")
