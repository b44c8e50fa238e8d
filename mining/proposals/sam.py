"""Class-agnostic automatic masks from a SAM-family model through onnxruntime (``sam`` proposer).

**The GPU worker's proposer.** SAM prompts its mask decoder with a regular grid of points, so its
cost grows with the grid: with real weights 25–50 s a frame on a CPU at SAM's 32×32 grid (1024
decoder prompts), well under a second on a GPU. ``points_per_side`` is part of the contract: 8
(64 prompts), 16 (256) and 32 (1024) cost about 1 : 4 : 16 in decoder runs.

The user brings two ONNX files (none are bundled or downloaded):

* **image encoder**, run once a frame: one input (1, 3, S, S) float32, the frame resized so its
  long side is S (``input_size``, 1024 for SAM and MobileSAM), normalised with ImageNet's mean
  (123.675, 116.28, 103.53) and std (58.395, 57.12, 57.375) on 0–255 RGB and zero-padded at the
  bottom and right (SAM's ``Sam.preprocess``); one output, the image embeddings (1, C, S/16, S/16).
  ``sam.image_encoder`` exported as it is (for MobileSAM, its TinyViT encoder the same way).
* **mask decoder**, in the layout of SAM's own ONNX export (``scripts/export_onnx_model.py``):

  ================  ==================  =====================================================
  name              shape               meaning
  ================  ==================  =====================================================
  image_embeddings  (1, C, e, e)        the encoder's output
  point_coords      (B, P, 2)           prompt points in resized-input pixels (x, y); here each
                                        prompt is one grid point plus SAM's padding point (0, 0)
  point_labels      (B, P)              1 foreground, −1 padding
  mask_input        (1, 1, 4e, 4e)      zeros (no mask prompt)
  has_mask_input    (1,)                0
  orig_im_size      (2,)                the size ``masks`` is upsampled to: here the frame's
                                        aspect at the low-res side (4e), as ``masks`` is not read
  masks             (B, M, h, w)        not read: onnxruntime computes every output of the graph,
                                        and at the frame's (H, W) a batch of 64 prompts × 4 masks
                                        would be 480 MB of KITTI logits; low_res_masks is upsampled
                                        here for the masks that pass the IoU filter only
  iou_predictions   (B, M)              predicted mask IoU
  low_res_masks     (B, M, 4e, 4e)      mask logits
  ================  ==================  =====================================================

  B is 1 in SAM's export (only the point count is dynamic): one decoder run per grid point. An
  export with a symbolic B takes ``points_per_batch`` prompts a run. M = 4 (SAM's export without
  ``--return-single-mask``: the single-mask token, then the three multimask outputs, of which the
  automatic generator uses the three, as here), 3 (those three) or 1 (``--return-single-mask``).

Automatic mask generation, with SAM's ``SamAutomaticMaskGenerator`` defaults (``[proposals.sam]``):
a ``points_per_side``² grid at cell centres; masks with predicted IoU < ``pred_iou_thresh``
dropped; logits upsampled as SAM's postprocessing does (bilinear to S×S, crop to the resized frame,
bilinear to the frame); stability score = |logits > offset| / |logits > −offset| <
``stability_score_thresh`` dropped; mask = logits > 0; box NMS at ``box_nms_thresh`` over all
masks by predicted IoU; with ``min_region_area`` > 0, holes and islands below it removed (SAM's
``min_mask_region_area``), then NMS again. Only the grid's single full-frame crop is run (SAM's
``crop_n_layers`` = 0, its default).

Output: objectness = the predicted IoU clipped to [0, 1] (the model's own mask-quality score),
sorted, at most ``max_proposals``; boxes the masks' tight pixel boxes; posterior None (SAM names
no class: in a union with a classifier the class comes from it, mining/proposals/union.py).
"""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np

from mining.boxes import nms_keep
from mining.errors import ConfigError, InputError
from mining.files import check_regular
from mining.masks import crop_rle
from mining.proposals.config import ProposalConfig, SamConfig
from mining.proposals.registry import ModelBatch
from mining.types import Proposals

PROPOSER_NAME = "sam"
PIXEL_MEAN = np.array([123.675, 116.28, 103.53], np.float32)  # SAM (Sam.pixel_mean): ImageNet mean on 0–255
PIXEL_STD = np.array([58.395, 57.12, 57.375], np.float32)  # SAM (Sam.pixel_std): ImageNet std on 0–255
MASK_THRESHOLD = 0.0  # SAM (Sam.mask_threshold): a pixel is in the mask where its logit is above 0
DECODER_INPUTS = ("image_embeddings", "point_coords", "point_labels", "mask_input", "has_mask_input", "orig_im_size")
DECODER_OUTPUTS = ("iou_predictions", "low_res_masks")  # read; "masks" is left to onnxruntime to skip


