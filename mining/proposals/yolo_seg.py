"""What the YOLO-seg family's proposers share: the letterbox in, the decoding out, onnxruntime's session.

The ``onnx`` proposer (a COCO YOLO-seg model, ``onnx_yolo``), its generic candidates
(``onnx_generic``) and ``fastsam`` (a one-class YOLOv8-seg network) read one layout: input
(1, 3, h, w) RGB in [0, 1], letterboxed to multiples of 32; output 0 (1, 4 + K + 32, N) per
anchor a box, K class scores and 32 mask coefficients; output 1 (1, 32, h/4, w/4) mask
prototypes. Decoding follows the model card (../shared/models/SOURCES.md, "Decoding"):

* objectness = max class probability (the class outputs are already sigmoids; there is no
  separate objectness), class = argmax;
* low-confidence predictions are kept on purpose: generic proposals live on recall;
* class-agnostic NMS, at most ``max_proposals`` kept, sorted by score;
* mask = sigmoid(coefficients · prototypes), computed only inside the box, mapped from the
  prototype grid (1/4 of the input) to frame pixels in one affine warp (upsampling, padding
  removal and resizing at once), thresholded, and run-length encoded straight from the crop.

Class posterior over the 80 COCO classes + unknown: the sigmoid scores p_1..p_80 are
independent "is it class k" probabilities, not a distribution. The model's confidence that
the object is *some* known class is max p, so u = 1 − max p is the mass left for "none of
the 80", i.e. unknown. posterior = [p_1..p_80, u] / (Σp + u) keeps the ranking and ratios
between known classes, grows the unknown share as the detector grows unsure, and sums to 1.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from mining.boxes import nms_keep
from mining.errors import ConfigError, InputError
from mining.files import check_regular
from mining.masks import crop_rle
from mining.proposals.config import FastSamConfig, OnnxConfig
from mining.types import N_CLASSES, Proposals

N_COCO = 80  # class scores in the model output (rows 4..83)
N_COEFFS = 32  # mask coefficients per anchor (rows 84..115)
SIZE_MULTIPLE = 32  # largest model stride: input sides must be multiples of it
COCO_PROPOSER = "onnx"  # the name a COCO model's rows carry unless the caller names them (onnx_yolo.PROPOSER_NAME)


def default_cache_dir() -> Path:
    """Where converted models are kept by default: the user's cache folder (XDG_CACHE_HOME), tube_miner/onnx."""
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "tube_miner" / "onnx"


def model_file(model_path: str, section: str, what: str, found: str) -> Path:
    """The user's model file of ``proposals.<section>.model_path``: ConfigError where the setting is
    empty (``what`` says what to give), InputError naming the path where no file is there."""
    if not model_path:
        raise ConfigError(f"proposals.{section}.model_path is empty: give the path of {what} (weights are not bundled)")
    path = Path(model_path).expanduser()
    if not check_regular(path).is_file():  # a FIFO is named as one, not as missing
        raise InputError(f"{found} not found (proposals.{section}.model_path)", path)
    return path


def cache_folder(cache_dir: str) -> Path:
    """Where converted or resized models are kept: ``cache_dir``, or ``default_cache_dir()`` where it is ""."""
    return Path(cache_dir).expanduser() if cache_dir else default_cache_dir()


@dataclass(frozen=True)
class Letterbox:
    """Where a frame lands in the model input: resized by ``scale``, offset by the padding."""

    input_hw: tuple[int, int]
    scale: float
    resized_hw: tuple[int, int]
    pad_x: int
    pad_y: int


