"""Tube embeddings from an image encoder the user brings (``mine embed``): the contract.

**The model.** One ONNX file, a CLIP- or DINO-style image encoder: one crop in, one vector out.

=========  ========================  ==========================================================
           shape                     meaning
=========  ========================  ==========================================================
input      (B, 3, H, W) float32      RGB, scaled to [0, 1], then (x − mean) / std per channel
                                     (``PRESETS``, chosen by ``--preset``). B fixed 1 (one crop a
                                     run), fixed N or symbolic (a batch a run); H, W fixed (the
                                     crop is resized to them) or symbolic (``--input-size``, 224)
output     (B, D) or (B, T, D)       a vector per crop, D ≥ 2; with a token axis the first token
                                     is taken (the CLS token of a ViT: CLIP's and DINO's
                                     image embedding). The first output unless ``--output`` names one
=========  ========================  ==========================================================

The model is checked when it is loaded, before anything is written under ``--out``: a missing,
empty, truncated or random file, a graph onnxruntime cannot load, an input that is not one
(B, 3, H, W) float32 image, or an output that is not (B, D) / (B, T, D) with D ≥ 2 and finite
on a dummy crop is refused in one line naming the file and why (``Encoder``). Its version is
the sha256 of its bytes (``model_sha256``), stored with every vector.

**Normalisation presets** (``PRESETS``): ``clip`` (OpenAI CLIP's mean and std), ``dino`` and
``imagenet`` (ImageNet's mean and std, which DINO and DINOv2 use).

**Best views.** Per tube, the ``views`` (default 3) observed frames whose mask has the largest
area × objectness (a missing objectness counts 1), ties to the earlier frame. Each view is the
tube's box widened by ``margin`` on each side (``export/crops.crop_box``: the crops export's rule),
then widened to the model input's aspect around its centre, padded with the preset's mean colour
where it leaves the image (so the pad is 0 after normalisation), resized to H × W (area averaging
when shrinking, bicubic when enlarging, as CLIP's and DINO's transforms). Each crop's vector is
L2-normalised, the views' vectors averaged, and the mean L2-normalised again: one unit vector per
tube, each view weighing the same.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from mining.config import EmbedConfig
from mining.errors import ConfigError, InputError
from mining.export.crops import crop_box
from mining.files import check_regular

# Normalisation of [0, 1] RGB, per preset: (mean, std).
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)  # OpenAI CLIP (clip/clip.py _transform)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)  # OpenAI CLIP (clip/clip.py _transform)
IMAGENET_MEAN = (0.485, 0.456, 0.406)  # torchvision's ImageNet constants; DINO and DINOv2 use them
IMAGENET_STD = (0.229, 0.224, 0.225)  # torchvision's ImageNet constants; DINO and DINOv2 use them
PRESETS = {"clip": (CLIP_MEAN, CLIP_STD), "dino": (IMAGENET_MEAN, IMAGENET_STD),
           "imagenet": (IMAGENET_MEAN, IMAGENET_STD)}
MIN_DIM = 2  # ours: a vector of one number ranks, it does not describe
HASH_CHUNK = 1 << 20  # ours: bytes read per step while hashing the model file
FLOAT_TENSOR = 1  # onnx.TensorProto.FLOAT


def file_sha256(path: Path) -> str:
    """sha256 of a file's bytes: the model's version."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(HASH_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def providers(device: str) -> list[str]:
    """onnxruntime's providers for ``device`` (auto: CUDA where this onnxruntime has it, else the CPU)."""
    import onnxruntime as ort

    cuda = "CUDAExecutionProvider" in ort.get_available_providers()
    if device == "cuda" and not cuda:
        raise ConfigError("--device cuda, but this onnxruntime has no CUDA provider (install onnxruntime-gpu on the "
                          "GPU nodes, or use --device auto or cpu)")
    return ["CUDAExecutionProvider", "CPUExecutionProvider"] if cuda and device != "cpu" else ["CPUExecutionProvider"]