def point_grid(points_per_side: int) -> np.ndarray:
    """(n², 2) points (x, y) in [0, 1]: cell centres of an n × n grid, x fastest (SAM's build_point_grid)."""
    c = (np.arange(points_per_side) + 0.5) / points_per_side
    xx, yy = np.meshgrid(c, c)
    return np.column_stack([xx.ravel(), yy.ravel()])


def resized_hw(frame_hw: tuple[int, int], size: int) -> tuple[int, int]:
    """The frame's size with its long side resized to ``size`` (SAM's ResizeLongestSide, rounding half up)."""
    H, W = frame_hw
    scale = size / max(H, W)
    return int(H * scale + 0.5), int(W * scale + 0.5)


def preprocess(image: np.ndarray, size: int) -> np.ndarray:
    """(H, W, 3) uint8 RGB → (1, 3, S, S) float32: resized, normalised, zero-padded bottom-right."""
    nh, nw = resized_hw(image.shape[:2], size)
    interp = cv2.INTER_AREA if nh < image.shape[0] else cv2.INTER_LINEAR  # area averaging when shrinking
    resized = cv2.resize(image, (nw, nh), interpolation=interp).astype(np.float32)
    out = np.zeros((size, size, 3), np.float32)
    out[:nh, :nw] = (resized - PIXEL_MEAN) / PIXEL_STD
    return out.transpose(2, 0, 1)[None]


def upscale_logits(low: np.ndarray, size: int, frame_hw: tuple[int, int]) -> np.ndarray:
    """(L, L) low-res logits → (H, W) frame logits, as SAM's postprocessing (bilinear, half-pixel centres)."""
    H, W = frame_hw
    nh, nw = resized_hw(frame_hw, size)
    square = cv2.resize(low, (size, size), interpolation=cv2.INTER_LINEAR)
    return cv2.resize(square[:nh, :nw], (W, H), interpolation=cv2.INTER_LINEAR)


def stability_score(logits: np.ndarray, offset: float) -> float:
    """IoU of the masks at logit cuts +offset and −offset (SAM's calculate_stability_score); 0 when both are empty."""
    union = int(np.count_nonzero(logits > MASK_THRESHOLD - offset))
    return int(np.count_nonzero(logits > MASK_THRESHOLD + offset)) / union if union else 0.0


def remove_small_regions(mask: np.ndarray, min_area: int) -> np.ndarray:
    """Fill holes and drop islands smaller than ``min_area`` pixels (SAM's remove_small_regions, both modes)."""
    out = mask.copy()
    for fill in (True, False):  # holes first, then islands, as SAM's postprocess_small_regions
        work = (~out if fill else out).astype(np.uint8)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(work, connectivity=8)
        small = [i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] < min_area]
        if small:
            out = out | np.isin(labels, small) if fill else out & ~np.isin(labels, small)
    return out


def _providers(device: str) -> list[str]:
    import onnxruntime as ort

    cuda = "CUDAExecutionProvider" in ort.get_available_providers()
    if device == "cuda" and not cuda:
        raise ConfigError("proposals.sam.device='cuda', but this onnxruntime has no CUDA provider "
                          "(install onnxruntime-gpu on the GPU workers, or set device='cpu')")
    if device == "cpu" or not cuda:
        return ["CPUExecutionProvider"]
    return ["CUDAExecutionProvider", "CPUExecutionProvider"]


def _dims(arg) -> list[int | None]:
    """Declared dimensions of an onnxruntime input or output: ints, None where symbolic."""
    return [d if isinstance(d, int) else None for d in (arg.shape or [])]


