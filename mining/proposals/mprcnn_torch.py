"""Image-level mask proposals from MP R-CNN, the paper's proposer, on torchvision's Mask R-CNN.

MP R-CNN (paper §3.1) is a Mask R-CNN (ResNet-50 FPN here: torchvision's
``maskrcnn_resnet50_fpn``) whose classification part only tells objects from background, plus
a second classification head over background + the 80 COCO classes. At test time the
category-agnostic head gives each proposal its confidence and the second head its class
posterior. This module runs torchvision's own modules (transform, backbone, RPN, RoI pooling,
box head, box coder, mask head, mask pasting) and does the decoding itself, because
torchvision's post-processing does per-class NMS and drops the background:

* objectness = 1 − p(background) of the objectness head's softmax;
* one row per RoI: its box (and mask) from the regression (mask channel) of its most probable
  of the 80 classes, or from the single "object" row of a category-agnostic head;
* low-confidence rows are kept on purpose (``score_threshold``): generic proposals live on recall;
* class-agnostic NMS (``torchvision.ops.nms`` over all classes at once, frame by frame), ranked
  by the objectness log-odds (which, unlike objectness in float32, does not saturate at 1), at
  most ``max_proposals`` per frame, best first;
* masks from the mask head for the kept boxes only, pasted at frame size, thresholded,
  run-length encoded from the crop; a proposal whose mask comes out empty is dropped.

Class posterior over the 80 COCO classes + unknown, from the class head's 81-way softmax
[background, 80 classes]: the 80 class probabilities are columns 0..79, and the background
probability is the unknown mass (column 80). That is the original implementation's
``second_posterior`` (index 0 = background, see shared/data/proposals_4dgvt_format) and the
paper's unknown test: where the category-agnostic head says "object" but the 80-class head
says "background", the object is of none of the 80 classes. ``unknown_mass = "none"``
instead renormalises the 80 class probabilities (unknown 0).

Weights (never bundled or downloaded; ``torch.load(weights_only=True)``, nothing is
unpickled) come in one of three layouts, told apart by their keys and shapes:

* **torchvision**: the state dict of ``maskrcnn_resnet50_fpn`` with its 91-way COCO head
  (``roi_heads.box_predictor.cls_score`` (91, 1024): background + COCO category ids 1..90, of
  which 10 ids are unused gaps; ``bbox_pred`` (364, 1024); ``mask_fcn_logits`` (91, 256, 1, 1)),
  e.g. torchvision's released COCO Mask R-CNN file. It is read through
  ``torchvision_to_two_head``: the single head plays both parts.
* **two-head** (MP R-CNN): every key of ``maskrcnn_resnet50_fpn`` except the box predictor's
  and the mask predictor's last layer, plus:

  ====================================================  =============  =====================================
  key                                                   shape          meaning
  ====================================================  =============  =====================================
  roi_heads.box_predictor.objectness.weight / .bias     (1+M, 1024)    category-agnostic head: softmax, row 0
                                                                       background, rows 1..M object; M = 1
                                                                       when trained category-agnostic (the
                                                                       paper), M = 90 when converted
  roi_heads.box_predictor.cls_score.weight / .bias      (81, 1024)     class head: row 0 background, rows
                                                                       1..80 the COCO classes in
                                                                       mining.formats.coco order
  roi_heads.box_predictor.bbox_pred.weight / .bias      (4·C, 1024)    box deltas; C = 2 (background,
                                                                       object: category-agnostic) or C = 81
                                                                       (per class, class-head order)
  roi_heads.mask_predictor.mask_fcn_logits.weight/.bias (C, 256, 1, 1) mask logits, same C as bbox_pred
  ====================================================  =============  =====================================

* **class-agnostic**: a Mask R-CNN trained with two classes, background and "object" — the
  torchvision layout with ``num_classes=2`` (``cls_score`` (2, 1024), ``bbox_pred`` (8, 1024),
  ``mask_fcn_logits`` (2, 256, 1, 1)), or the two-head layout without ``cls_score`` (its
  objectness head (2, 1024) and C = 2). Objectness = p(object) of that head; no class head, so
  **posterior None**: in a union with a classifier ("onnx+torch") the class comes from the
  classifier's rows (mining/proposals/union.py), and ``unknown_mass`` does not apply. A research
  group's class-agnostic Mask R-CNN (as the paper trains MP R-CNN's first head) plugs in so.

``torchvision_to_two_head`` maps the 91-way head onto that layout exactly: the objectness
head is the whole 91-way classifier (p(object) = the mass of all 90 foreground outputs), the
class head its background row and the rows of the 80 used COCO ids (``COCO_CATEGORY_IDS``),
box deltas and mask channels the same rows. The 10 unused ids had no training examples; they
count toward objectness (as 1 − p(background) of torchvision's softmax) and are left out of
the class posterior. A torchvision checkpoint and its conversion give the same proposals.

The backbone's batch norm runs with ``batch_norm_eps`` (0, as torchvision runs its COCO
weights); a state dict with or without ``*.num_batches_tracked`` entries loads alike.
"""

