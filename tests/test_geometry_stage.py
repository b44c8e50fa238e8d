"""Geometry stage on real KITTI frames: egomotion, scene flow, ground plane, failures."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from _geometry_data import oxts_positions, raw_calib, raw_frame, tracking_calib, tracking_frame, tracking_poses

from mining.errors import InputError
from mining.eval.odometry import odometry_errors, rotation_angle
from mining.geometry.config import GeometryConfig, GroundConfig
from mining.geometry.flow import match_quad, stereo_features
from mining.geometry.ground import fit_ground_plane, ground_candidates
from mining.geometry.poses import chain_egomotion
from mining.geometry.stage import GeometryStage
from mining.types import StereoFrame

STEPS = ("disparity", "flow", "egomotion", "ground")


@pytest.fixture(scope="module")
def tracking_run(kitti_tracking_root):
    calib = tracking_calib(kitti_tracking_root)
    stage = GeometryStage(calib, GeometryConfig())
    frames = [tracking_frame(kitti_tracking_root, calib, i) for i in range(9)]
    return frames, [stage.run(f) for f in frames]


def test_first_frame_has_no_flow_and_every_step_is_timed(tracking_run):
    _, out = tracking_run
    assert out[0].flow is None and out[0].egomotion is None
    for g in out:
        assert all(g.timings_ms[k] > 0 for k in STEPS)
        assert g.depth.shape == g.disparity.shape
        assert np.isnan(g.depth[np.isnan(g.disparity)]).all()


def test_egomotion_agrees_with_orbslam3(tracking_run, kitti_tracking_root):
    _, out = tracking_run
    assert all(g.egomotion.ok and g.egomotion.reason == "" for g in out[1:])
    estimate = chain_egomotion([None] + [g.egomotion.T_cur_prev for g in out[1:]])
    truth = tracking_poses(kitti_tracking_root)[: len(out)]
    err = odometry_errors(estimate, truth, min_frames=5)
    assert err.segments > 0
    assert err.translation_pct <= 2.0
    for k, g in enumerate(out[1:]):
        true_step = np.linalg.inv(truth[k + 1]) @ truth[k]  # T_cur_prev of the reference
        assert np.degrees(rotation_angle(true_step[:3, :3].T @ g.egomotion.T_cur_prev[:3, :3])) < 0.2
        assert g.egomotion.rmse_px < 1.5 and g.egomotion.inliers >= 50


def test_egomotion_distance_agrees_with_oxts(kitti_raw_root):
    calib = raw_calib(kitti_raw_root)[0]
    stage = GeometryStage(calib)
    out = [stage.run(raw_frame(kitti_raw_root, calib, i)) for i in range(5)]
    poses = chain_egomotion([None] + [g.egomotion.T_cur_prev for g in out[1:]])
    gps = oxts_positions(kitti_raw_root, 5)
    travelled = np.linalg.norm(gps[-1] - gps[0])
    assert travelled > 4.0
    assert abs(np.linalg.norm(poses[-1][:3, 3]) - travelled) / travelled <= 0.02


@pytest.mark.parametrize("kind", ["noise", "textureless"])
def test_egomotion_failure_is_flagged_not_identity(tracking_run, kind):
    frames, _ = tracking_run
    stage = GeometryStage(frames[0].calib)
    stage.run(frames[0])
    nxt = frames[1]
    if kind == "noise":
        rng = np.random.default_rng(1)
        left, right = (rng.integers(0, 256, nxt.left.shape, dtype=np.uint8) for _ in range(2))
    else:
        left = right = np.full_like(nxt.left, 128)
    g = stage.run(StereoFrame(nxt.dataset, nxt.sequence, nxt.index, nxt.t_ns, left, right, nxt.calib))
    assert not g.egomotion.ok
    assert g.egomotion.T_cur_prev is None and g.egomotion.reason
    assert np.isnan(g.flow.motion).all() and not g.flow.inlier.any()


def test_static_scene_flow_is_near_zero(tracking_run):
    _, out = tracking_run
    static = []
    for g in out[1:]:
        f = g.flow
        assert len(f) >= 200
        assert f.inlier.mean() > 0.5
        near = f.inlier & (f.points[:, 2] < 20.0)
        assert near.sum() >= 50
        static.append(f.motion[near])
        assert (f.points[:, 2] <= 90.0).all() and (np.abs(f.points[:, 0]) <= 30.0).all()
        assert (f.points_prev[:, 2] <= 90.0).all() and (np.abs(f.points_prev[:, 0]) <= 30.0).all()
    motion = np.concatenate(static)
    # Stereo depth noise dominates along z (≈0.1 m at 15 m for 0.15 px); x and y are tighter.
    assert np.median(np.linalg.norm(motion, axis=1)) < 0.15
    assert (np.median(np.abs(motion), axis=0)[:2] < 0.06).all()


def test_cycle_check_rejects_planted_wrong_match(tracking_run):
    frames, out = tracking_run
    cfg = GeometryConfig().flow
    calib = frames[0].calib
    feats = []
    for f, g in zip(frames[3:5], out[3:5]):
        gray = [cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) for img in (f.left, f.right)]
        feats.append(stereo_features(gray[0], gray[1], g.disparity, cfg))
    prev, cur = feats
    T = out[4].egomotion.T_cur_prev
    kept = match_quad(prev, cur, calib, cfg, T)
    # Two features that close their cycle, far apart, with different disparities.
    ids = [int(np.flatnonzero((prev.uv_left == p).all(axis=1))[0]) for p in kept.uv_prev_left]
    disp = prev.uv_left[ids, 0] - prev.uv_right[ids, 0]
    a = ids[int(np.argmin(disp))]
    b = ids[int(np.argmax(disp))]
    # Plant a wrong left↔right match at t−1: a's right partner becomes b's (shifted to a's row).
    wrong = prev.uv_right.copy()
    wrong[a] = prev.uv_right[b] + np.array([0.0, prev.uv_left[a, 1] - prev.uv_right[b, 1]], np.float32)
    prev.uv_right = wrong
    again = match_quad(prev, cur, calib, cfg, T)
    assert not (again.uv_prev_left == prev.uv_left[a]).all(axis=1).any()
    assert len(again) >= len(kept) - 2  # the rest still closes


def test_ground_plane_on_kitti(tracking_run):
    _, out = tracking_run
    for g in out:
        assert g.ground.ok, g.ground.reason
        assert np.degrees(np.arccos(-g.ground.normal[1])) < 5.0
        assert 1.5 <= g.ground.d <= 1.8  # camera height, KITTI mounts it at 1.65 m
        assert g.ground.height(np.array([[0.0, 0.0, 10.0]]))[0] == pytest.approx(g.ground.d, abs=0.2)


def test_ground_plane_needs_enough_points(tracking_run):
    _, out = tracking_run
    cfg = GroundConfig()
    # Real road candidates of frame 0, cut below the minimum.
    pts = ground_candidates(out[0].disparity, tracking_run[0][0].calib, cfg)
    assert len(pts) >= cfg.min_points
    few = fit_ground_plane(pts[: cfg.min_points - 1], cfg)
    assert not few.ok and few.normal is None and "too few" in few.reason
    with pytest.raises(ValueError):
        few.height(pts[:1])


def test_stage_rejects_wrong_image_shape(tracking_run):
    frames, _ = tracking_run
    f = frames[0]
    stage = GeometryStage(f.calib)
    with pytest.raises(InputError):
        stage.run(StereoFrame(f.dataset, f.sequence, f.index, f.t_ns, f.left[:-1], f.right[:-1], f.calib))


def test_exact_depth_is_the_synthetic_truth_and_refused_without_it(tracking_run):
    """``geometry.stereo.exact_depth`` (an instrument for the recall funnel) takes the renderer's
    depth instead of matching; a frame without it (every real source) is an error naming the frame."""
    import dataclasses

    from mining.sources import open_source

    src = open_source("synthetic", None, n_frames=2)
    frame = next(iter(src.read(src.plan("0000"), 0, 1)))
    cfg = GeometryConfig()
    cfg.stereo.exact_depth = True
    g = GeometryStage(frame.calib, cfg).run(frame)
    truth = frame.truth.depth
    near = np.isfinite(truth) & (truth <= cfg.stereo.max_depth_m)
    np.testing.assert_allclose(g.depth[near], truth[near], rtol=1e-5)
    assert np.isnan(g.depth[~near]).all()
    assert g.ground.ok  # the ground plane comes from the exact disparity too
    real, _ = tracking_run
    with pytest.raises(InputError, match=r"exact_depth.*synthetic only.*none") as err:
        GeometryStage(real[0].calib, cfg).run(real[0])
    assert err.value.frame == real[0].index
    with pytest.raises(InputError, match="exact_depth"):
        GeometryStage(frame.calib, cfg).run(dataclasses.replace(frame, truth=None, index=frame.index + 1))
