"""Warp points of a mask whose pixels include an occluder's depth (``localise.at_median_depth``).

Real case from the renderer: synthetic seed 0004, frame 17, a pedestrian (track 250) 29 m
away and 17 m to the left, proposed by the shared ONNX model (mask IoU 0.74 with its truth);
about 5 % of the mask's pixels have stereo depth 8 m (a nearer object at the mask's border).
Warped at their own depth, those pixels move 40+ px when the camera steps back one frame, the
predicted box is three times the person's width, and no tube ever started on this person in
the 12 frames it was seen. Truth: the renderer's masks, boxes and camera poses.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import MODEL

from mining.boxes import box_iou
from mining.config import load_config
from mining.eval.synthetic import gt_frame
from mining.localise.config import LocaliseConfig
from mining.localise.localise import _may_move_to_median_depth, at_median_depth, triangulation_covariance
from mining.masks import mask_iou
from mining.pipeline.frames import FrameLoop
from mining.sources import open_source
from mining.tubes.warp import mask_points, predict_boxes
from mining.types import StereoCalib

PERSON = 250  # track id in synthetic seed 0004 (200 frames)


@pytest.fixture(scope="module")
def frames():
    src = open_source("synthetic", None, n_frames=200)
    return list(src.read(src.plan("0004"), 16, 18))


def _person(frames, units: float):
    """The person's observation in frame 17 (localised with ``units``) and its truth in frame 16."""
    pytest.importorskip("onnxruntime")
    if not MODEL.is_file():
        pytest.skip(f"no ONNX model at {MODEL}")
    cfg = load_config(None, ['proposals.proposer="onnx"', f'proposals.onnx.model_path="{MODEL.as_posix()}"',
                             f"localise.point_depth_outlier_units={units}"])
    f16, f17 = frames
    rec = FrameLoop(cfg).step(f17)
    gt = gt_frame(f17.truth)
    iou = mask_iou([gt.rles[list(gt.track_ids).index(PERSON)]], list(rec.localised.proposals.rles))[0]
    j = int(iou.argmax())
    assert iou[j] > 0.6  # the model's mask is on the person
    g16 = gt_frame(f16.truth)
    return rec.localised, j, g16.boxes[list(g16.track_ids).index(PERSON)]


def _box_one_frame_back(frames, obs, j) -> np.ndarray:
    f16, f17 = frames
    mp = mask_points(obs.points[j], obs.grid[j], obs.proposals.boxes[j], obs.position[j], f17.calib, f17.truth.pose)
    return predict_boxes([mp], np.zeros((1, 3)), f16.truth.pose, f16.calib)


def test_occluder_pixels_take_the_persons_depth(frames):
    ref, j, _ = _person(frames, 0.0)
    assert np.mean(ref.points[j][:, 2] < 12.0) > 0.02  # REFERENCE keeps them at 8 m
    obs, j, _ = _person(frames, 5.0)
    z = obs.points[j][:, 2]
    assert np.all(np.abs(z - np.median(z)) < 4.0)  # the person's own depth spread and stereo noise


def test_one_frame_back_the_predicted_box_stays_on_the_person(frames):
    ref, j, truth16 = _person(frames, 0.0)
    assert box_iou(_box_one_frame_back(frames, ref, j), truth16[None])[0, 0] < 0.3
    obs, j, truth16 = _person(frames, 5.0)
    assert box_iou(_box_one_frame_back(frames, obs, j), truth16[None])[0, 0] > 0.5


def test_a_moved_point_keeps_its_pixel():
    calib = StereoCalib(fx=721.5, fy=721.5, cx=609.6, cy=172.9, baseline_m=0.54, width=1242, height=375)
    rng = np.random.default_rng(0)
    z = np.r_[rng.normal(30.0, 0.3, 200), [8.0, 8.2]]
    u, v = rng.uniform(300, 330, z.size), rng.uniform(150, 200, z.size)
    pts = calib.backproject(u, v, z).astype(np.float32)
    noise_z = float(np.sqrt(triangulation_covariance(np.median(pts, axis=0)[None], calib, LocaliseConfig())[0, 2, 2]))
    out = at_median_depth(pts, noise_z, LocaliseConfig().point_depth_outlier_units)
    np.testing.assert_allclose(out[:200], pts[:200])  # inliers untouched
    assert np.all(np.abs(out[200:, 2] - np.median(pts[:, 2])) < 1e-3)
    np.testing.assert_allclose(calib.project(out[200:].astype(np.float64)), np.c_[u, v][200:], atol=1e-3)


def test_masks_left_out_of_the_depth_outlier_step_are_ones_it_leaves_unchanged():
    """``_may_move_to_median_depth`` skips only masks whose points ``at_median_depth`` returns as they are."""
    rng = np.random.default_rng(1)
    sizes = rng.integers(0, 60, 400)
    bounds = np.concatenate([[0], np.cumsum(sizes)])
    z = rng.normal(20.0, 1.0, bounds[-1]).astype(np.float32)
    z[rng.random(z.size) < 0.03] = 9.0  # a few occluder depths
    var_z = rng.uniform(0.01, 1.0, sizes.size) ** 2
    masks = np.flatnonzero(rng.random(sizes.size) < 0.8)
    units = LocaliseConfig().point_depth_outlier_units
    may = set(_may_move_to_median_depth(z, bounds, masks, var_z, units).tolist())
    assert 0 < len(may) < masks.size
    for i in masks:
        pts = np.zeros((sizes[i], 3), np.float32)
        pts[:, 2] = z[bounds[i]:bounds[i + 1]]
        if i not in may:
            assert at_median_depth(pts, float(np.sqrt(var_z[i])), units) is pts


def test_velocity_noise_is_the_configured_multiple_of_the_position_covariance(frames):
    """``localise.velocity_noise_factor`` (REFERENCE: 2) sets the velocity measurement noise."""
    f17 = frames[1]
    for factor in (2.0, 7.0):
        cfg = load_config(None, [f"localise.velocity_noise_factor={factor}"])
        o = FrameLoop(cfg).step(f17).localised
        assert len(o.covariance) > 0
        np.testing.assert_allclose(o.velocity_covariance, factor * o.covariance)
