"""The weight-free stereo proposer on real KITTI tracking 0005 frames and synthetic frames with
unknown objects (geometry computed once per module)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from pycocotools import mask as mask_utils

from mining.boxes import box_iou
from mining.errors import InputError
from mining.formats.kitti_tracking import read_kitti_tracking
from mining.geometry.config import GroundConfig
from mining.geometry.ground import estimate_ground
from mining.geometry.stage import GeometryStage
from mining.proposals.stereo import CUES, StereoProposer, objectness_from_cues
from mining.proposals.stereo_config import StereoProposerConfig
from mining.sources import open_source

N_FRAMES = 8  # frames 0–7 of 0005: 24 labelled cars at 29–58 m


@pytest.fixture(scope="module")
def kitti_frames(kitti_tracking_root):
    src = open_source("kitti", str(kitti_tracking_root))
    plan = src.plan("0005")
    stage = GeometryStage(plan.calib)
    frames = [(f, stage.run(f)) for f in src.read(plan, 0, N_FRAMES)]
    proposer = StereoProposer()
    return [(f, g, proposer(f, g)) for f, g in frames]


@pytest.fixture(scope="module")
def labels(kitti_tracking_root):
    return read_kitti_tracking(kitti_tracking_root / "training" / "label_02" / "0005.txt")


def test_car_recall_on_kitti(kitti_frames, labels):
    # Measured on frames 0–7: R@20 = 0.83, R@all = 0.875 of 24 cars (box IoU ≥ 0.5); thresholds leave a margin.
    hits = {20: [], None: []}
    for f, _, p in kitti_frames:
        gt = labels.box[(labels.frame == f.index) & (labels.type != "DontCare")]
        assert len(gt) > 0
        for n in hits:
            iou = box_iou(gt, p.boxes[:n].astype(np.float64))
            hits[n] += list(iou.max(axis=1) >= 0.5)
    assert np.mean(hits[None]) >= 0.75
    assert np.mean(hits[20]) >= 0.65


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_proposals_are_valid(kitti_frames):
    # What every proposer keeps (shapes, dtypes, ranges, order, 3D rows): tests/test_proposals_contract.py.
    for f, _, p in kitti_frames:
        n = len(p)
        assert 10 <= n <= StereoProposerConfig().max_proposals
        masks = mask_utils.decode(p.rles)
        for i in range(n):
            ys, xs = np.nonzero(masks[:, :, i])
            assert ys.size > 0
            # The box is the mask's own bounding box (x2, y2 exclusive).
            assert (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1) == tuple(p.boxes[i].astype(int))


def test_objectness_is_monotone_in_each_cue(kitti_frames):
    cfg = StereoProposerConfig()
    rng = np.random.default_rng(0)
    cues = rng.random((500, len(CUES)))
    base = objectness_from_cues(cues, cfg)
    for k in range(len(CUES)):
        up = cues.copy()
        up[:, k] = np.minimum(1.0, up[:, k] + rng.random(500) * 0.5)
        assert (objectness_from_cues(up, cfg) >= base).all()
        assert (objectness_from_cues(up, cfg) > base).any()
    with pytest.raises(ValueError):
        objectness_from_cues(cues, dataclasses.replace(cfg, w_fill=-1.0))
    # The proposer's scores are exactly the function of the cues it reports.
    f, g, _ = kitti_frames[0]
    result = StereoProposer(cfg).propose(f, g)
    p = result.proposals
    assert result.cues.shape == (len(p), len(CUES)) and result.reason == ""
    assert ((result.cues >= 0) & (result.cues <= 1)).all()
    np.testing.assert_allclose(objectness_from_cues(result.cues, cfg), p.objectness, atol=1e-6)
    assert set(result.timings_ms) == {"points", "cluster", "stats", "masks", "encode"}


def test_no_ground_plane_gives_no_proposals(kitti_frames):
    f, g, _ = kitti_frames[0]
    # A real RANSAC failure: more candidate points demanded than the frame has.
    failed = estimate_ground(g.disparity, f.calib, GroundConfig(min_points=10**7))
    assert not failed.ok
    result = StereoProposer().propose(f, dataclasses.replace(g, ground=failed))
    p = result.proposals
    assert len(p) == 0 and p.boxes.shape == (0, 4) and p.posterior is None
    assert result.reason.startswith("no ground plane") and result.cues.shape == (0, len(CUES))


def test_bad_geometry_raises(kitti_frames):
    f, g, _ = kitti_frames[0]
    with pytest.raises(InputError, match="depth map"):
        StereoProposer()(f, dataclasses.replace(g, depth=g.depth[:100]))
    with pytest.raises(InputError, match="geometry of frame"):
        StereoProposer()(f, dataclasses.replace(g, index=g.index + 1))


@pytest.fixture(scope="module")
def synthetic_frames():
    src = open_source("synthetic", None, n_frames=50)
    out = []
    for seq in ("0000", "0001", "0002"):
        plan = src.plan(seq)
        for i in range(0, 50, 10):
            f = next(iter(src.read(plan, i, i + 1)))
            out.append((f, GeometryStage(plan.calib).run(f)))
    return out


@pytest.mark.slow  # renders and proposes a synthetic sequence
def test_unknown_objects_are_found_on_synthetic(synthetic_frames):
    # Objects no detector knows (cones, bins, crates, debris) within 30 m. Measured on these
    # 15 frames (issue 29): box IoU ≥ 0.5 for 22 of 47 (0.47), mask IoU ≥ 0.5 for 24 (0.51); before
    # the colour refinement and the issue-29 settings 17 and 15 (0.32): stereo at half resolution
    # fattens small objects sideways and merges them with what stands behind, and the image step
    # moves the masks to the outline. Debris (≤ 0.3 m high) mostly lies under the ground cut.
    proposer = StereoProposer()
    box_hit, mask_hit = [], []
    for f, g in synthetic_frames:
        p = proposer(f, g)
        for o in f.truth.objects:
            if o.known or o.center_cam[2] >= 30 or o.mask.sum() < 50:
                continue
            gt = mask_utils.encode(np.asfortranarray(o.mask.astype(np.uint8)))
            box_hit.append(box_iou(np.array([o.box], np.float64), p.boxes.astype(np.float64)).max() >= 0.5)
            mask_hit.append(mask_utils.iou(p.rles, [gt], [0]).max() >= 0.5)
    assert len(box_hit) >= 15
    assert np.mean(box_hit) >= 0.35
    assert np.mean(mask_hit) >= 0.40
