"""The ``fastsam`` proposer's contract, on real KITTI 0005 frames with a tiny random-weight model.

conftest's ``fastsam_model`` is a YOLOv8-seg-layout graph (FastSAM's: one class, 32 coefficients,
prototypes at 1/4, anchors and strides as constants) with random weights: it exercises the input
/ output contract and the resize path (onnx_convert) of a fixed-size export, not accuracy.
"""

from __future__ import annotations

import numpy as np
import pytest
from pycocotools import mask as mask_utils

from conftest import MODEL, kitti_0005_stereo
from mining.boxes import box_iou
from mining.errors import ConfigError, InputError
from mining.proposals.config import FastSamConfig, OnnxConfig, UnionConfig
from mining.proposals.fastsam import FastSamProposer
from mining.proposals.onnx_yolo import OnnxProposer
from mining.proposals.union import detectability, union
from mining.types import UNKNOWN_CLASS

pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

SMALL = {"auto_max_side": 256}  # KITTI 1242×375 runs at 96×256: the tiny model converted to the frame's aspect


@pytest.fixture(scope="module")
def frames(kitti_tracking_root):
    left, _, _ = kitti_0005_stereo(kitti_tracking_root, 2)
    return left


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("fastsam_cache")


def _cfg(model, cache, **kw) -> FastSamConfig:
    return FastSamConfig(model_path=str(model), cache_dir=str(cache), **{**SMALL, **kw})


@pytest.fixture(scope="module")
def proposer(fastsam_model, cache, frames):
    return FastSamProposer(_cfg(fastsam_model, cache), frame_size=frames[0].shape[:2])


def test_output_contract(proposer, frames):
    cfg = proposer.cfg
    H, W = frames[0].shape[:2]
    p = proposer(5, frames[0])
    n = len(p)
    assert 0 < n <= cfg.max_proposals and p.frame == 5
    assert proposer.n_classes == 1 and p.proposer == ["fastsam"] * n
    assert p.posterior is None and p.class_weight is None  # class-agnostic: no class, no evidence weight
    assert p.boxes.shape == (n, 4) and p.boxes.dtype == np.float32
    assert (p.boxes >= 0).all() and (p.boxes[:, [0, 2]] <= W).all() and (p.boxes[:, [1, 3]] <= H).all()
    assert p.objectness.dtype == np.float32 and (np.diff(p.objectness) <= 0).all()
    assert ((p.objectness >= cfg.score_threshold) & (p.objectness <= 1)).all()
    # Objectness is the model's own score: each value is one of its anchors' score-row entries.
    pred, _, _ = proposer.raw_outputs(frames[0])
    assert np.isin(p.objectness, pred[4]).all()
    iou = box_iou(p.boxes.astype(float), p.boxes.astype(float))
    np.fill_diagonal(iou, 0)
    assert iou.max() <= cfg.nms_iou + 1e-6  # class-agnostic NMS at FastSAM's 0.9
    for rle, box, (x, y, w, h) in zip(p.rles, p.boxes, mask_utils.toBbox(p.rles)):
        assert list(rle["size"]) == [H, W] and mask_utils.area(rle) > 0
        # every mask pixel's centre lies inside its box
        assert x + 0.5 >= box[0] - 1e-3 and x + w - 0.5 <= box[2] + 1e-3
        assert y + 0.5 >= box[1] - 1e-3 and y + h - 0.5 <= box[3] + 1e-3


def test_fixed_size_export_runs_as_is_and_other_sizes_are_converted_once(fastsam_model, cache, proposer, frames):
    # "auto" at the frame's aspect: the 64×64 export is rebuilt at 96×256 in the cache.
    assert list(proposer.model_files) == [(96, 256)]
    assert proposer.model_files[(96, 256)].parent == cache
    native = FastSamProposer(_cfg(fastsam_model, cache, input_height=64, input_width=64))
    assert native.model_files == {(64, 64): fastsam_model}  # its own size: the user's file, unconverted
    p = native(0, frames[0])
    assert 0 < len(p) <= native.cfg.max_proposals and p.posterior is None


