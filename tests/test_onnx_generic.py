"""Generic candidates of the COCO ONNX model (mining/proposals/onnx_generic.py): the anchors below the
decoder's score cut, decoded by its own rules, marked "onnx_generic" and class-agnostic."""

from __future__ import annotations

import numpy as np
import pytest
from pycocotools import mask as mask_utils

from mining.config import load_config
from mining.proposals.config import OnnxConfig, OnnxGenericConfig
from mining.proposals.onnx_generic import PROPOSER_NAME, generic_candidates
from mining.proposals.yolo_seg import N_COCO, N_COEFFS, decode_predictions, plan_letterbox

H, W = 96, 160  # a small frame; the model input is the same size (no scaling, no padding)


def _outputs(anchors: list[tuple[tuple[float, float, float, float], float]]) -> tuple[np.ndarray, np.ndarray]:
    """(116, N) predictions with one anchor per (box cx, cy, w, h; best class score) and prototypes that
    make every anchor's mask its whole box (coefficient 1 on a constant positive prototype)."""
    pred = np.zeros((4 + N_COCO + N_COEFFS, len(anchors)), np.float32)
    for j, (box, score) in enumerate(anchors):
        pred[:4, j] = box
        pred[4 + j % N_COCO, j] = score  # a different class per anchor: the class plays no part
        pred[4 + N_COCO, j] = 1.0
    protos = np.zeros((N_COEFFS, H // 4, W // 4), np.float32)
    protos[0] = 5.0
    return pred, protos


def test_generic_candidates_are_the_anchors_below_the_cut_marked_and_class_agnostic():
    onnx = OnnxConfig(model_path="unused")
    lb = plan_letterbox(onnx, (H, W))
    assert lb.input_hw == (H, W) and lb.scale == 1.0
    anchors = [((40, 40, 30, 30), 0.6),     # the decoder's own
               ((110, 50, 20, 40), 0.004),  # a generic candidate
               ((111, 50, 20, 40), 0.003),  # its duplicate: suppressed by the candidates' own NMS
               ((150, 80, 30, 40), 0.002),  # a generic candidate cut by the frame border
               ((20, 80, 10, 10), 0.0005)]  # below min_score: nothing
    pred, protos = _outputs(anchors)
    learned = decode_predictions(3, pred, protos, lb, (H, W), onnx)
    generic = generic_candidates(3, pred, protos, lb, (H, W), onnx, OnnxGenericConfig())
    assert len(learned) == 1 and learned.objectness[0] == pytest.approx(0.6)
    assert len(generic) == 2
    assert generic.proposer == [PROPOSER_NAME] * 2
    assert generic.posterior is None  # class-agnostic: a union weighs them as evidence for "unknown"
    assert generic.frame == 3
    np.testing.assert_allclose(generic.objectness, [0.004, 0.002], rtol=1e-6)  # best first, the model's own score
    b = generic.boxes
    assert (b[:, 0] >= 0).all() and (b[:, 1] >= 0).all() and (b[:, 2] <= W).all() and (b[:, 3] <= H).all()
    np.testing.assert_allclose(b[1], [135, 60, W, H])  # clipped to the frame
    m = mask_utils.decode(generic.rles[1]).astype(bool)
    assert m.shape == (H, W) and m[60:, 135:].all() and not m[:60].any()
    # a stricter min_score drops the weaker ones; NMS off keeps the duplicate
    assert len(generic_candidates(3, pred, protos, lb, (H, W), onnx, OnnxGenericConfig(min_score=0.003))) == 1
    assert len(generic_candidates(3, pred, protos, lb, (H, W), onnx, OnnxGenericConfig(nms_iou=1.0))) == 3


def test_generic_candidates_are_on_by_default_and_can_be_switched_off():
    cfg = load_config(None, [])
    assert cfg.proposals.onnx_generic.enabled is True
    assert load_config(None, ["proposals.onnx_generic.enabled=false"]).proposals.onnx_generic.enabled is False


@pytest.mark.slow  # converts the shared model at a new size and runs it twice (~4 s)
def test_union_with_generic_keeps_the_learned_rows_and_adds_marked_ones(kitti_tracking_root, tmp_path):
    import cv2

    from conftest import MODEL
    from mining.proposals.make import make_proposer
    from mining.proposals.onnx_yolo import OnnxProposer
    from mining.types import FrameGeometry, GroundPlane, StereoCalib, StereoFrame

    if not MODEL.is_file():
        pytest.skip(f"shared model not present at {MODEL}")
    bgr = cv2.imread(str(kitti_tracking_root / "training" / "image_02" / "0005" / "000000.png"))
    rgb = cv2.cvtColor(cv2.resize(bgr, (621, 188), interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB)
    sets = [f"proposals.onnx.model_path={MODEL}", f"proposals.onnx.cache_dir={tmp_path}", "proposals.proposer=onnx"]
    cfg = load_config(None, sets)  # on by default
    calib = StereoCalib(360.0, 360.0, 310.0, 94.0, 0.54, 621, 188)
    frame = StereoFrame("kitti", "0005", 0, 0, rgb, rgb, calib)
    geom = FrameGeometry(0, 0, np.full((188, 621), np.nan, np.float32), np.full((188, 621), np.nan, np.float32),
                         None, None, GroundPlane(None, 0.0, 0, False, "none"))
    both = make_proposer(cfg.proposals, (188, 621))(frame, geom)
    alone = OnnxProposer(cfg.proposals.onnx, frame_size=(188, 621))(0, rgb)
    learned = [i for i, n in enumerate(both.proposer) if n == "onnx"]
    generic = [i for i, n in enumerate(both.proposer) if n == PROPOSER_NAME]
    assert len(learned) == len(alone) and generic  # every learned row stands; generic ones are added
    assert sorted(both.objectness[learned].tolist()) == sorted(alone.objectness.tolist())
    # the union gives the uncovered generic rows "unknown" with a detectability weight, never a COCO class
    assert np.isfinite(both.posterior[generic]).all() and (both.posterior[generic].argmax(axis=1) == 80).all()
    assert (both.objectness[generic] < cfg.proposals.onnx.score_threshold).all()
    off = make_proposer(load_config(None, sets + ["proposals.onnx_generic.enabled=false"]).proposals, (188, 621))(frame, geom)
    assert off.proposer == ["onnx"] * len(alone)  # off: today's proposals, nothing generic