def _declared(path: Path) -> tuple[list[int | None], int]:
    """(the declared input dims, its element type) of the ONNX file's one image input, read
    without onnxruntime; InputError naming the file for anything off the contract."""
    import onnx

    try:
        model = onnx.load(str(path), load_external_data=False)
    except Exception as e:  # onnx raises DecodeError and friends on truncated or foreign bytes
        raise InputError(f"embedding model: not a readable ONNX model (truncated or not ONNX): {e}", path) from None
    inits = {i.name for i in model.graph.initializer}
    inputs = [i for i in model.graph.input if i.name not in inits]
    if not model.graph.node or len(inputs) != 1:
        raise InputError(f"embedding model: expected one (B, 3, H, W) image input and a graph, got {len(inputs)} "
                         f"input(s) and {len(model.graph.node)} node(s)", path)
    t = inputs[0].type.tensor_type
    dims = [int(d.dim_value) if d.HasField("dim_value") else None for d in t.shape.dim]
    return dims, int(t.elem_type)


@dataclass(frozen=True)
class ModelInput:
    """What the encoder takes: batch (None: any), height, width."""

    batch: int | None
    height: int
    width: int


class Encoder:
    """The user's image encoder, checked against the contract (module docstring) on load."""

    def __init__(self, path: str | Path, cfg: EmbedConfig, device: str | None = None):
        if not str(path):
            raise ConfigError("--model is empty: give the image encoder's ONNX file (no weights are bundled)")
        self.path = Path(path).expanduser()
        if not check_regular(self.path).is_file():  # a FIFO is named as one, not as missing
            raise InputError("embedding model not found", self.path)
        if self.path.stat().st_size == 0:
            raise InputError("embedding model: empty file", self.path)
        if cfg.preset not in PRESETS:
            raise ConfigError(f"--preset {cfg.preset!r}: one of {', '.join(PRESETS)}")
        self.cfg = cfg
        self.mean, self.std = (np.asarray(v, np.float32) for v in PRESETS[cfg.preset])
        dims, elem = _declared(self.path)
        if len(dims) != 4 or dims[1] not in (None, 3) or elem != FLOAT_TENSOR:
            raise InputError(f"embedding model: the input is {dims} of ONNX type {elem}, not (B, 3, H, W) float32",
                             self.path)
        h, w = dims[2] or cfg.input_size, dims[3] or cfg.input_size
        self.input = ModelInput(dims[0], h, w)
        self.session = self._session(device or cfg.device)
        self.input_name = self.session.get_inputs()[0].name
        outs = [o.name for o in self.session.get_outputs()]
        if cfg.output and cfg.output not in outs:
            raise InputError(f"embedding model: no output {cfg.output!r} (it has {outs})", self.path)
        self.output = cfg.output or outs[0]
        self.sha256 = file_sha256(self.path)
        # The contract, on dummy crops: two where the export takes a batch, so a batch that does not run fails here.
        probe = self.embed_crops([np.full((h, w, 3), 128, np.uint8)] * min(2, self.batch))
        self.dim = int(probe.shape[1])

    def _session(self, device: str):
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = self.cfg.intra_op_num_threads
        opts.inter_op_num_threads = 1
        opts.log_severity_level = 3  # an export's unused initialisers are not worth a warning per actor
        try:
            return ort.InferenceSession(str(self.path), opts, providers=providers(device))
        except Exception as e:  # onnxruntime's own errors: not a model it can run
            raise InputError(f"embedding model: onnxruntime cannot load it: {str(e).splitlines()[0]}", self.path) from None

    @property
    def batch(self) -> int:
        """Crops a run: the fixed batch of the export, or ``embed.batch`` where it is symbolic."""
        return self.input.batch or self.cfg.batch

    def prepare(self, crop: np.ndarray) -> np.ndarray:
        """(h, w, 3) uint8 RGB crop → (3, H, W) float32: resized, scaled, normalised."""
        H, W = self.input.height, self.input.width
        interp = cv2.INTER_AREA if crop.shape[0] > H or crop.shape[1] > W else cv2.INTER_CUBIC
        x = cv2.resize(crop, (W, H), interpolation=interp).astype(np.float32) / 255.0
        return ((x - self.mean) / self.std).transpose(2, 0, 1)

    def _run(self, x: np.ndarray) -> np.ndarray:
        n = len(x)
        if self.input.batch is not None and n < self.input.batch:  # a fixed batch: fill it, read the first n
            x = np.concatenate([x, np.repeat(x[-1:], self.input.batch - n, axis=0)])
        try:
            (y,) = self.session.run([self.output], {self.input_name: x})
        except Exception as e:  # the graph does not take what its declaration says
            raise InputError(f"embedding model: failed on a ({len(x)}, 3, {self.input.height}, {self.input.width}) "
                             f"input: {str(e).splitlines()[0]}", self.path) from None
        y = np.asarray(y)
        if y.ndim == 3:  # (B, T, D): the first token (a ViT's CLS token)
            y = y[:, 0, :]
        if y.ndim != 2 or y.shape[0] != len(x) or y.shape[1] < MIN_DIM:
            raise InputError(f"embedding model: output {self.output!r} is {list(np.asarray(y).shape)} for a batch of "
                             f"{len(x)}, not (B, D) or (B, T, D) with D ≥ {MIN_DIM}", self.path)
        if not np.isfinite(y).all():
            raise InputError(f"embedding model: output {self.output!r} is not finite", self.path)
        return y[:n].astype(np.float32)

    def embed_crops(self, crops: list[np.ndarray]) -> np.ndarray:
        """(len(crops), D) L2-normalised vectors of uint8 RGB crops, ``batch`` crops a run."""
        out = []
        for s in range(0, len(crops), self.batch):
            out.append(self._run(np.stack([self.prepare(c) for c in crops[s:s + self.batch]])))
        y = np.concatenate(out) if out else np.zeros((0, 0), np.float32)
        return unit(y)

    def crop(self, image: np.ndarray, bbox) -> np.ndarray:
        """The view of a box in a frame (module docstring): margin, the input's aspect, mean-colour pad."""
        return aspect_crop(image, bbox, self.cfg.margin, self.input.width / self.input.height,
                           np.round(self.mean * 255).astype(np.uint8))


