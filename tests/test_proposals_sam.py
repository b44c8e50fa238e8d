"""The ``sam`` proposer's contract (SAM-family automatic masks), on a real KITTI 0005 frame.

conftest's ``sam_models`` are tiny random-weight graphs in SAM's layouts (tests/_tiny_models.py):
an image encoder (1, 3, 128, 128) → (1, 8, 8, 8) and mask decoders with the official export's
inputs and outputs, one with a symbolic prompt batch and one with SAM's fixed B = 1. Their masks
are blobs around each prompt point: the grid, filters, upsampling, NMS and output are under
test, not accuracy.
"""

from __future__ import annotations

import numpy as np
import pytest
from pycocotools import mask as mask_utils

from conftest import TINY_SAM_SIZE, kitti_0005_stereo
from mining.boxes import box_iou
from mining.errors import ConfigError, InputError
from mining.proposals.config import SamConfig
from mining.proposals.sam import (PIXEL_MEAN, PIXEL_STD, SamProposer, point_grid, preprocess, remove_small_regions,
                                  resized_hw, stability_score, upscale_logits)

ort = pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")

GRID = 8  # points per side in these tests (SAM's default is 32)


@pytest.fixture(scope="module")
def frame(kitti_tracking_root):
    left, _, _ = kitti_0005_stereo(kitti_tracking_root, 1)
    return left[0]


def _cfg(models, decoder="decoder", **kw) -> SamConfig:
    base = {"input_size": TINY_SAM_SIZE, "points_per_side": GRID, "device": "cpu"}
    return SamConfig(encoder_path=str(models["encoder"]), decoder_path=str(models[decoder]), **{**base, **kw})


@pytest.fixture(scope="module")
def proposer(sam_models):
    return SamProposer(_cfg(sam_models))


@pytest.fixture(scope="module")
def everything(proposer, frame):
    return proposer(2, frame)


def test_output_contract(proposer, everything, frame):
    cfg, p = proposer.cfg, everything
    H, W = frame.shape[:2]
    n = len(p)
    assert proposer.batched and 0 < n <= cfg.max_proposals and p.frame == 2
    assert p.proposer == ["sam"] * n and p.posterior is None and p.class_weight is None
    assert p.objectness.dtype == np.float32 and (np.diff(p.objectness) <= 0).all()
    assert ((p.objectness >= cfg.pred_iou_thresh) & (p.objectness <= 1)).all()
    # Boxes are the masks' tight pixel boxes, inside the frame.
    assert p.boxes.shape == (n, 4) and p.boxes.dtype == np.float32
    x, y, w, h = mask_utils.toBbox(p.rles).T
    np.testing.assert_array_equal(p.boxes, np.column_stack([x, y, x + w, y + h]).astype(np.float32))
    assert (p.boxes[:, [0, 2]] <= W).all() and (p.boxes[:, [1, 3]] <= H).all() and (p.boxes >= 0).all()
    assert all(list(r["size"]) == [H, W] for r in p.rles) and (mask_utils.area(p.rles) > 0).all()
    iou = box_iou(p.boxes.astype(float), p.boxes.astype(float))
    np.fill_diagonal(iou, 0)
    assert iou.max() <= cfg.box_nms_thresh + 1e-6


def test_point_grid_is_sams(proposer, frame):
    np.testing.assert_allclose(point_grid(2), [[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]])
    H, W = frame.shape[:2]
    nh, nw = resized_hw((H, W), TINY_SAM_SIZE)
    assert (nh, nw) == (39, 128)  # 375 × 128 / 1242 = 38.6, rounded half up as ResizeLongestSide does
    pts = proposer.points((H, W))
    assert pts.shape == (GRID * GRID, 2)
    assert pts[:, 0].min() == pytest.approx(nw / (2 * GRID)) and pts[:, 1].max() == pytest.approx(nh * (1 - 0.5 / GRID))


def test_preprocess_normalises_and_pads_bottom_right():
    img = np.full((30, 60, 3), 200, np.uint8)
    x = preprocess(img, 64)
    assert x.shape == (1, 3, 64, 64) and x.dtype == np.float32
    np.testing.assert_allclose(x[0, :, :32, :64].reshape(3, -1).T, np.tile((200 - PIXEL_MEAN) / PIXEL_STD, (32 * 64, 1)),
                               rtol=1e-6)
    assert (x[0, :, 32:, :] == 0).all()


def test_upsampling_matches_the_decoders_own_masks(sam_models, proposer, frame):
    """SAM's postprocessing (to S×S, crop, to the frame) as the graph's ``masks`` output computes it."""
    H, W = frame.shape[:2]
    emb = proposer.encoder.run(None, {"x": preprocess(frame, TINY_SAM_SIZE)})[0]
    dec = ort.InferenceSession(str(sam_models["decoder"]), providers=["CPUExecutionProvider"])
    feeds = {"image_embeddings": emb, "point_coords": np.array([[[30, 20], [0, 0]], [[90, 5], [0, 0]]], np.float32),
             "point_labels": np.array([[1, -1], [1, -1]], np.float32), "mask_input": np.zeros((1, 1, 32, 32), np.float32),
             "has_mask_input": np.zeros(1, np.float32), "orig_im_size": np.array([H, W], np.float32)}
    masks, _, low = dec.run(None, feeds)
    for b in range(2):
        for m in range(4):
            up = upscale_logits(low[b, m], TINY_SAM_SIZE, (H, W))
            assert np.abs(up - masks[b, m]).max() <= 1e-5 * np.abs(masks[b, m]).max()