from __future__ import annotations

import re
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from mining.errors import ConfigError, InputError
from mining.files import check_regular
from mining.formats.coco import COCO_CATEGORY_IDS
from mining.masks import crop_rle
from mining.proposals.config import ProposalConfig, TorchConfig
from mining.proposals.registry import ModelBatch
from mining.types import N_CLASSES, Proposals

try:
    import torch
    import torchvision
    from torch import nn
    from torchvision.models.detection import maskrcnn_resnet50_fpn
    from torchvision.models.detection.mask_rcnn import MaskRCNNPredictor
    from torchvision.models.detection.roi_heads import paste_masks_in_image
    from torchvision.models.detection.transform import resize_boxes
    from torchvision.ops import clip_boxes_to_image, nms, remove_small_boxes
except ImportError as e:  # the extra is not installed
    raise ConfigError(f"the torch proposer needs PyTorch and torchvision ({e}): install the extra, "
                      "pip install -e .[torch]") from e

PROPOSER_NAME = "torch"
N_TORCHVISION = 91  # torchvision's COCO head: background + COCO category ids 1..90 (ten ids unused)
N_CLASS_HEAD = 81  # MP R-CNN's class head: background + the 80 COCO classes
BOX_HEAD_DIM = 1024  # TwoMLPHead representation size of maskrcnn_resnet50_fpn
MASK_HEAD_DIM = 256  # mask head channels of maskrcnn_resnet50_fpn
MIN_BOX_SIDE = 1e-2  # torchvision's remove_small_boxes cut in postprocess_detections, pixels
PASTE_CHUNK = 32  # masks pasted at frame size at a time (32 × 375 × 1242 float32 ≈ 60 MB)
PREDICTOR = "roi_heads.box_predictor."
MASK_LOGITS = "roi_heads.mask_predictor.mask_fcn_logits."
# Row of each two-head class-head output in torchvision's 91-way head: background, then the 80 used ids.
CLASS_ROWS = (0, *COCO_CATEGORY_IDS)


class TwoHeadPredictor(nn.Module):
    """MP R-CNN's box predictor: a category-agnostic objectness head, an 81-way class head
    (background + 80 COCO classes; absent in a class-agnostic model) and box deltas for C = 2
    (agnostic) or 81 classes."""

    def __init__(self, in_channels: int, n_objectness: int, n_box_classes: int, class_head: bool = True):
        super().__init__()
        self.objectness = nn.Linear(in_channels, n_objectness)
        self.cls_score = nn.Linear(in_channels, N_CLASS_HEAD) if class_head else None
        self.bbox_pred = nn.Linear(in_channels, 4 * n_box_classes)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
        x = x.flatten(start_dim=1)
        return self.objectness(x), None if self.cls_score is None else self.cls_score(x), self.bbox_pred(x)


def is_two_head(state: Mapping[str, torch.Tensor]) -> bool:
    return PREDICTOR + "objectness.weight" in state


def is_class_agnostic_torchvision(state: Mapping[str, torch.Tensor]) -> bool:
    """torchvision's layout trained with num_classes=2 (background, object)."""
    w = state.get(PREDICTOR + "cls_score.weight")
    return not is_two_head(state) and w is not None and w.ndim == 2 and w.shape[0] == 2


