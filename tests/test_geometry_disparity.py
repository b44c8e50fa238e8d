"""Dense disparity on real stereo ground truth (KITTI 2015, KITTI raw LiDAR, Middlebury)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from _geometry_data import raw_calib, raw_frame, raw_lidar, rgb

from mining.eval.stereo import bad_n, d1_all
from mining.geometry.config import StereoConfig
from mining.geometry.disparity import StereoMatcher, compute_disparity


def _kitti2015(root):
    base = root / "kitti2015_000046"
    gt = cv2.imread(str(base / "disp_occ_0/000046_10.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / 256.0
    gt[gt == 0] = np.nan
    return rgb(base / "image_2/000046_10.png"), rgb(base / "image_3/000046_10.png"), gt


def test_kitti2015_d1_all_within_ten_percent(stereo_gt_root):
    left, right, gt = _kitti2015(stereo_gt_root)
    disp = compute_disparity(left, right, StereoConfig())
    assert disp.shape == left.shape[:2] and disp.dtype == np.float32
    # Invalid pixels are NaN, never 0 or negative.
    assert not (disp <= 0).any()
    assert np.isnan(disp).any()
    assert d1_all(disp, gt) <= 0.10  # missing estimates count as errors


def test_kitti_raw_depth_matches_lidar(kitti_raw_root):
    calib = raw_calib(kitti_raw_root)[0]
    frame = raw_frame(kitti_raw_root, calib, 0)
    depth = calib.depth_from_disparity(StereoMatcher(StereoConfig()).compute(frame.left, frame.right))
    u, v, z = raw_lidar(kitti_raw_root, 0)
    near = z <= 40.0
    est = depth[np.round(v[near]).astype(int), np.round(u[near]).astype(int)]
    truth = z[near]
    valid = np.isfinite(est)
    assert near.sum() > 10_000
    assert valid.mean() >= 0.90
    assert np.mean(np.abs(est[valid] - truth[valid]) / truth[valid]) <= 0.04


def _read_pfm(path):
    with open(path, "rb") as f:
        assert f.readline().strip() == b"Pf"
        width, height = map(int, f.readline().split())
        scale = float(f.readline())
        data = np.fromfile(f, "<f4" if scale < 0 else ">f4").reshape(height, width)
    return np.flipud(data).copy()  # PFM rows run bottom to top


def test_middlebury_motorcycle_bad2_nonoccluded(stereo_gt_root):
    base = stereo_gt_root / "middlebury2014_motorcycleQ"
    gt = _read_pfm(base / "disp0GT.pfm")
    gt[~np.isfinite(gt)] = np.nan
    nonocc = cv2.imread(str(base / "mask0nocc.png"), cv2.IMREAD_GRAYSCALE) == 255
    # calib.txt: vmax = 65 px at this resolution; doffs only shifts depth, not image disparity.
    disp = compute_disparity(rgb(base / "im0.png"), rgb(base / "im1.png"), StereoConfig(num_disparities=64))
    assert bad_n(disp, gt, nonocc, 2.0) <= 0.15  # measured 0.093 with the defaults


def test_matcher_rejects_bad_settings_and_inputs():
    with pytest.raises(ValueError):
        StereoMatcher(StereoConfig(num_disparities=100))
    with pytest.raises(ValueError):
        StereoMatcher(StereoConfig(block_size=4))
    with pytest.raises(ValueError):
        StereoMatcher(StereoConfig(mode="elas"))
    m = StereoMatcher(StereoConfig())
    with pytest.raises(ValueError):
        m.compute(np.zeros((10, 20, 3), np.uint8), np.zeros((10, 21, 3), np.uint8))


def _textured_pair(h: int = 96, w: int = 256, d: float = 9.5):
    """A fronto-parallel textured plane at a sub-pixel disparity d (the right image is the left shifted by d)."""
    rng = np.random.default_rng(1)
    tex = cv2.GaussianBlur(rng.integers(0, 255, (h, w + 32)).astype(np.float32), (0, 0), 1.0)
    xs = np.arange(w, dtype=np.float32)[None, :].repeat(h, 0)
    ys = np.arange(h, dtype=np.float32)[:, None].repeat(w, 1)
    left = cv2.remap(tex, xs + 16, ys, cv2.INTER_LINEAR)
    right = cv2.remap(tex, xs + 16 + d, ys, cv2.INTER_LINEAR)  # x_right = x_left − d
    rgb = lambda g: np.repeat(np.clip(g, 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)
    return rgb(left), rgb(right)


def test_far_full_resolution_pass_refines_small_disparities_only():
    left, right = _textured_pair()
    half = StereoMatcher(StereoConfig(num_disparities=64, far_full_disparities=0)).compute(left, right)
    far = StereoMatcher(StereoConfig(num_disparities=64, far_full_disparities=16)).compute(left, right)
    full = StereoMatcher(StereoConfig(num_disparities=64, downscale=1)).compute(left, right)
    core = (slice(16, -16), slice(48, -16))
    err = lambda d: float(np.nanmedian(np.abs(d[core] - 9.5)))
    # a 16 px far range with the 8 px margin switches disparities below 8 px only: 9.5 px keeps the half-resolution value
    np.testing.assert_array_equal(np.isnan(far), np.isnan(half))
    np.testing.assert_allclose(far[np.isfinite(far)], half[np.isfinite(half)])
    far_wide = StereoMatcher(StereoConfig(num_disparities=64, far_full_disparities=32)).compute(left, right)
    # below 32 − 8 px: the full-resolution value (measured median error 0.125 px vs 0.344 px at half resolution)
    assert err(far_wide) == pytest.approx(err(full), abs=0.02) and err(far_wide) < 0.5 * err(half)
    assert StereoConfig().far_full_disparities == 32  # on by default since issue 39 (0 = the single pass)
    with pytest.raises(ValueError):
        StereoMatcher(StereoConfig(far_full_disparities=20))