def test_official_export_one_point_a_run_gives_the_same_proposals(sam_models, everything, frame):
    single = SamProposer(_cfg(sam_models, "decoder_b1"))
    assert not single.batched
    p = single(2, frame)
    assert p.rles == everything.rles
    np.testing.assert_array_equal(p.objectness, everything.objectness)
    np.testing.assert_array_equal(p.boxes, everything.boxes)


def test_filters_and_max_proposals_cut(sam_models, proposer, everything, frame):
    strict = SamProposer(_cfg(sam_models, pred_iou_thresh=0.95))(2, frame)
    assert 0 < len(strict) < len(everything) and (strict.objectness >= 0.95).all()
    few = SamProposer(_cfg(sam_models, max_proposals=3))(2, frame)
    assert few.rles == everything.rles[:3]
    loose = SamProposer(_cfg(sam_models, stability_score_thresh=0.0))(2, frame)
    assert len(loose) >= len(everything)
    cleaned = SamProposer(_cfg(sam_models, min_region_area=400))(2, frame)
    assert 0 < len(cleaned) and (mask_utils.area(cleaned.rles) > 0).all()
    assert (np.diff(cleaned.objectness) <= 0).all()
    coarse = SamProposer(_cfg(sam_models, points_per_side=4))(2, frame)
    assert 0 < len(coarse) <= len(everything)


def test_stability_score_and_small_regions():
    logits = np.tile(np.arange(-5.0, 5.0, 1.0, dtype=np.float32), (4, 1))  # a ramp: 3 of 10 columns > 1, 5 > −1
    assert stability_score(logits, 1.0) == pytest.approx(3 / 5)
    assert stability_score(np.full((3, 3), -9.0, np.float32), 1.0) == 0.0
    m = np.zeros((20, 20), bool)
    m[2:15, 2:15] = True
    m[6, 6] = False  # a 1-pixel hole
    m[18, 18] = True  # a 1-pixel island
    out = remove_small_regions(m, 5)
    assert out[6, 6] and not out[18, 18] and out.sum() == 13 * 13


def test_bad_files_and_settings_name_the_file_and_the_reason(sam_models, tmp_path, frame):
    from _tiny_models import sam_decoder_onnx

    with pytest.raises(ConfigError, match="proposals.sam.encoder_path is empty"):
        SamProposer(SamConfig())
    with pytest.raises(InputError, match="absent.onnx"):
        SamProposer(SamConfig(encoder_path=str(tmp_path / "absent.onnx"), decoder_path=str(sam_models["decoder"])))
    no_size = sam_decoder_onnx(tmp_path / "no_orig_size.onnx", TINY_SAM_SIZE, drop_input="orig_im_size")
    with pytest.raises(InputError, match=r"no_orig_size.onnx.*missing input\(s\) \['orig_im_size'\]"):
        SamProposer(_cfg({**sam_models, "decoder": no_size}))
    with pytest.raises(InputError, match=r"encoder.onnx.*missing input"):  # the encoder given as decoder
        SamProposer(_cfg({**sam_models, "decoder": sam_models["encoder"]}))
    with pytest.raises(InputError, match=r"decoder.onnx.*image encoder: expected one \(1, 3, S, S\) input"):
        SamProposer(_cfg({**sam_models, "encoder": sam_models["decoder"]}))
    with pytest.raises(ConfigError, match=r"encoder.onnx.*128×128.*input_size is 1024"):
        SamProposer(_cfg(sam_models, input_size=1024))
    bogus = tmp_path / "text.onnx"
    bogus.write_text("not a model")
    with pytest.raises(InputError, match="text.onnx"):
        SamProposer(_cfg({**sam_models, "decoder": bogus}))
    wide = sam_decoder_onnx(tmp_path / "wide.onnx", 2 * TINY_SAM_SIZE)  # embeddings 16×16, the encoder gives 8×8
    with pytest.raises(InputError, match=r"wide.onnx, frame 4: SAM mask decoder failed"):
        SamProposer(_cfg({**sam_models, "decoder": wide}))(4, frame)
    if "CUDAExecutionProvider" not in ort.get_available_providers():
        with pytest.raises(ConfigError, match="onnxruntime-gpu"):
            SamProposer(_cfg(sam_models, device="cuda"))
        assert SamProposer(_cfg(sam_models, device="auto")).providers == ["CPUExecutionProvider"]


def test_bench_proposals_times_sams_stages(sam_models, shared_data, tmp_path, capsys):
    """`mine bench proposals` with the sam proposer: per-frame time and its stages for the grid asked."""
    import json

    from mining.cli import main

    settings = ['proposals.proposer="sam"', f'proposals.sam.encoder_path="{sam_models["encoder"].as_posix()}"',
                f'proposals.sam.decoder_path="{sam_models["decoder"].as_posix()}"',
                f"proposals.sam.input_size={TINY_SAM_SIZE}", "proposals.sam.points_per_side=4", 'proposals.sam.device="cpu"']
    args = ["bench", "proposals", "--data", str(shared_data), "--frames", "0:2", "--json", str(tmp_path / "b.json")]
    for s in settings:
        args += ["--set", s]
    assert main(args) == 0
    assert "4×4 grid (16 prompts)" in capsys.readouterr().out
    rows = json.loads((tmp_path / "b.json").read_text())["rows"]
    assert [r["mode"] for r in rows] == ["per frame", "grid 4²"]
    assert set(rows[1]["ms_per_frame"]) == {"encoder", "decoder", "masks", "nms"} and rows[1]["fps"] > 0
