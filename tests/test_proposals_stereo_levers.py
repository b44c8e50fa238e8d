"""Issue 29's levers of the stereo proposer, each on a small array case where it must make the
difference: the image refinement of a bleeding mask, low standing surfaces under the ground
cut, and support by visible surface for far objects. Depth maps are built from a known ground
plane, so each case is exact and fast (no matcher, no renderer)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pycocotools import mask as mask_utils

from mining.masks import crop_rle, mask_iou
from mining.proposals.stereo import StereoProposer, colour_bins, refine_by_colour, refine_with_image
from mining.proposals.stereo_config import StereoProposerConfig
from mining.types import FrameGeometry, GroundPlane, StereoCalib, StereoFrame

H, W = 188, 621  # half KITTI size
CALIB = StereoCalib(360.0, 360.0, W / 2, H / 2, 0.54, W, H)
CAM_HEIGHT = 1.65


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def bleeding_case() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 12 × 24 px orange object on textured grey road; the stereo mask misses its two right
    columns and bleeds 10 px onto the road at its left (left-reference stereo)."""
    rng = np.random.default_rng(0)
    img = np.clip(rng.normal(110, 12, (80, 80, 3)), 0, 255).astype(np.uint8)
    truth = np.zeros((80, 80), bool)
    truth[30:54, 40:52] = True
    img[truth] = (230, 120, 30)
    mask = np.zeros((80, 80), bool)
    mask[30:54, 30:50] = True
    return img, truth, mask


def test_colour_refinement_moves_a_bleeding_mask_to_the_outline():
    img, truth, mask = bleeding_case()
    assert iou(mask, truth) < 0.5
    cfg = StereoProposerConfig(refine="colour")
    crop, x0, y0 = refine_by_colour(mask[30:54, 30:50], 30, 30, colour_bins(img, cfg.refine_colour_bits), cfg)
    out = np.zeros_like(truth)
    out[y0:y0 + crop.shape[0], x0:x0 + crop.shape[1]] = crop
    assert iou(out, truth) >= 0.8
    # GrabCut from the same start reaches the outline too (at ~4 ms a mask)
    crop, x0, y0 = refine_with_image(mask[30:54, 30:50], 30, 30, img, cfg)
    out[:] = False
    out[y0:y0 + crop.shape[0], x0:x0 + crop.shape[1]] = crop
    assert iou(out, truth) >= 0.7


def test_colour_refinement_keeps_the_mask_where_colours_do_not_tell():
    img, truth, mask = bleeding_case()
    img[:] = 110  # object and road of one colour: no colour model separates them
    cfg = StereoProposerConfig(refine="colour")
    crop = mask[30:54, 30:50]
    out, x0, y0 = refine_by_colour(crop, 30, 30, colour_bins(img, cfg.refine_colour_bits), cfg)
    assert out is crop and (x0, y0) == (30, 30)


def ground_depth() -> np.ndarray:
    """Depth of a flat road 1.65 m under the camera (NaN above the horizon)."""
    v = np.arange(H, dtype=np.float64)[:, None] - CALIB.cy
    with np.errstate(divide="ignore"):
        z = np.where(v > 0.5, CALIB.fy * CAM_HEIGHT / np.maximum(v, 1e-9), np.nan)
    return np.repeat(z, W, axis=1).astype(np.float32)


def standing_box(depth: np.ndarray, z: float, x: tuple[float, float], height: float) -> np.ndarray:
    """Paint a vertical face at depth z, x ∈ [x0, x1] m, from the ground up to ``height``; its mask."""
    v = np.arange(H)[:, None]
    u = np.arange(W)[None, :]
    y = (v - CALIB.cy) * z / CALIB.fy  # camera y of the face at each row (down positive)
    xs = (u - CALIB.cx) * z / CALIB.fx
    m = (y <= CAM_HEIGHT) & (y >= CAM_HEIGHT - height) & (xs >= x[0]) & (xs <= x[1])
    depth[m] = z
    return m


def frame_and_geometry(depth: np.ndarray, image: np.ndarray | None = None) -> tuple[StereoFrame, FrameGeometry]:
    img = np.full((H, W, 3), 100, np.uint8) if image is None else image
    frame = StereoFrame("test", "0", 0, 0, img, img, CALIB)
    ground = GroundPlane(np.array([0.0, -1.0, 0.0]), CAM_HEIGHT, 1000, True)
    return frame, FrameGeometry(0, 0, CALIB.bf / depth, depth, None, None, ground)


def best_iou(proposals, truth: np.ndarray) -> float:
    if not len(proposals):
        return 0.0
    gt = crop_rle(truth, 0, 0, H, W)
    return float(mask_iou([gt], proposals.rles).max())


def test_low_standing_object_is_proposed_only_with_the_low_lever():
    # A 0.2 m tall, 1.2 m wide face 6 m ahead (a tyre lying flat, a kerb-side box): wholly
    # under the 0.2 m ground cut, it stands up from the road (its disparity is constant down
    # the image where the road's grows).
    depth = ground_depth()
    truth = standing_box(depth, 6.0, (-0.6, 0.6), 0.2)
    frame, geom = frame_and_geometry(depth)
    off = StereoProposer(StereoProposerConfig(low_min_height_m=0.0))(frame, geom)
    on = StereoProposer(StereoProposerConfig(low_min_height_m=0.04))(frame, geom)
    assert best_iou(off, truth) < 0.5
    assert best_iou(on, truth) >= 0.5


def test_far_object_outranks_a_near_small_one_when_support_counts_surface():
    # A 1.6 × 1.2 m object at 40 m has fewer sample points than a 0.5 × 0.5 m box at 8 m but
    # four times its surface. With one mask to build, support by points takes the near box;
    # support by visible surface takes the far object.
    depth = ground_depth()
    far = standing_box(depth, 40.0, (-4.0, -2.4), 1.2)
    near = standing_box(depth, 8.0, (1.0, 1.5), 0.5)
    frame, geom = frame_and_geometry(depth)
    base = StereoProposerConfig(max_proposals=1, mask_budget=1.0, support_ref_depth_m=0.0)
    by_points = StereoProposer(base)(frame, geom)
    by_surface = StereoProposer(dataclasses.replace(base, support_ref_depth_m=10.0))(frame, geom)
    assert len(by_points) == 1 and best_iou(by_points, near) >= 0.5
    assert len(by_surface) == 1 and best_iou(by_surface, far) >= 0.4  # its feet lie under the far ground cut
    assert abs(by_surface.position[0, 2] - 40.0) < 2.0 and abs(by_points.position[0, 2] - 8.0) < 1.0


@pytest.mark.parametrize("refine", ["none", "colour", "grabcut"])
def test_refinement_keeps_proposals_valid(refine):
    depth = ground_depth()
    standing_box(depth, 8.0, (-0.5, 0.5), 0.8)
    img = np.full((H, W, 3), 100, np.uint8)
    frame, geom = frame_and_geometry(depth, img)
    p = StereoProposer(StereoProposerConfig(refine=refine))(frame, geom)
    assert len(p) >= 1
    m = mask_utils.decode(p.rles)
    for i in range(len(p)):
        ys, xs = np.nonzero(m[:, :, i])
        assert (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1) == tuple(p.boxes[i].astype(int))