def unit(v: np.ndarray) -> np.ndarray:
    """Rows of ``v`` scaled to L2 norm 1 (a zero row stays zero)."""
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return (v / np.where(n > 0, n, 1.0)).astype(np.float32)


def tube_vector(views: np.ndarray) -> np.ndarray:
    """One unit vector from a tube's unit view vectors: their mean, L2-normalised."""
    return unit(views.mean(axis=0, keepdims=True))[0]


def aspect_crop(image: np.ndarray, bbox, margin: float, aspect: float, fill: np.ndarray) -> np.ndarray:
    """The box with ``margin`` (``crop_box``), widened about its centre to width / height = ``aspect``,
    padded with ``fill`` where it leaves the image."""
    h, w = image.shape[:2]
    x0, x1, y0, y1 = crop_box(bbox, w, h, margin)
    cw, ch = x1 - x0, y1 - y0
    if cw / ch < aspect:
        cw = int(round(ch * aspect))
    else:
        ch = int(round(cw / aspect))
    cx, cy = (x0 + x1) / 2.0, (y0 + y1) / 2.0
    ax, ay = int(round(cx - cw / 2.0)), int(round(cy - ch / 2.0))
    out = np.empty((ch, cw, 3), np.uint8)
    out[:] = fill
    sx0, sy0, sx1, sy1 = max(ax, 0), max(ay, 0), min(ax + cw, w), min(ay + ch, h)
    out[sy0 - ay:sy1 - ay, sx0 - ax:sx1 - ax] = image[sy0:sy1, sx0:sx1]
    return out


def best_views(rows: list[dict], areas: list[float], k: int) -> list[dict]:
    """The ``k`` observed rows of a tube with the largest mask area × objectness (None counts 1),
    ties to the earlier frame; in frame order. ``areas``: each row's mask area in pixels."""
    scored = [(-a * (1.0 if r.get("objectness") is None else float(r["objectness"])), r["frame"], i)
              for i, (r, a) in enumerate(zip(rows, areas)) if r["observed"]]
    return sorted((rows[i] for _, _, i in sorted(scored)[:k]), key=lambda r: r["frame"])


def views_key(views: list[dict]) -> str:
    """A hash of what a tube's views are (frames, boxes, masks): a tube whose views changed is embedded again."""
    blob = json.dumps([[int(v["frame"]), [round(float(x), 3) for x in v["bbox"]], str(v["rle_counts"])] for v in views])
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def settings_key(cfg: EmbedConfig, model_input: ModelInput, output: str) -> str:
    """A hash of the settings beside the model that make a vector (views, margin, input size, output)."""
    blob = json.dumps({"views": cfg.views, "margin": cfg.margin, "input": [model_input.height, model_input.width],
                       "output": output, "preset": cfg.preset}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]