class SamProposer:
    """Loads both models once (a long-lived worker, best a GPU one) and turns frames into ``Proposals``."""

    def __init__(self, cfg: SamConfig):
        for key in ("encoder_path", "decoder_path"):
            if not getattr(cfg, key):
                raise ConfigError(f"proposals.sam.{key} is empty: give the SAM image encoder and mask decoder "
                                  f"ONNX files (weights are not bundled)")
        self.cfg = cfg
        self.encoder_path = Path(cfg.encoder_path).expanduser()
        self.decoder_path = Path(cfg.decoder_path).expanduser()
        for key, p in (("encoder_path", self.encoder_path), ("decoder_path", self.decoder_path)):
            if not check_regular(p).is_file():  # a FIFO is named as one, not as missing
                raise InputError(f"SAM ONNX file not found (proposals.sam.{key})", p)
        self.providers = _providers(cfg.device)
        self.encoder = self._load(self.encoder_path, "image encoder")
        self.decoder = self._load(self.decoder_path, "mask decoder")
        self._check_encoder()
        self._check_decoder()
        self.last_timings_ms: dict[str, float] = {}

    def _load(self, path: Path, what: str):
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = self.cfg.intra_op_num_threads
        opts.inter_op_num_threads = 1
        opts.log_severity_level = 3  # unused initialisers of exports are not worth a warning per worker
        try:
            return ort.InferenceSession(str(path), opts, providers=self.providers)
        except Exception as e:  # onnxruntime's own errors: not a model it can run
            raise InputError(f"SAM {what}: not an ONNX model onnxruntime can load: {e}", path) from None

    def _check_encoder(self) -> None:
        ins, outs = self.encoder.get_inputs(), self.encoder.get_outputs()
        if len(ins) != 1 or len(_dims(ins[0])) != 4:
            raise InputError(f"SAM image encoder: expected one (1, 3, S, S) input, got "
                             f"{[(i.name, i.shape) for i in ins]}", self.encoder_path)
        _, c, h, w = _dims(ins[0])
        if c not in (None, 3) or (h is not None and w is not None and h != w):
            raise InputError(f"SAM image encoder: input {ins[0].name} is {ins[0].shape}, not (1, 3, S, S)",
                             self.encoder_path)
        side = h or w
        if side is not None and side != self.cfg.input_size:
            raise ConfigError(f"file {self.encoder_path}: the SAM image encoder takes {side}×{side} inputs, "
                              f"proposals.sam.input_size is {self.cfg.input_size}")
        if len(outs) < 1 or len(_dims(outs[0])) != 4:
            raise InputError(f"SAM image encoder: expected a (1, C, S/16, S/16) embeddings output, got "
                             f"{[(o.name, o.shape) for o in outs]}", self.encoder_path)
        self.encoder_input = ins[0].name

    def _check_decoder(self) -> None:
        ins = {i.name: i for i in self.decoder.get_inputs()}
        outs = {o.name for o in self.decoder.get_outputs()}
        missing = [n for n in DECODER_INPUTS if n not in ins]
        missing_out = [n for n in DECODER_OUTPUTS if n not in outs]
        if missing or missing_out:
            raise InputError(f"SAM mask decoder: not the official SAM ONNX export layout: missing input(s) "
                             f"{missing}, output(s) {missing_out}; it needs inputs {list(DECODER_INPUTS)} and "
                             f"outputs {list(DECODER_OUTPUTS)}", self.decoder_path)
        extra = sorted(set(ins) - set(DECODER_INPUTS))
        if extra:
            raise InputError(f"SAM mask decoder: inputs {extra} are not in the official export layout", self.decoder_path)
        coords = _dims(ins["point_coords"])
        if len(coords) != 3:
            raise InputError(f"SAM mask decoder: point_coords is {ins['point_coords'].shape}, not (B, P, 2)",
                             self.decoder_path)
        self.batched = coords[0] is None  # SAM's own export fixes B = 1: one point a run
        mask_in = _dims(ins["mask_input"])
        self.mask_input_hw = tuple(mask_in[2:]) if len(mask_in) == 4 and None not in mask_in[2:] else None

    def points(self, frame_hw: tuple[int, int]) -> np.ndarray:
        """The prompt grid in resized-input pixels (x, y), as SAM's predictor transforms it."""
        nh, nw = resized_hw(frame_hw, self.cfg.input_size)
        return (point_grid(self.cfg.points_per_side) * [nw, nh]).astype(np.float32)

    def __call__(self, frame: int, image: np.ndarray) -> Proposals:
        if not (isinstance(image, np.ndarray) and image.ndim == 3 and image.shape[2] == 3 and image.dtype == np.uint8):
            shape = getattr(image, "shape", None)
            raise InputError(f"expected an (H, W, 3) uint8 RGB image, got {shape} {getattr(image, 'dtype', '')}",
                             frame=frame)
        cfg, H, W = self.cfg, image.shape[0], image.shape[1]
        t0 = time.perf_counter()
        try:
            emb = self.encoder.run(None, {self.encoder_input: preprocess(image, cfg.input_size)})[0]
        except Exception as e:  # onnxruntime: the file's graph does not take what its contract says
            raise InputError(f"SAM image encoder failed: {e}", self.encoder_path, frame) from None
        t1 = time.perf_counter()
        side = 4 * emb.shape[-1]
        mask_hw = self.mask_input_hw or (side, side)
        fixed = {"image_embeddings": emb, "mask_input": np.zeros((1, 1, *mask_hw), np.float32),
                 "has_mask_input": np.zeros(1, np.float32),
                 # masks (not read) is computed at orig_im_size all the same: the frame's aspect at the
                 # low-res side keeps it as small as low_res_masks (at (H, W) it costs more than the rest)
                 "orig_im_size": np.array(resized_hw((H, W), side), np.float32)}
        pts = self.points((H, W))
        step = cfg.points_per_batch if self.batched else 1
        rles, boxes, scores = [], [], []
        t_dec = 0.0
        for s in range(0, len(pts), step):
            chunk = pts[s:s + step]
            coords = np.stack([chunk, np.zeros_like(chunk)], axis=1)  # each grid point and SAM's padding point
            labels = np.tile(np.array([[1.0, -1.0]], np.float32), (len(chunk), 1))
            td = time.perf_counter()
            try:
                iou, low = self.decoder.run(list(DECODER_OUTPUTS), {**fixed, "point_coords": coords,
                                                                    "point_labels": labels})
            except Exception as e:
                raise InputError(f"SAM mask decoder failed: {e}", self.decoder_path, frame) from None
            t_dec += time.perf_counter() - td
            if iou.ndim != 2 or low.ndim != 4 or low.shape[:2] != iou.shape or iou.shape[0] != len(chunk):
                raise InputError(f"SAM mask decoder: outputs iou_predictions {iou.shape} and low_res_masks {low.shape} "
                                 f"are not (B, M) and (B, M, 4e, 4e) for B = {len(chunk)}", self.decoder_path, frame)
            if iou.shape[1] == 4:  # single-mask token first, then the multimask outputs the generator uses
                iou, low = iou[:, 1:], low[:, 1:]
            for b, m in zip(*np.nonzero(iou >= cfg.pred_iou_thresh)):
                logits = upscale_logits(low[b, m], cfg.input_size, (H, W))
                if stability_score(logits, cfg.stability_score_offset) < cfg.stability_score_thresh:
                    continue
                mask = logits > MASK_THRESHOLD
                box = _tight_box(mask)
                if box is None:
                    continue
                rles.append(_rle(mask, box))
                boxes.append(box)
                scores.append(float(iou[b, m]))
        t2 = time.perf_counter()
        out = self._select(frame, rles, np.asarray(boxes, np.float64).reshape(-1, 4), np.asarray(scores), (H, W))
        self.last_timings_ms = {"encoder": 1e3 * (t1 - t0), "decoder": 1e3 * t_dec,
                                "masks": 1e3 * (t2 - t1 - t_dec), "nms": 1e3 * (time.perf_counter() - t2)}
        return out

    def _select(self, frame: int, rles: list[dict], boxes: np.ndarray, scores: np.ndarray,
                frame_hw: tuple[int, int]) -> Proposals:
        cfg = self.cfg
        # nms_keep's top_k cuts before suppressing (OpenCV): every mask takes part, the cut comes after.
        keep = nms_keep(boxes, scores, cfg.box_nms_thresh, len(rles)) if len(rles) else np.zeros(0, np.int64)
        if cfg.min_region_area <= 0:
            keep = keep[:cfg.max_proposals]
        rles, boxes, scores = [rles[i] for i in keep], boxes[keep], scores[keep]
        if cfg.min_region_area > 0:
            from pycocotools import mask as mask_utils

            cleaned = []
            for i, rle in enumerate(rles):
                mask = remove_small_regions(mask_utils.decode(rle).astype(bool), cfg.min_region_area)
                box = _tight_box(mask)
                if box is not None:
                    cleaned.append((_rle(mask, box), box, scores[i]))
            rles = [c[0] for c in cleaned]
            boxes = np.asarray([c[1] for c in cleaned], np.float64).reshape(-1, 4)
            scores = np.asarray([c[2] for c in cleaned])
            keep = nms_keep(boxes, scores, cfg.box_nms_thresh, len(rles))[:cfg.max_proposals] if len(rles) else keep[:0]
            rles, boxes, scores = [rles[i] for i in keep], boxes[keep], scores[keep]
        return Proposals(frame=frame, rles=rles, boxes=boxes.astype(np.float32).reshape(-1, 4),
                         objectness=np.clip(scores, 0.0, 1.0).astype(np.float32), posterior=None,
                         proposer=[PROPOSER_NAME] * len(rles))


def _tight_box(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """x1, y1, x2, y2 pixel edges of a mask's pixels (x2, y2 exclusive); None when empty."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return None
    return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1


def _rle(mask: np.ndarray, box: tuple[int, int, int, int]) -> dict:
    x0, y0, x1, y1 = box
    return crop_rle(mask[y0:y1, x0:x1], x0, y0, *mask.shape)


def sam_model(cfg: ProposalConfig, frame_size: tuple[int, int]) -> ModelBatch:
    """The registry's factory of ``sam`` (``proposals.sam``; the frame size plays no part): one frame at a time."""
    sam = SamProposer(cfg.sam)
    return lambda frames, images: [[sam(f, im)] for f, im in zip(frames, images)]
