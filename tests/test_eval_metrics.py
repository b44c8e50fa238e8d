"""Benchmark metrics and file formats, on hand-worked cases and the KITTI devkit demo data."""

from __future__ import annotations

import numpy as np
import pytest

from mining.eval.depth import depth_errors
from mining.eval.odometry import odometry_errors
from mining.eval.stereo import bad_n, d1_all
from mining.formats.disparity import read_disparity_png, read_pfm, write_disparity_png
from mining.formats.poses import read_poses, write_poses
from mining.geometry.poses import chain_egomotion


def _pose(x: float, z: float, yaw: float = 0.0) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[:3, 3] = [x, 0, z]
    return T


def test_d1_counts_errors_over_3px_and_5pct():
    truth = np.array([[10.0, 100.0, np.nan, 50.0]])
    est = np.array([[13.5, 104.0, 7.0, np.nan]])
    # 10 → 13.5: 3.5 px and 35 % → bad; 100 → 104: 4 px but 4 % → good; NaN truth ignored;
    # missing estimate → bad.
    assert d1_all(est, truth) == pytest.approx(2 / 3)


def test_bad_n_with_mask():
    truth = np.array([[10.0, 20.0, 30.0]])
    est = np.array([[10.5, 23.0, 30.0]])
    assert bad_n(est, truth, threshold=2.0) == pytest.approx(1 / 3)
    assert bad_n(est, truth, mask=np.array([[True, False, True]])) == 0.0


def test_depth_errors_hand_worked():
    truth = np.array([10.0, 20.0, np.nan, 50.0])
    est = np.array([11.0, 20.0, 5.0, np.nan])
    e = depth_errors(est, truth)
    assert e.n_points == 3 and e.valid == pytest.approx(2 / 3)
    assert e.abs_rel == pytest.approx(0.05)
    assert depth_errors(est, truth, max_depth_m=15).n_points == 1


def test_odometry_perfect_and_scaled():
    truth = np.array([_pose(0, k * 1.0, 0.01 * k) for k in range(10)])
    perfect = odometry_errors(truth.copy(), truth)
    assert perfect.translation_pct == pytest.approx(0, abs=1e-9) and perfect.segments > 0
    scaled = truth.copy()
    scaled[:, :3, 3] *= 1.02  # 2 % scale drift
    assert odometry_errors(scaled, truth).translation_pct == pytest.approx(2.0, rel=0.05)


def test_chain_egomotion_breaks_on_failure():
    truth = [_pose(0, k * 1.0) for k in range(4)]
    T = [None] + [np.linalg.inv(truth[k]) @ truth[k - 1] for k in range(1, 4)]
    np.testing.assert_allclose(chain_egomotion(T), np.array(truth), atol=1e-12)
    T[2] = None
    poses = chain_egomotion(T)
    assert np.isfinite(poses[1]).all() and np.isnan(poses[2]).all() and np.isnan(poses[3]).all()


def test_disparity_png_round_trip(tmp_path):
    d = np.array([[np.nan, 0.5, 12.34, 250.0]], np.float32)
    write_disparity_png(tmp_path / "d.png", d)
    back = read_disparity_png(tmp_path / "d.png")
    assert np.isnan(back[0, 0])
    np.testing.assert_allclose(back[0, 1:], d[0, 1:], atol=1 / 512)


def test_poses_round_trip_with_nan(tmp_path):
    poses = np.array([_pose(0, 0), _pose(1, 2, 0.1), np.full((4, 4), np.nan)])
    write_poses(tmp_path / "p.txt", poses)
    back = read_poses(tmp_path / "p.txt")
    np.testing.assert_allclose(back[:2], poses[:2], atol=1e-8)
    assert np.isnan(back[2, :3]).all()


def test_devkit_disparity_png_reads_16bit(stereo_gt_root):
    gt = read_disparity_png(stereo_gt_root / "kitti_devkit_demo" / "disp_gt.png")
    est = read_disparity_png(stereo_gt_root / "kitti_devkit_demo" / "disp_est.png")
    valid = np.isfinite(gt)
    # SOURCES.md: 23.9 % valid, 4.74–115.93 px; an 8-bit read would cap at 1 px.
    assert valid.mean() == pytest.approx(0.239, abs=0.005)
    assert 4.7 < np.nanmin(gt) and 115.9 < np.nanmax(gt) < 116.0
    assert d1_all(est, gt) < 0.2  # the devkit's demo estimate is a decent one


def test_middlebury_pfm(stereo_gt_root):
    gt = read_pfm(stereo_gt_root / "middlebury2014_motorcycleQ" / "disp0GT.pfm")
    assert gt.shape == (497, 741)
    assert np.isnan(gt).sum() == 7684
    assert 9.1 < np.nanmin(gt) < 9.2 and 62.8 < np.nanmax(gt) < 62.9
