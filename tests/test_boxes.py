"""Box algebra (mining/boxes.py): the fused tube gate and the pair path equal the plain
functions, on the real 4D-GVT proposal boxes of KITTI tracking 0005 (consecutive frames,
as the tube gate sees predictions against observations)."""

from __future__ import annotations

import numpy as np
import pytest

from mining.boxes import box_gates, box_ioa, box_iou, nms_keep, paired_box_iou, size_similarity
from mining.proposals.precomputed import JsonProposals
from mining.tubes.config import TubeConfig

W, H = 1242, 375
FRAMES = range(8)
EPS = np.finfo(float).eps


@pytest.fixture(scope="module")
def frame_boxes(shared_data) -> list[np.ndarray]:
    root = shared_data / "proposals_4dgvt_format" / "kitti_tracking_0005" / "top500"
    reader = JsonProposals(root, image_size=(W, H))
    boxes = [np.asarray(reader(f).boxes, np.float64).reshape(-1, 4) for f in FRAMES]
    assert all(len(b) > 100 for b in boxes)
    return boxes


def _pairs(frame_boxes):
    return [(frame_boxes[t], frame_boxes[t + 1]) for t in range(len(frame_boxes) - 1)]


def test_box_gates_equals_plain_iou_and_similarity(frame_boxes):
    # The fused gate compares inter > t·union and multiplies the ratios in another order;
    # it may differ from the plain test only for a pair within rounding of a threshold.
    cfg = TubeConfig()
    thresholds = [(cfg.gate_box_iou, cfg.gate_size_similarity), (0.1, 0.3), (0.5, 0.8), (0.0, 0.0)]
    n_pairs = n_gated = 0
    for pred, obs in _pairs(frame_boxes):
        iou, sim = box_iou(pred, obs), size_similarity(pred, obs)
        for t_iou, t_sim in thresholds:
            fused = box_gates(pred, obs, t_iou, t_sim)
            plain = (iou > t_iou) & (sim > t_sim)
            differ = fused != plain
            near = (np.abs(iou - t_iou) <= 1e-12) | (np.abs(sim - t_sim) <= 1e-12)
            assert near[differ].all()
            assert differ.sum() <= 1e-4 * differ.size  # and that is rare
            if t_iou == 0 and t_sim == 0:  # inter > 0 and sim > 0: the same test exactly
                assert not differ.any()
            n_pairs += fused.size
            n_gated += int(fused.sum())
    assert n_gated > 1000 and n_gated < n_pairs  # the thresholds cut through real pairs


def test_paired_iou_is_the_full_matrix_bit_for_bit(frame_boxes):
    for pred, obs in _pairs(frame_boxes):
        full = box_iou(pred, obs)
        r, c = np.nonzero(box_gates(pred, obs, 0.1, 0.0))
        assert np.array_equal(paired_box_iou(pred[r], obs[c]), full[r, c])
        assert np.array_equal(paired_box_iou(pred[:, None], obs[None, :]), full)


def test_trackeval_rule_only_changes_empty_boxes(frame_boxes):
    # min_area (TrackEval's epsilon) changes nothing for real boxes, zeroes degenerate ones.
    for pred, obs in _pairs(frame_boxes):
        assert np.array_equal(box_iou(pred, obs, min_area=EPS), box_iou(pred, obs))
    a = np.array([[0.0, 0, 10, 10]])
    tiny = np.array([[0.0, 0, 1e-9, 1e-9], [5, 0, 15, 10]])
    np.testing.assert_array_equal(box_iou(a, tiny, min_area=EPS), [[0.0, 50 / 150]])
    assert box_iou(a, tiny)[0, 0] > 0


def test_ioa_and_degenerate_boxes():
    a = np.array([[0.0, 0, 10, 10], [3, 3, 3, 8]])
    b = np.array([[5.0, 0, 15, 10], [0, 0, 0, 10], [20, 20, 30, 30]])
    np.testing.assert_array_equal(box_ioa(a, b, min_area=EPS), [[0.5, 0.0, 0.0], [0.0, 0.0, 0.0]])
    np.testing.assert_array_equal(box_iou(a, b), [[50 / 150, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert box_iou(a, np.empty((0, 4))).shape == (2, 0)
    assert not box_gates(a, b, 0.0, 0.0)[:, 1].any()  # zero-width boxes never gate


def test_nms_keep_best_first_and_no_kept_pair_overlaps_more_than_the_threshold(frame_boxes):
    boxes = frame_boxes[0]
    scores = np.linspace(0.1, 0.9, len(boxes))[::-1].copy()
    keep = nms_keep(boxes, scores, 0.5, 100)
    assert len(keep) and np.all(np.diff(scores[keep]) <= 0)
    iou = box_iou(boxes[keep], boxes[keep])
    np.fill_diagonal(iou, 0)
    assert iou.max() <= 0.5 + 1e-6
    assert len(nms_keep(boxes, scores, 0.5, 2)) == 2
    assert nms_keep(np.zeros((0, 4)), np.zeros(0), 0.5, 10).shape == (0,)