def plan_letterbox(cfg: OnnxConfig | FastSamConfig, frame_hw: tuple[int, int]) -> Letterbox:
    """Model input size and letterbox placement for frames of size ``frame_hw``."""
    H, W = frame_hw
    size = (cfg.input_height, cfg.input_width)
    if size == ("auto", "auto"):
        scale = min(1.0, cfg.auto_max_side / max(H, W))  # never upsample, cap the long side
        h_in = math.ceil(round(H * scale) / SIZE_MULTIPLE) * SIZE_MULTIPLE
        w_in = math.ceil(round(W * scale) / SIZE_MULTIPLE) * SIZE_MULTIPLE
    elif all(isinstance(s, int) and not isinstance(s, bool) and s > 0 and s % SIZE_MULTIPLE == 0 for s in size):
        h_in, w_in = size
        scale = min(h_in / H, w_in / W)
    else:
        raise ConfigError(f"proposals.onnx input_height/input_width: both 'auto' or both positive multiples of "
                          f"{SIZE_MULTIPLE}, got {size!r}")
    nh, nw = min(h_in, round(H * scale)), min(w_in, round(W * scale))
    return Letterbox((h_in, w_in), scale, (nh, nw), (w_in - nw) // 2, (h_in - nh) // 2)


def letterbox_image(image: np.ndarray, lb: Letterbox, pad_value: int) -> np.ndarray:
    """(H, W, 3) uint8 RGB → (1, 3, h, w) float32 in [0, 1], as the model expects."""
    h_in, w_in = lb.input_hw
    nh, nw = lb.resized_hw
    canvas = np.full((h_in, w_in, 3), pad_value, np.uint8)
    resized = image if image.shape[:2] == (nh, nw) else cv2.resize(image, (nw, nh), interpolation=cv2.INTER_LINEAR)
    canvas[lb.pad_y:lb.pad_y + nh, lb.pad_x:lb.pad_x + nw] = resized
    return (canvas.transpose(2, 0, 1)[None].astype(np.float32)) * np.float32(1.0 / 255.0)


def check_image(frame: int, image: np.ndarray) -> None:
    """InputError naming the frame unless ``image`` is an (H, W, 3) uint8 RGB array."""
    if not (isinstance(image, np.ndarray) and image.ndim == 3 and image.shape[2] == 3 and image.dtype == np.uint8):
        shape = getattr(image, "shape", None)
        raise InputError(f"expected an (H, W, 3) uint8 RGB image, got {shape} {getattr(image, 'dtype', '')}",
                         frame=frame)


def execution_providers(device: str) -> list[str]:
    """onnxruntime's providers for ``proposals.onnx.device``: "cpu"; "cuda" (refused by name where
    this onnxruntime has no CUDA provider); "auto" = CUDA where it has one, else the CPU."""
    import onnxruntime as ort

    have = ort.get_available_providers()
    if device == "cpu":
        return ["CPUExecutionProvider"]
    if device == "cuda" and "CUDAExecutionProvider" not in have:
        raise ConfigError("proposals.onnx.device='cuda', but this onnxruntime has no CUDA provider "
                          f"(it has {', '.join(have)}): install onnxruntime-gpu")
    if device in ("cuda", "auto"):
        return (["CUDAExecutionProvider"] if "CUDAExecutionProvider" in have else []) + ["CPUExecutionProvider"]
    raise ConfigError(f"proposals.onnx.device: 'cpu', 'cuda' or 'auto', got {device!r}")


def new_session(path: Path, intra_op_num_threads: int, providers: list[str]):
    """An onnxruntime session as the family runs one: ``intra_op_num_threads`` threads within an
    operator, one across, operators in sequence (Ray parallelises over actors)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = intra_op_num_threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    return ort.InferenceSession(str(path), opts, providers=providers)


def class_posterior(probs: np.ndarray) -> np.ndarray:
    """(N, 80) sigmoid class scores → (N, 81) distribution with unknown mass 1 − max p (see module doc)."""
    p = np.asarray(probs, np.float64)
    u = 1.0 - p.max(axis=1, keepdims=True)
    full = np.concatenate([p, u], axis=1)
    return (full / full.sum(axis=1, keepdims=True)).astype(np.float32)


def decode_predictions(frame: int, pred: np.ndarray, protos: np.ndarray, lb: Letterbox,
                       frame_hw: tuple[int, int], cfg: OnnxConfig | FastSamConfig, n_classes: int = N_COCO,
                       name: str = COCO_PROPOSER) -> Proposals:
    """Network outputs → Proposals in frame pixels: threshold, class-agnostic NMS, masks, posterior.

    ``pred`` has 4 box rows, ``n_classes`` class-score rows and 32 coefficient rows. The 81-way
    posterior needs the 80 COCO classes; with any other class count (FastSAM's one "object" class)
    the rows are class-agnostic: objectness the best class score, posterior None.
    """
    H, W = frame_hw
    probs = pred[4:4 + n_classes].T  # (N, n_classes)
    score = probs.max(axis=1)
    cand = np.nonzero(score >= cfg.score_threshold)[0]
    cxcywh = pred[:4, cand].T.astype(np.float64)
    boxes = np.column_stack([cxcywh[:, :2] - cxcywh[:, 2:] / 2, cxcywh[:, :2] + cxcywh[:, 2:] / 2])
    boxes -= [lb.pad_x, lb.pad_y, lb.pad_x, lb.pad_y]
    boxes /= lb.scale
    boxes = np.clip(boxes, 0, [W, H, W, H])
    # NMS on the clipped frame boxes, so the kept set satisfies the IoU bound as stored.
    keep = nms_keep(boxes, score[cand], cfg.nms_iou, cfg.max_proposals)
    idx, boxes = cand[keep], boxes[keep]
    coeffs = pred[4 + n_classes:4 + n_classes + N_COEFFS, idx].T
    rles, kept = _masks(coeffs, protos, boxes, lb, frame_hw, cfg.mask_threshold)
    idx, boxes = idx[kept], boxes[kept]
    return Proposals(
        frame=frame,
        rles=rles,
        boxes=boxes.astype(np.float32).reshape(-1, 4),
        objectness=score[idx].astype(np.float32),
        posterior=None if n_classes != N_COCO else
        class_posterior(probs[idx]) if len(idx) else np.zeros((0, N_CLASSES), np.float32),
        proposer=[name] * len(idx),
    )


def _masks(coeffs: np.ndarray, protos: np.ndarray, boxes: np.ndarray, lb: Letterbox,
           frame_hw: tuple[int, int], mask_threshold: float) -> tuple[list[dict], np.ndarray]:
    """RLE masks of the kept boxes; proposals whose mask comes out empty are dropped (they
    cannot be localised in 3D)."""
    H, W = frame_hw
    c, hp, wp = protos.shape
    ps = lb.input_hw[0] / hp  # prototype stride in input pixels (4)
    # Frame pixel centre u → prototype coordinate a·u + b (pixel-centre convention throughout).
    a = lb.scale / ps
    bx = (0.5 * lb.scale + lb.pad_x) / ps - 0.5
    by = (0.5 * lb.scale + lb.pad_y) / ps - 0.5
    cut = math.log(mask_threshold / (1.0 - mask_threshold))  # threshold on logits
    rles, kept = [], []
    for i, (x1, y1, x2, y2) in enumerate(boxes):
        # Pixels whose centres lie inside the box.
        X1, Y1 = max(0, math.ceil(x1 - 0.5)), max(0, math.ceil(y1 - 0.5))
        X2, Y2 = min(W, math.floor(x2 - 0.5) + 1), min(H, math.floor(y2 - 0.5) + 1)
        if X2 <= X1 or Y2 <= Y1:
            continue
        px0 = max(0, math.floor(a * X1 + bx))
        px1 = min(wp, math.ceil(a * (X2 - 1) + bx) + 2)
        py0 = max(0, math.floor(a * Y1 + by))
        py1 = min(hp, math.ceil(a * (Y2 - 1) + by) + 2)
        logits = (coeffs[i] @ protos[:, py0:py1, px0:px1].reshape(c, -1)).reshape(py1 - py0, px1 - px0)
        warp = np.array([[a, 0.0, a * X1 + bx - px0], [0.0, a, a * Y1 + by - py0]])
        up = cv2.warpAffine(logits, warp, (X2 - X1, Y2 - Y1), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                            borderMode=cv2.BORDER_REPLICATE)
        crop = up > cut
        if not crop.any():
            continue
        rles.append(crop_rle(crop, X1, Y1, H, W))
        kept.append(i)
    return rles, np.asarray(kept, np.int64)