def test_thresholds_and_max_proposals_cut(fastsam_model, cache, proposer, frames):
    everything = proposer(0, frames[0])
    few = FastSamProposer(_cfg(fastsam_model, cache, max_proposals=5), frame_size=frames[0].shape[:2])(0, frames[0])
    assert len(few) == 5
    np.testing.assert_array_equal(few.objectness, everything.objectness[:5])
    cut = float(everything.objectness[len(everything) // 3])
    high = FastSamProposer(_cfg(fastsam_model, cache, score_threshold=cut), frame_size=frames[0].shape[:2])(0, frames[0])
    assert 0 < len(high) < len(everything) and (high.objectness >= cut).all()


def test_same_frames_same_proposals(fastsam_model, cache, proposer, frames):
    again = FastSamProposer(_cfg(fastsam_model, cache), frame_size=frames[1].shape[:2])
    a, b, c = proposer(1, frames[1]), proposer(1, frames[1]), again(1, frames[1])
    for other in (b, c):
        assert a.rles == other.rles
        np.testing.assert_array_equal(a.boxes, other.boxes)
        np.testing.assert_array_equal(a.objectness, other.objectness)


def test_class_count_comes_from_the_output_shape(tmp_path, cache, frames):
    """Any YOLOv8-seg class count reads: K = rows − 4 − 32; the rows stay class-agnostic here."""
    from _tiny_models import fastsam_onnx

    for k in (3, 80):
        p = FastSamProposer(_cfg(fastsam_onnx(tmp_path / f"k{k}.onnx", n_classes=k), cache,
                                 input_height=64, input_width=64))
        out = p(0, frames[0])
        assert p.n_classes == k and len(out) > 0 and out.posterior is None and set(out.proposer) == {"fastsam"}


def test_bad_files_and_layouts_name_the_file_and_the_reason(tmp_path, cache, frames, kitti_tracking_root):
    from _tiny_models import fastsam_onnx

    with pytest.raises(ConfigError, match="proposals.fastsam.model_path is empty"):
        FastSamProposer(FastSamConfig())
    with pytest.raises(InputError, match="absent.onnx"):
        FastSamProposer(_cfg(tmp_path / "absent.onnx", cache))
    bogus = tmp_path / "labels.onnx"
    bogus.write_bytes((kitti_tracking_root / "training" / "label_02" / "0005.txt").read_bytes())
    with pytest.raises(InputError, match="labels.onnx.*not a readable ONNX model"):
        FastSamProposer(_cfg(bogus, cache))
    few_rows = fastsam_onnx(tmp_path / "few_rows.onnx", n_coeffs=30, proto_channels=32)
    with pytest.raises(InputError, match=r"few_rows.onnx.*35 rows"):
        FastSamProposer(_cfg(few_rows, cache, input_height=64, input_width=64))(0, frames[0])
    protos = fastsam_onnx(tmp_path / "protos.onnx", n_coeffs=16)
    with pytest.raises(InputError, match=r"protos.onnx.*16 channels"):
        FastSamProposer(_cfg(protos, cache, input_height=64, input_width=64))(0, frames[0])
    with pytest.raises(InputError, match="frame 3"):
        FastSamProposer(_cfg(few_rows, cache, input_height=64, input_width=64))(3, frames[0][:, :, 0])


def test_union_with_the_coco_model_gives_agnostic_rows_the_unknown_weighting(fastsam_model, cache, proposer, frames):
    """"onnx+fastsam": the COCO model classifies; FastSAM rows it does not cover count toward unknown,
    weighted by detectability of their height (mining/proposals/union.py)."""
    if not MODEL.is_file():
        pytest.skip(f"shared model not present at {MODEL}")
    coco = OnnxProposer(OnnxConfig(model_path=str(MODEL), cache_dir=str(cache)), frame_size=frames[0].shape[:2])
    cfg = UnionConfig()
    learned, agnostic = coco(0, frames[0]), proposer(0, frames[0])
    p = union([learned, agnostic], cfg.mask_iou, cfg)
    rows = np.array(p.proposer)
    assert set(rows) == {"onnx", "fastsam"} and len(p) <= len(learned) + len(agnostic)
    onnx_rows, fs = rows == "onnx", rows == "fastsam"
    np.testing.assert_allclose(p.posterior[onnx_rows].sum(1), 1.0, atol=1e-5)
    assert (p.class_weights()[onnx_rows] == 1).all()
    assert (p.posterior[fs, UNKNOWN_CLASS] == 1).all() and (p.posterior[fs, :UNKNOWN_CLASS] == 0).all()
    h = p.boxes[fs, 3] - p.boxes[fs, 1]
    np.testing.assert_allclose(p.class_weights()[fs], detectability(h, cfg), rtol=1e-5)
    assert ((p.class_weights()[fs] > 0) & (p.class_weights()[fs] < 1)).all()
