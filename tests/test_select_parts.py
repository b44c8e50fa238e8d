"""Co-selection keeps real objects and rejects parts and duplicates (issue 18, item 3).

The pairwise term is REFERENCE's Σ_t mask IoU (``overlap="iou"``) or ours, Σ_t intersection
over the smaller mask (``overlap="min"``), each with its own box gate. Tubes are real
``Tube``/``TubeFrame`` objects with COCO RLEs encoded by pycocotools from hand-drawn or
rendered masks; truth comes from numpy pixel counts or from how the masks were drawn.
Scores are typical of mined tubes: a car ~80, a part ~25 (ε1 = 20, ε2 = 30).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from conftest import coco_rle

from mining.masks import mask_ioa, mask_overlap_min, rle_box
from mining.select.config import OverlapWeight, Price, SelectConfig
from mining.select.coselect import co_select, pairwise_overlap
from mining.sources.synthetic import SyntheticSource
from mining.types import Tube, TubeFrame

H, W = 240, 640
CAR, PART = 80.0, 25.0  # typical mined scores (mine eval synthetic: ~3.5 a frame, cars of 20+ frames)
IOU, MIN = SelectConfig(overlap="iou"), SelectConfig(overlap="min")


def _rect(x1: int, y1: int, x2: int, y2: int, h: int = H, w: int = W) -> np.ndarray:
    m = np.zeros((h, w), bool)
    m[y1:y2, x1:x2] = True
    return m


def _tube(tube_id: int, masks: list[np.ndarray], first: int = 0) -> Tube:
    """A tube observed in consecutive frames with the given masks (box from the mask)."""
    t = Tube(tube_id, 0)
    for k, mask in enumerate(masks):
        rle = coco_rle(mask)
        t.frames.append(TubeFrame(first + k, (first + k) * 100_000_000, True, 0, rle, rle_box(rle), np.zeros(3),
                                  np.zeros(3), np.ones(3), np.zeros(3), 0.9, np.nan if k == 0 else 0.8,
                                  np.nan if k == 0 else 0.5))
    return t


def _moving(x1: int, y1: int, x2: int, y2: int, n: int = 10, step: int = 2) -> list[np.ndarray]:
    """A rectangle drifting right by ``step`` pixels a frame."""
    return [_rect(x1 + k * step, y1, x2 + k * step, y2) for k in range(n)]


# --------------------------------------------------------------------------- the helper


@pytest.mark.parametrize("a, b, expected", [
    (_rect(0, 0, 40, 40, 60, 60), _rect(5, 5, 15, 15, 60, 60), 1.0),  # 10×10 inside 40×40
    (_rect(0, 0, 10, 10, 60, 60), _rect(20, 20, 30, 30, 60, 60), 0.0),  # disjoint
    (_rect(0, 0, 20, 20, 60, 60), _rect(10, 0, 30, 20, 60, 60), 0.5),  # equal squares, half overlapping
])
def test_overlap_min_on_hand_made_masks(a, b, expected):
    by_pixels = (a & b).sum() / min(a.sum(), b.sum())
    assert by_pixels == expected
    got = mask_overlap_min([coco_rle(a)], [coco_rle(b)])
    assert got.shape == (1, 1) and got[0, 0] == pytest.approx(expected, abs=1e-12)
    assert mask_overlap_min([coco_rle(b)], [coco_rle(a)])[0, 0] == pytest.approx(expected, abs=1e-12)  # symmetric


def test_overlap_min_equals_pixel_counting_on_random_shapes():
    rng = np.random.default_rng(3)
    masks = []
    for _ in range(7):  # blobs of random size and place, some nested, some apart
        cx, cy, r = rng.integers(10, 90), rng.integers(10, 70), rng.integers(2, 30)
        yy, xx = np.mgrid[:80, :100]
        masks.append((xx - cx) ** 2 + 0.5 * (yy - cy) ** 2 < r * r)
    masks.append(np.zeros((80, 100), bool))  # an empty mask overlaps nothing
    got = mask_overlap_min([coco_rle(m) for m in masks[:5]], [coco_rle(m) for m in masks[3:]])
    for i, a in enumerate(masks[:5]):
        for j, b in enumerate(masks[3:]):
            smaller = min(a.sum(), b.sum())
            assert got[i, j] == pytest.approx((a & b).sum() / smaller if smaller else 0.0, abs=1e-12)


def test_pycocotools_crowd_rule_divides_by_the_first_list():
    """mask_ioa (pycocotools' iscrowd=1) is |A∩B| / |A| with A from its first argument,
    which mask_overlap_min relies on."""
    big, small = _rect(0, 0, 40, 40, 60, 60), _rect(5, 5, 15, 15, 60, 60)
    assert mask_ioa([coco_rle(small)], [coco_rle(big)])[0, 0] == 1.0
    assert mask_ioa([coco_rle(big)], [coco_rle(small)])[0, 0] == pytest.approx(100 / 1600)


# --------------------------------------------------------------------------- selection


def test_a_part_inside_a_car_wins_with_iou_and_loses_with_min():
    """A wheel arch (30×25) in the car's (160×80) lower front corner, 10 frames: its box IoU
    with the car's is 0.06, under the 0.1 gate, so REFERENCE's term never sees it."""
    car = _tube(0, _moving(100, 100, 260, 180))
    arch = _tube(1, _moving(225, 155, 255, 180))
    scores = np.array([CAR, PART])
    assert co_select([car, arch], scores, IOU).tolist() == [True, True]
    assert co_select([car, arch], scores, MIN).tolist() == [True, False]


def test_touching_neighbours_both_win_in_both_modes():
    """Two parked cars in a row: the nearer (lower in the image) hides the farther's rear
    corner. Their boxes overlap (40×55 px, both gates pass), their visible masks only in the
    3 columns where the nearer's hidden region is not cut out of the farther's mask."""
    near, far = [], []
    for k in range(10):
        front = _rect(100 + 2 * k, 110, 220 + 2 * k, 190)
        far.append(_rect(180 + 2 * k, 95, 300 + 2 * k, 165) & ~_rect(100 + 2 * k, 110, 217 + 2 * k, 190))
        near.append(front)
    near_t, far_t = _tube(0, near), _tube(1, far)
    scores = np.array([CAR, 40.0])  # the farther one partly hidden, with a modest score
    for cfg in (IOU, MIN):
        charged = pairwise_overlap([near_t, far_t], cfg.box_iou_gate, cfg.overlap)[0, 1]
        assert 0 < charged < 0.5  # gated in, charged a little: Σ over 10 frames of 165 / 6365 px at most
        assert co_select([near_t, far_t], scores, cfg).tolist() == [True, True]


def test_a_duplicate_loses_in_both_modes():
    car = _tube(0, _moving(100, 100, 260, 180))
    dup = _tube(1, _moving(103, 101, 263, 181))  # the same car again, shifted by a few pixels
    scores = np.array([CAR, 70.0])
    for cfg in (IOU, MIN):
        assert co_select([car, dup], scores, cfg).tolist() == [True, False]


def test_min_gate_lets_a_small_part_in_a_big_box_through():
    car = _tube(0, _moving(100, 100, 260, 180))
    arch = _tube(1, _moving(225, 155, 255, 180))
    iou = pairwise_overlap([car, arch], 0.1, "iou")
    mn = pairwise_overlap([car, arch], 0.1, "min")
    assert iou[0, 1] == 0.0  # box IoU 750 / 12800 ≈ 0.06 ≤ 0.1: every frame gated out
    assert mn[0, 1] == pytest.approx(10.0) and mn[1, 0] == mn[0, 1]  # inside in all 10 frames: 1 each


def test_min_gate_still_leaves_out_boxes_that_barely_meet():
    """Boxes sharing a corner of under 10 % of the smaller box: no mask comparison, no charge,
    though the masks do overlap there."""
    a = _tube(0, _moving(100, 100, 200, 180))
    b = _tube(1, _moving(195, 175, 245, 225))  # 5×5 corner of a 50×50 box: 1 %
    assert pairwise_overlap([a, b], 0.1, "min")[0, 1] == 0.0


def test_overlap_floor_frees_neighbours_whose_masks_bleed_into_each_other():
    """Two cars nose to tail at range, each mask fattened into the other (stereo edges): IoU
    0.12 a frame. At the calibrated price (ε1 0, ε2 3) the weaker one's score over 10 frames
    (3.0) is below the charge (3 × 1.23), so REFERENCE's Σ IoU drops it; with the floor
    (0.15: what two distinct objects' masks share, ``select.overlap_floor``) both are kept,
    and a duplicate (IoU ≈ 0.9 a frame) still loses."""
    near = _tube(0, _moving(100, 110, 220, 190))
    far = _tube(1, _moving(190, 100, 300, 175))  # 30 × 65 px in common: IoU 1950 / 15900
    dup = _tube(2, _moving(102, 111, 222, 191))
    scores = np.array([6.0, 3.0, 5.0])
    ref = SelectConfig(price=Price(reference=0.0), overlap_weight=OverlapWeight(reference=3.0))
    floored = SelectConfig(price=Price(reference=0.0), overlap_weight=OverlapWeight(reference=3.0), overlap_floor=0.15)
    assert pairwise_overlap([near, far], 0.1)[0, 1] == pytest.approx(10 * 1950 / 15900)
    assert pairwise_overlap([near, far], 0.1, floor=0.15)[0, 1] == 0.0
    iou_dup = pairwise_overlap([near, dup], 0.1)[0, 1]
    assert pairwise_overlap([near, dup], 0.1, floor=0.15)[0, 1] == pytest.approx((iou_dup - 1.5) / 0.85)
    assert co_select([near, far], scores[:2], ref).tolist() == [True, False]
    assert co_select([near, far], scores[:2], floored).tolist() == [True, True]
    assert co_select([near, far, dup], scores, floored).tolist() == [True, True, False]


def test_overlap_floor_of_one_is_refused():
    from mining.config import load_config
    from mining.errors import ConfigError

    with pytest.raises(ConfigError, match="overlap_floor"):
        load_config(None, ["select.overlap_floor=1.0"])


def test_unknown_overlap_is_refused():
    from mining.errors import ConfigError

    with pytest.raises(ConfigError, match="overlap"):
        pairwise_overlap([_tube(0, _moving(0, 0, 10, 10, n=1))], 0.1, "ioa")


# --------------------------------------------------------------------------- rendered


def test_rendered_car_keeps_its_tube_and_loses_its_wheel_corner():
    """Synthetic "alongside" scene at half resolution, 5 frames; tubes from the truth masks of
    every object seen in all of them, and a part tube: the car's truth mask in the lower
    quarter of its box's rows and the outer quarter of its columns (where a wheel is)."""
    cv2.setNumThreads(1)
    src = SyntheticSource(n_frames=5, scenario="alongside", width=621, height=188, fx=360.77)
    plan = src.plan("0000")
    frames = [src.read_frame(plan, i).truth.objects for i in range(5)]
    seen = {o.track_id for o in frames[0] if all(
        any(p.track_id == o.track_id and p.mask.sum() >= 200 for p in f) for f in frames)}
    masks = {tid: [next(o.mask for o in f if o.track_id == tid) for f in frames] for tid in sorted(seen)}
    nearest = max(masks, key=lambda tid: masks[tid][0].sum())
    parts = []
    for m in masks[nearest]:
        ys, xs = np.nonzero(m)
        region = np.zeros_like(m)
        region[ys.max() - (ys.max() - ys.min()) // 4:, : xs.min() + (xs.max() - xs.min()) // 4 + 1] = True
        parts.append(m & region)
    assert all(p.sum() > 50 for p in parts)
    tubes = [_tube(i, ms) for i, ms in enumerate(masks.values())] + [_tube(len(masks), parts)]
    scores = np.array([CAR] * len(masks) + [PART])
    assert len(masks) >= 3  # the car, its neighbour ahead, parked cars
    assert co_select(tubes, scores, IOU).tolist() == [True] * (len(masks) + 1)  # REFERENCE keeps the part
    assert co_select(tubes, scores, MIN).tolist() == [True] * len(masks) + [False]
