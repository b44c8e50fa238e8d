"""The ONNX YOLO-seg proposer on real KITTI frames with the shared (user-provided) model.

The project bundles no weights; these tests use ../shared/models/yolov8n-seg_int8.onnx.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from pycocotools import mask as mask_utils

from conftest import MODEL
from mining.boxes import box_iou
from mining.errors import ConfigError, InputError
from mining.formats.kitti_tracking import read_kitti_tracking
from mining.masks import crop_rle
from mining.proposals.config import OnnxConfig
from mining.proposals.onnx_convert import anchor_grid, converted_model, convert_to_float
from mining.proposals.onnx_yolo import OnnxProposer
from mining.proposals.yolo_seg import decode_predictions, letterbox_image, plan_letterbox

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")



@pytest.fixture(scope="module")
def model_path():
    if not MODEL.is_file():
        pytest.skip(f"shared model not present at {MODEL}")
    return MODEL


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("onnx_cache")


@pytest.fixture(scope="module")
def frames(kitti_tracking_root):
    out = []
    for i in range(16):
        bgr = cv2.imread(str(kitti_tracking_root / "training" / "image_02" / "0005" / f"{i:06d}.png"))
        assert bgr is not None
        out.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    return out


@pytest.fixture(scope="module")
def cars(kitti_tracking_root):
    gt = read_kitti_tracking(kitti_tracking_root / "training" / "label_02" / "0005.txt")
    return [gt.box[(gt.frame == i) & (gt.type == "Car")] for i in range(16)]


def _cfg(model_path, cache_dir, **kw) -> OnnxConfig:
    return OnnxConfig(model_path=str(model_path), cache_dir=str(cache_dir), **kw)


@pytest.fixture(scope="module")
def full_proposer(model_path, cache_dir):
    return OnnxProposer(_cfg(model_path, cache_dir), frame_size=(375, 1242))


@pytest.fixture(scope="module")
def square_proposer(model_path, cache_dir):
    return OnnxProposer(_cfg(model_path, cache_dir, input_height=320, input_width=320))


def test_converted_graph_is_float_at_the_new_size(model_path, tmp_path):
    dst = convert_to_float(model_path, tmp_path / "m.onnx", 384, 1248)
    m = onnx.load(str(dst))
    ops = {n.op_type for n in m.graph.node}
    assert not ops & {"ConvInteger", "DynamicQuantizeLinear", "Cast"}
    assert "Conv" in ops
    dims = [d.dim_value for d in m.graph.input[0].type.tensor_type.shape.dim]
    assert dims == [1, 3, 384, 1248]
    sess = ort.InferenceSession(str(dst), providers=["CPUExecutionProvider"])
    n_anchors = sum((384 // s) * (1248 // s) for s in (8, 16, 32))
    out0, out1 = sess.run(None, {"images": np.full((1, 3, 384, 1248), 0.45, np.float32)})
    assert out0.shape == (1, 116, n_anchors) and out1.shape == (1, 32, 96, 312)
    # The anchor grid inside the graph is the one decoding assumes: stride 8 first, row-major.
    grid, strides = anchor_grid(384, 1248, [8, 16, 32])
    consts = {t.name: onnx.numpy_helper.to_array(t) for t in m.graph.initializer}
    assert any(a.shape == (1, 2, n_anchors) and np.array_equal(a[0], grid) for a in consts.values())
    assert any(a.shape == (1, n_anchors) and np.array_equal(a[0], strides) for a in consts.values())


def test_every_float_conv_reproduces_its_int8_chain(model_path, square_proposer, frames):
    """Exactness of step 1: fed the same quantised activations, each float Conv equals its
    DynamicQuantizeLinear → ConvInteger → Cast → Mul chain up to float rounding."""
    from onnx import helper

    converted = onnx.load(str(square_proposer.converted_paths[(320, 320)]))
    float_inits = {t.name: t for t in converted.graph.initializer}
    float_convs = {n.output[0]: n for n in converted.graph.node if n.op_type == "Conv"}
    m = onnx.load(str(model_path))
    g = m.graph
    producer = {o: n for n in g.node for o in n.output}
    consumer = {i: n for n in g.node for i in n.input}
    extra, pairs = [], []
    for n in [n for n in g.node if n.op_type == "ConvInteger"]:
        chain_out = consumer[consumer[n.output[0]].output[0]].output[0]  # ConvInteger → Cast → Mul
        fc = float_convs[chain_out]
        dql = producer[n.input[0]]
        extra.append(helper.make_node("DequantizeLinear", list(dql.output), [chain_out + "_deq"]))
        g.initializer.append(float_inits[fc.input[1]])
        attrs = {a.name: helper.get_attribute_value(a) for a in fc.attribute}
        extra.append(helper.make_node("Conv", [chain_out + "_deq", fc.input[1]], [chain_out + "_float"], **attrs))
        pairs.append((chain_out, chain_out + "_float"))
    g.node.extend(extra)
    for a, b in pairs:
        g.output.extend([helper.make_tensor_value_info(x, onnx.TensorProto.FLOAT, None) for x in (a, b)])
    assert len(pairs) == 76
    sess = ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"])
    lb = plan_letterbox(square_proposer.cfg, frames[0].shape[:2])
    names = [x for pair in pairs for x in pair]
    out = dict(zip(names, sess.run(names, {"images": letterbox_image(frames[0], lb, 114)})))
    for a, b in pairs:
        scale = np.abs(out[a]).max()
        assert np.abs(out[a] - out[b]).max() <= 1e-5 * scale, a


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_float_model_agrees_with_int8_at_320(model_path, square_proposer, frames):
    """Same input, same decoding: predictions of the int8 and the converted float model match.

    The int8 model quantises activations at run time, so outputs differ slightly (measured on
    frames 0–15: confident anchors' box IoU ≥ 0.86, same class, score within 0.09).
    """
    cfg = dataclasses.replace(square_proposer.cfg, score_threshold=0.1, nms_iou=0.5)
    int8 = ort.InferenceSession(str(model_path), providers=["CPUExecutionProvider"])
    n_confident = n_sure = n_matched = 0
    for i in range(4, 16):
        pred_f, protos_f, lb = square_proposer.raw_outputs(frames[i])
        pred_q, protos_q = (o[0] for o in int8.run(None, {"images": letterbox_image(frames[i], lb, cfg.pad_value)}))
        # Anchor by anchor, wherever either model is confident.
        conf = np.maximum(pred_f[4:84].max(0), pred_q[4:84].max(0)) >= 0.15
        n_confident += int(conf.sum())
        boxes = [np.column_stack([p[:2, conf].T - p[2:4, conf].T / 2, p[:2, conf].T + p[2:4, conf].T / 2])
                 for p in (pred_f, pred_q)]
        assert (np.diag(box_iou(boxes[0].astype(float), boxes[1].astype(float))) >= 0.8).all()
        assert (pred_f[4:84, conf].argmax(0) == pred_q[4:84, conf].argmax(0)).all()
        assert np.abs(pred_f[4:84, conf].max(0) - pred_q[4:84, conf].max(0)).max() < 0.15
        # Detections after NMS: a box near an NMS decision may flip, nearly all must match.
        a = decode_predictions(i, pred_q, protos_q, lb, frames[i].shape[:2], cfg)
        b = decode_predictions(i, pred_f, protos_f, lb, frames[i].shape[:2], cfg)
        for x, y in ((a, b), (b, a)):
            sure = x.objectness >= 0.15
            n_sure += int(sure.sum())
            if sure.any() and len(y):
                iou = box_iou(x.boxes[sure].astype(float), y.boxes.astype(float))
                same = x.posterior[sure].argmax(1) == y.posterior[iou.argmax(1)].argmax(1)
                n_matched += int(((iou.max(1) >= 0.8) & same).sum())
    assert n_confident >= 50
    assert n_matched >= 0.9 * n_sure and n_sure >= 40


def _recall(proposer, frames, cars, iou_min, score_min=0.0) -> float:
    hit = total = 0
    for i in range(4):
        p = proposer(i, frames[i])
        keep = p.objectness >= score_min
        total += len(cars[i])
        if keep.any():
            hit += int((box_iou(cars[i], p.boxes[keep].astype(float)).max(1) >= iou_min).sum())
    return hit / total


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_full_aspect_finds_far_more_cars_than_320(full_proposer, square_proposer, frames, cars):
    # Measured on frames 0–3 (12 cars): full aspect 1.00 / 1.00; 320 letterbox 0.17 (IoU 0.7) and
    # 0.00 (score ≥ 0.25). At IoU 0.5 with every proposal down to score 0.01 both reach 1.00:
    # loose low-score boxes from the 320 model overlap the cars, but they are not localised.
    full_tight = _recall(full_proposer, frames, cars, 0.7)
    square_tight = _recall(square_proposer, frames, cars, 0.7)
    full_sure = _recall(full_proposer, frames, cars, 0.5, score_min=0.25)
    square_sure = _recall(square_proposer, frames, cars, 0.5, score_min=0.25)
    assert full_tight >= 0.9 and full_sure >= 0.9
    assert full_tight >= square_tight + 0.5
    assert full_sure >= square_sure + 0.5
    assert _recall(full_proposer, frames, cars, 0.5) >= 0.9


def test_proposals_are_valid(full_proposer, frames):
    # What every proposer keeps (shapes, dtypes, ranges, order, canonical RLEs): tests/test_proposals_contract.py.
    cfg = full_proposer.cfg
    p = full_proposer(3, frames[3])
    n = len(p)
    assert 0 < n <= cfg.max_proposals
    assert (p.objectness >= cfg.score_threshold).all()
    # Unknown mass grows as confidence drops: the most confident proposal has the least.
    assert p.posterior[0, 80] <= p.posterior[-1, 80]
    # Class-agnostic NMS: no kept pair overlaps more than nms_iou.
    iou = box_iou(p.boxes.astype(float), p.boxes.astype(float))
    np.fill_diagonal(iou, 0)
    assert iou.max() <= cfg.nms_iou + 1e-6
    boxes_of_masks = mask_utils.toBbox(p.rles)  # x, y, w, h of each mask
    for rle, box, mbox in zip(p.rles, p.boxes, boxes_of_masks):
        assert mask_utils.decode(rle).any()
        # Every mask pixel's centre lies inside the box.
        x, y, w, h = mbox
        assert x + 0.5 >= box[0] - 1e-3 and x + w - 0.5 <= box[2] + 1e-3
        assert y + 0.5 >= box[1] - 1e-3 and y + h - 0.5 <= box[3] + 1e-3


def test_car_masks_cover_their_cars(full_proposer, frames, cars):
    """The best proposal for each ground-truth car is a car-shaped mask filling much of the box."""
    p = full_proposer(0, frames[0])
    iou = box_iou(cars[0], p.boxes.astype(float))
    for j in iou.argmax(1):
        x1, y1, x2, y2 = p.boxes[j]
        fill = mask_utils.area(p.rles[j]) / ((x2 - x1) * (y2 - y1))
        assert 0.4 < fill <= 1.0
        assert p.posterior[j].argmax() == 2  # COCO "car"


def test_max_proposals_caps_the_best(model_path, cache_dir, full_proposer, frames):
    few = OnnxProposer(_cfg(model_path, cache_dir, max_proposals=5), frame_size=(375, 1242))(1, frames[1])
    everything = full_proposer(1, frames[1])
    assert 0 < len(few) <= 5
    np.testing.assert_array_equal(few.objectness, everything.objectness[:len(few)])


def test_crop_rle_runs_across_columns(frames):
    """A crop spanning the full height joins runs across column ends, as Fortran order does."""
    grey = cv2.cvtColor(frames[0], cv2.COLOR_RGB2GRAY)
    crop = grey[:, 300:420] > 90
    full = np.zeros(grey.shape, np.uint8)
    full[:, 300:420] = crop
    assert crop[0].any() and crop[-1].any()  # the case under test occurs in this crop
    assert crop_rle(crop, 300, 0, *grey.shape)["counts"] == mask_utils.encode(np.asfortranarray(full))["counts"]


def test_conversion_is_cached(model_path, tmp_path):
    a = converted_model(model_path, tmp_path, 320, 640)
    stamp = a.stat().st_mtime_ns
    b = converted_model(model_path, tmp_path, 320, 640)
    assert a == b and b.stat().st_mtime_ns == stamp
    assert converted_model(model_path, tmp_path, 320, 320) != a


def test_letterbox_plan():
    auto = plan_letterbox(OnnxConfig(), (375, 1242))
    assert auto.input_hw == (384, 1248) and auto.scale == 1.0 and (auto.pad_x, auto.pad_y) == (3, 4)
    big = plan_letterbox(OnnxConfig(), (960, 1280 * 2))
    assert big.input_hw[1] == 1280 and big.input_hw[0] % 32 == 0
    sq = plan_letterbox(OnnxConfig(input_height=320, input_width=320), (375, 1242))
    assert sq.resized_hw == (97, 320) and sq.pad_y == 111
    with pytest.raises(ConfigError):
        plan_letterbox(OnnxConfig(input_height=100, input_width=320), (375, 1242))


def test_missing_model_names_the_path(tmp_path):
    missing = tmp_path / "no_such_model.onnx"
    with pytest.raises(InputError, match="no_such_model.onnx"):
        OnnxProposer(OnnxConfig(model_path=str(missing), cache_dir=str(tmp_path)))
    with pytest.raises(ConfigError, match="model_path"):
        OnnxProposer(OnnxConfig(model_path=""))


def test_unreadable_model_names_the_path(tmp_path, kitti_tracking_root):
    # A real file that is not an ONNX model: a KITTI label file.
    bogus = tmp_path / "labels.onnx"
    bogus.write_bytes((kitti_tracking_root / "training" / "label_02" / "0005.txt").read_bytes())
    with pytest.raises(InputError, match="labels.onnx"):
        convert_to_float(bogus, tmp_path / "out.onnx", 320, 320)


def test_bad_image_names_the_frame(full_proposer, frames):
    with pytest.raises(InputError, match="frame 7"):
        full_proposer(7, frames[0][:, :, 0])