def agnostic_to_two_head(state: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """A num_classes=2 torchvision state dict → the two-head layout without class head: its
    (background, object) classifier is the objectness head; box deltas and masks stay."""
    out = {k: v for k, v in state.items() if not k.startswith(PREDICTOR + "cls_score.")}
    for part in ("weight", "bias"):
        out[PREDICTOR + f"objectness.{part}"] = state[PREDICTOR + f"cls_score.{part}"]
    return out


def torchvision_to_two_head(state: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """torchvision's 91-class Mask R-CNN state dict → the two-head layout (module docstring), exactly."""
    cls_w = state.get(PREDICTOR + "cls_score.weight")
    if cls_w is None or cls_w.ndim != 2 or cls_w.shape[0] != N_TORCHVISION:
        shape = None if cls_w is None else tuple(cls_w.shape)
        raise ValueError(f"{PREDICTOR}cls_score.weight: expected ({N_TORCHVISION}, {BOX_HEAD_DIM}) "
                         f"(torchvision's COCO Mask R-CNN), got {shape}")
    rows = torch.tensor(CLASS_ROWS)
    box_rows = (4 * rows[:, None] + torch.arange(4)).reshape(-1)  # the 4 deltas of each class row
    out = {k: v for k, v in state.items() if not k.startswith(PREDICTOR) and not k.startswith(MASK_LOGITS)}
    for part in ("weight", "bias"):
        cls = state[PREDICTOR + f"cls_score.{part}"]
        out[PREDICTOR + f"objectness.{part}"] = cls.clone()
        out[PREDICTOR + f"cls_score.{part}"] = cls[rows].clone()
        out[PREDICTOR + f"bbox_pred.{part}"] = state[PREDICTOR + f"bbox_pred.{part}"][box_rows].clone()
        out[MASK_LOGITS + part] = state[MASK_LOGITS + part][rows].clone()
    return out


def read_checkpoint(path: str | Path) -> dict[str, torch.Tensor]:
    """A state dict from ``path`` (``torch.load``, weights only: tensors and plain containers)."""
    p = Path(path).expanduser()
    if not check_regular(p).is_file():  # a FIFO is named as one, not as missing
        raise ConfigError(f"file {p}: proposals.torch.model_path: no such file")
    try:
        obj = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:  # pickle, zip and tensor errors alike: the file is not a weights-only state dict
        raise ConfigError(f"file {p}: not a readable PyTorch state dict (torch.load, weights only): "
                          f"{type(e).__name__}: {e}") from None
    if isinstance(obj, Mapping) and len(obj) == 1 and next(iter(obj)) in ("model", "state_dict"):
        obj = next(iter(obj.values()))  # a checkpoint that wraps the state dict
    if not (isinstance(obj, Mapping) and obj and all(isinstance(k, str) and isinstance(v, torch.Tensor)
                                                     for k, v in obj.items())):
        raise ConfigError(f"file {p}: expected a state dict (parameter name → tensor), got {type(obj).__name__}")
    return dict(obj)


def build_model(state: Mapping[str, torch.Tensor], cfg: TorchConfig, path: str | Path) -> nn.Module:
    """maskrcnn_resnet50_fpn with MP R-CNN's heads, sized by and loaded from a state dict in either layout."""
    try:
        if is_two_head(state):
            two = dict(state)
        elif is_class_agnostic_torchvision(state):
            two = agnostic_to_two_head(state)
        else:
            two = torchvision_to_two_head(state)
        class_head = PREDICTOR + "cls_score.weight" in two
        n_obj = two[PREDICTOR + "objectness.weight"].shape[0]
        n_box = two[PREDICTOR + "bbox_pred.weight"].shape[0] // 4
        n_mask = two[MASK_LOGITS + "weight"].shape[0]
    except (KeyError, ValueError) as e:
        raise ConfigError(f"file {path}: not a maskrcnn_resnet50_fpn state dict in the torchvision or two-head "
                          f"layout: {e}") from None
    if n_obj < 2 or n_box not in (2, N_CLASS_HEAD) or n_mask != n_box:
        raise ConfigError(f"file {path}: two-head layout needs objectness rows ≥ 2 and bbox_pred / mask_fcn_logits "
                          f"for the same C ∈ {{2, 81}} classes; got objectness {n_obj}, bbox_pred {n_box}, "
                          f"mask {n_mask}")
    if not class_head and (n_obj != 2 or n_box != 2):
        raise ConfigError(f"file {path}: a class-agnostic Mask R-CNN (no 81-way class head) needs 2 classes "
                          f"(background, object) in its classifier, bbox_pred and mask_fcn_logits; got "
                          f"classifier {n_obj}, bbox_pred {n_box}, mask {n_mask}")
    model = maskrcnn_resnet50_fpn(
        weights=None, weights_backbone=None, num_classes=n_box, min_size=cfg.min_size, max_size=cfg.max_size,
        rpn_pre_nms_top_n_test=cfg.rpn_pre_nms_top_n, rpn_post_nms_top_n_test=cfg.rpn_post_nms_top_n)
    model.roi_heads.box_predictor = TwoHeadPredictor(BOX_HEAD_DIM, n_obj, n_box, class_head)
    model.roi_heads.mask_predictor = MaskRCNNPredictor(MASK_HEAD_DIM, MASK_HEAD_DIM, n_mask)
    try:
        missing, unexpected = model.load_state_dict(two, strict=False)
    except RuntimeError as e:  # shape mismatches
        raise ConfigError(f"file {path}: does not fit maskrcnn_resnet50_fpn: {e}") from None
    missing = [k for k in missing if not k.endswith("num_batches_tracked")]
    if missing or unexpected:
        raise ConfigError(f"file {path}: does not fit maskrcnn_resnet50_fpn: missing keys {missing[:5]}"
                          f"{' …' if len(missing) > 5 else ''}, unexpected keys {unexpected[:5]}"
                          f"{' …' if len(unexpected) > 5 else ''}")
    for m in model.modules():
        if isinstance(m, (nn.BatchNorm2d, torchvision.ops.FrozenBatchNorm2d)):
            m.eps = cfg.batch_norm_eps
    return model.eval()


def resolve_device(name: str) -> torch.device:
    """``"auto"`` → CUDA when present, else the CPU; ``"cpu"``, ``"cuda"``, ``"cuda:N"`` as given."""
    if not re.fullmatch(r"auto|cpu|cuda(:\d+)?", name):
        raise ConfigError(f"proposals.torch.device: 'auto', 'cpu', 'cuda' or 'cuda:N', got {name!r}")
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"proposals.torch.device={name!r}, but this torch sees no CUDA device")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ConfigError(f"proposals.torch.device={name!r}: only {torch.cuda.device_count()} CUDA device(s)")
    return dev


def _check(cfg: TorchConfig) -> None:
    bad = []
    if cfg.batch_size < 1:
        bad.append(f"batch_size {cfg.batch_size} < 1")
    if not 0.0 <= cfg.score_threshold <= 1.0:
        bad.append(f"score_threshold {cfg.score_threshold} outside [0, 1]")
    if not 0.0 < cfg.nms_iou <= 1.0:
        bad.append(f"nms_iou {cfg.nms_iou} outside (0, 1]")
    if not 0.0 < cfg.mask_threshold < 1.0:
        bad.append(f"mask_threshold {cfg.mask_threshold} outside (0, 1)")
    if cfg.max_proposals < 1 or cfg.rpn_pre_nms_top_n < 1 or cfg.rpn_post_nms_top_n < 1:
        bad.append("max_proposals, rpn_pre_nms_top_n and rpn_post_nms_top_n must be ≥ 1")
    if not 0 < cfg.min_size <= cfg.max_size:
        bad.append(f"need 0 < min_size ≤ max_size, got {cfg.min_size}, {cfg.max_size}")
    if cfg.unknown_mass not in ("background", "none"):
        bad.append(f"unknown_mass {cfg.unknown_mass!r} is not 'background' or 'none'")
    if cfg.num_threads < 0:
        bad.append(f"num_threads {cfg.num_threads} < 0")
    if bad:
        raise ConfigError("proposals.torch: " + "; ".join(bad))


def class_posterior(cls_prob: np.ndarray, unknown_mass: str) -> np.ndarray:
    """(N, 81) class-head softmax [background, 80 classes] → (N, 81) posterior [80 classes, unknown]."""
    p = np.asarray(cls_prob, np.float64)
    if unknown_mass == "background":
        full = np.concatenate([p[:, 1:], p[:, :1]], axis=1)
    else:
        full = np.concatenate([p[:, 1:], np.zeros((len(p), 1))], axis=1)
    return (full / full.sum(axis=1, keepdims=True)).astype(np.float32)


class TorchProposer:
    """Loads MP R-CNN once (a long-lived worker: a Ray actor) and turns frames into ``Proposals``.

    ``proposer(frame, image)`` does one frame; ``propose_batch(frames, images)`` runs
    ``batch_size`` frames per forward pass and gives the same proposals.
    """

    def __init__(self, cfg: TorchConfig):
        if not cfg.model_path:
            raise ConfigError("proposals.torch.model_path is empty: give the path of a maskrcnn_resnet50_fpn state "
                              "dict (torchvision's COCO Mask R-CNN weights or the two-head layout; none are bundled)")
        _check(cfg)
        self.cfg = cfg
        self.model_path = Path(cfg.model_path).expanduser()
        self.device = resolve_device(cfg.device)
        if cfg.num_threads and self.device.type == "cpu":
            torch.set_num_threads(cfg.num_threads)
        if cfg.precision == "fp16" and self.device.type != "cuda":
            raise ConfigError(f"proposals.torch.precision='fp16' needs a CUDA device; the proposer runs on "
                              f"{self.device} (proposals.torch.device={cfg.device!r})")
        self.model = build_model(read_checkpoint(self.model_path), cfg, self.model_path).to(self.device)
        self.last_timings_ms: dict[str, float] = {}

    def __call__(self, frame: int, image: np.ndarray) -> Proposals:
        return self.propose_batch([frame], [image])[0]

    def propose_batch(self, frames: Sequence[int], images: Sequence[np.ndarray]) -> list[Proposals]:
        """Proposals of each frame, ``batch_size`` frames per forward pass."""
        if len(frames) != len(images):
            raise ValueError(f"{len(frames)} frame indices for {len(images)} images")
        for frame, image in zip(frames, images):
            if not (isinstance(image, np.ndarray) and image.ndim == 3 and image.shape[2] == 3
                    and image.dtype == np.uint8):
                shape = getattr(image, "shape", None)
                raise InputError(f"expected an (H, W, 3) uint8 RGB image, got {shape} {getattr(image, 'dtype', '')}",
                                 frame=frame)
        out: list[Proposals] = []
        b = self.cfg.batch_size
        # fp16: the network in half precision where autocast allows it; its heads' outputs return to float32.
        half = torch.autocast("cuda", dtype=torch.float16, enabled=self.cfg.precision == "fp16")
        for s in range(0, len(frames), b):
            with half:
                out.extend(self._forward(list(frames[s:s + b]), list(images[s:s + b])))
        return out

    @torch.inference_mode()
    def _forward(self, frames: list[int], images: list[np.ndarray]) -> list[Proposals]:
        cfg, model, dev = self.cfg, self.model, self.device
        rh = model.roi_heads
        t0 = time.perf_counter()
        tensors = [torch.from_numpy(np.ascontiguousarray(im)).to(dev).permute(2, 0, 1).float().div_(255.0)
                   for im in images]
        batch, _ = model.transform(tensors)
        features = model.backbone(batch.tensors)
        rois, _ = model.rpn(batch, features)
        t1 = time.perf_counter()
        x = rh.box_head(rh.box_roi_pool(features, rois, batch.image_sizes))
        obj_logits, cls_logits, deltas = rh.box_predictor(x)
        # float() is a no-op in fp32; under fp16 autocast the heads' outputs come back to float32 here.
        obj_logits, deltas = obj_logits.float(), deltas.float()
        cls_logits = None if cls_logits is None else cls_logits.float()
        # log p(object) − log p(background): ranks like objectness but does not saturate at 1 in float32.
        log_odds = torch.logsumexp(obj_logits[:, 1:], dim=1) - obj_logits[:, 0]
        objectness = torch.sigmoid(log_odds)  # = 1 − p(background)
        cls_prob = None if cls_logits is None else torch.softmax(cls_logits, dim=1)  # None: class-agnostic
        n_box = deltas.shape[1] // 4
        # The class whose regression (and mask) a RoI uses: its most probable of the 80, or "object".
        if n_box == N_CLASS_HEAD and cls_prob is not None:
            channel = 1 + cls_prob[:, 1:].argmax(dim=1)
        else:
            channel = torch.ones(len(obj_logits), dtype=torch.long, device=dev)
        decoded = rh.box_coder.decode(deltas, rois)  # (R, C, 4) in resized-image pixels
        boxes_in = decoded[torch.arange(len(channel), device=dev), channel]
        # Clip in the resized image, then work in frame pixels (NMS there, so the stored boxes keep the IoU bound).
        boxes, frame_boxes, which = [], [], []
        for i, (b, hw, im) in enumerate(zip(boxes_in.split([len(r) for r in rois]), batch.image_sizes, images)):
            b = clip_boxes_to_image(b, hw)
            boxes.append(b)
            frame_boxes.append(clip_boxes_to_image(resize_boxes(b, list(hw), list(im.shape[:2])), im.shape[:2]))
            which.append(torch.full((len(b),), i, dtype=torch.long, device=dev))
        boxes, frame_boxes, which = torch.cat(boxes), torch.cat(frame_boxes), torch.cat(which)
        kept = []
        for i in range(len(images)):  # frame by frame, so a frame's proposals do not depend on its batch
            cand = torch.nonzero((which == i) & (objectness >= cfg.score_threshold)).squeeze(1)
            cand = cand[remove_small_boxes(frame_boxes[cand], MIN_BOX_SIDE)]
            kept.append(cand[nms(frame_boxes[cand], log_odds[cand], cfg.nms_iou)][:cfg.max_proposals])  # best first
        t2 = time.perf_counter()
        sel = torch.cat(kept)
        masks = torch.zeros((0, 28, 28), device=dev)
        if len(sel):
            mf = rh.mask_head(rh.mask_roi_pool(features, [boxes[k] for k in kept], batch.image_sizes))
            logits = rh.mask_predictor(mf).float()  # (K, C, 28, 28)
            mch = channel[sel] if logits.shape[1] == N_CLASS_HEAD else torch.ones_like(sel)
            masks = logits[torch.arange(len(sel), device=dev), mch].sigmoid()
        t3 = time.perf_counter()
        out, start = [], 0
        cls_np = None if cls_prob is None else cls_prob[sel].double().cpu().numpy()
        obj_np = objectness[sel].cpu().numpy().astype(np.float32)
        for i, (frame, image, k) in enumerate(zip(frames, images, kept)):
            n = len(k)
            rles, ok = _encode(masks[start:start + n], frame_boxes[k], image.shape[:2], cfg.mask_threshold)
            rows = start + ok
            out.append(Proposals(
                frame=frame,
                rles=rles,
                boxes=frame_boxes[k][torch.as_tensor(ok, device=dev)].cpu().numpy().astype(np.float32).reshape(-1, 4),
                objectness=obj_np[rows],
                posterior=(None if cls_np is None else class_posterior(cls_np[rows], cfg.unknown_mass) if len(rows)
                           else np.zeros((0, N_CLASSES), np.float32)),
                proposer=[PROPOSER_NAME] * len(rows),
            ))
            start += n
        t4 = time.perf_counter()
        self.last_timings_ms = {"backbone_rpn": 1e3 * (t1 - t0), "box_head_nms": 1e3 * (t2 - t1),
                                "mask_head": 1e3 * (t3 - t2), "paste_encode": 1e3 * (t4 - t3)}
        return out


def _encode(masks: torch.Tensor, boxes: torch.Tensor, frame_hw: tuple[int, int],
            threshold: float) -> tuple[list[dict], np.ndarray]:
    """Frame-size COCO RLEs of (K, 28, 28) mask probabilities in their boxes, and the rows kept
    (a mask that comes out empty is dropped: it cannot be localised in 3D)."""
    H, W = frame_hw
    rles, ok = [], []
    for s in range(0, len(masks), PASTE_CHUNK):
        pasted = paste_masks_in_image(masks[s:s + PASTE_CHUNK, None], boxes[s:s + PASTE_CHUNK], (H, W))[:, 0]
        binary = (pasted >= threshold).cpu().numpy()
        for j, m in enumerate(binary):
            rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
            if rows.size == 0:
                continue
            y0, y1, x0, x1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
            rles.append(crop_rle(m[y0:y1, x0:x1], int(x0), int(y0), H, W))
            ok.append(s + j)
    return rles, np.asarray(ok, np.int64)


def torch_model(cfg: ProposalConfig, frame_size: tuple[int, int]) -> ModelBatch:
    """The registry's factory of ``torch`` (``proposals.torch``; the frame size plays no part):
    ``batch_size`` frames per forward pass."""
    mprcnn = TorchProposer(cfg.torch)
    return lambda frames, images: [[p] for p in mprcnn.propose_batch(frames, images)]
