"""Class-agnostic mask proposals from FastSAM ("everything" mode) exported to ONNX (``fastsam`` proposer).

FastSAM-s / FastSAM-x (Zhao et al. 2023, trained on 2 % of SA-1B) are YOLOv8-seg networks with a
single class, "object". Any YOLOv8-seg-layout model is read the same way; its class count comes
from the output shape.

Input / output contract of the ONNX file (what ``ultralytics`` ``FastSAM("FastSAM-s.pt").export(
format="onnx")`` writes):

=========  ======================  ===========================================================
name       shape                   meaning
=========  ======================  ===========================================================
input 0    (1, 3, h, w) float32    RGB in [0, 1], letterboxed (grey ``pad_value``), h and w
                                   multiples of 32; fixed or dynamic
output 0   (1, 4 + K + 32, N)      per anchor: cx, cy, w, h in input pixels; K class scores
                                   (sigmoids; K = 1 for FastSAM); 32 mask coefficients
output 1   (1, 32, h/4, w/4)       mask prototypes
=========  ======================  ===========================================================

Decoding is the YOLO-seg family's (mining/proposals/yolo_seg.py: letterbox, class-agnostic NMS in
frame pixels, masks from coefficients · prototypes inside the box), with:

* objectness = the model's own score (the best of the K class scores: FastSAM's one score);
* posterior None: the model names no class. In a union with a classifier ("onnx+fastsam",
  "onnx+fastsam+stereo") an uncovered FastSAM row counts toward "unknown", weighted by how
  likely the classifier would have found a COCO object of its size (mining/proposals/union.py);
  a covered one merges into the classifier's row.

Input size. A fixed-size export (Ultralytics' default, ``dynamic=False``) carries its anchor grid
as constants; run at another size (``"auto"``: the frame's aspect) it is rebuilt once by
``onnx_convert.converted_model``, the COCO model's path (on a float model its step 1, the int8
→ float rewrite, finds nothing to do; step 2 rebuilds the anchor constants). A dynamic export
(``dynamic=True``) computes its anchors in the graph and runs as is at any size.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from mining.errors import InputError
from mining.proposals.config import FastSamConfig, ProposalConfig
from mining.proposals.onnx_convert import converted_model
from mining.proposals.yolo_seg import (N_COEFFS, Letterbox, cache_folder, check_image, decode_predictions,
                                       letterbox_image, model_file, new_session, plan_letterbox)
from mining.proposals.registry import ModelBatch
from mining.types import Proposals

PROPOSER_NAME = "fastsam"


def declared_input_hw(model_path: Path) -> tuple[int | None, int | None]:
    """The (h, w) an ONNX model's first input declares; None for a dynamic side."""
    import onnx

    try:
        model = onnx.load(str(model_path), load_external_data=False)
    except Exception as e:  # onnx raises DecodeError and friends
        raise InputError(f"not a readable ONNX model: {e}", model_path) from None
    if len(model.graph.input) < 1:
        raise InputError("the model has no input", model_path)
    dims = model.graph.input[0].type.tensor_type.shape.dim
    if len(dims) != 4:
        raise InputError(f"expected one (1, 3, h, w) image input, the first input has {len(dims)} dimensions",
                         model_path)
    return tuple(int(d.dim_value) if d.HasField("dim_value") else None for d in dims[2:])  # type: ignore[return-value]


def class_count(pred: np.ndarray, protos: np.ndarray, path: Path) -> int:
    """K of a (4 + K + 32, N) prediction and (32, h, w) prototypes; InputError naming the file if off-layout."""
    if pred.ndim != 2 or protos.ndim != 3:
        raise InputError(f"expected outputs (1, 4 + K + 32, N) and (1, 32, h/4, w/4), got {pred.shape} (batch "
                         f"dropped) and {protos.shape}", path)
    if protos.shape[0] != N_COEFFS:
        raise InputError(f"prototype output has {protos.shape[0]} channels, the YOLOv8-seg layout has {N_COEFFS}", path)
    k = pred.shape[0] - 4 - N_COEFFS
    if k < 1:
        raise InputError(f"prediction output has {pred.shape[0]} rows; the YOLOv8-seg layout needs 4 box rows, at "
                         f"least one class row and {N_COEFFS} mask coefficients (≥ {4 + 1 + N_COEFFS})", path)
    return k


class FastSamProposer:
    """Loads the model once (a long-lived worker) and turns frames into class-agnostic ``Proposals``."""

    def __init__(self, cfg: FastSamConfig, frame_size: tuple[int, int] | None = None):
        self.model_path = model_file(cfg.model_path, "fastsam", "a FastSAM ONNX export", "FastSAM ONNX model")
        self.cfg = cfg
        self.cache_dir = cache_folder(cfg.cache_dir)
        self.declared_hw = declared_input_hw(self.model_path)
        self._sessions: dict[tuple[int, int], tuple] = {}
        self.model_files: dict[tuple[int, int], Path] = {}  # input size → the file run (the user's or a resized copy)
        self.n_classes: int | None = None
        self.last_timings_ms: dict[str, float] = {}
        fixed = isinstance(cfg.input_height, int) and isinstance(cfg.input_width, int)
        if frame_size is not None or fixed:
            self._session(plan_letterbox(cfg, frame_size or (cfg.input_height, cfg.input_width)).input_hw)

    def _session(self, input_hw: tuple[int, int]):
        if input_hw not in self._sessions:
            dynamic = None in self.declared_hw
            path = self.model_path if dynamic or self.declared_hw == input_hw else \
                converted_model(self.model_path, self.cache_dir, *input_hw)
            self.model_files[input_hw] = path
            try:
                sess = new_session(path, self.cfg.intra_op_num_threads, ["CPUExecutionProvider"])
            except Exception as e:  # onnxruntime's own errors: not a model it can run
                raise InputError(f"onnxruntime cannot load it: {e}", self.model_path) from None
            if len(sess.get_outputs()) < 2:
                raise InputError(f"expected two outputs (predictions, prototypes), the model has "
                                 f"{len(sess.get_outputs())}", self.model_path)
            self._sessions[input_hw] = (sess, sess.get_inputs()[0].name)
        return self._sessions[input_hw]

    def raw_outputs(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray, Letterbox]:
        """Run the network: (4 + K + 32, N) predictions, (32, h/4, w/4) prototypes and the letterbox."""
        lb = plan_letterbox(self.cfg, image.shape[:2])
        sess, name = self._session(lb.input_hw)
        out0, out1 = sess.run(None, {name: letterbox_image(image, lb, self.cfg.pad_value)})[:2]
        return out0[0], out1[0], lb

    def __call__(self, frame: int, image: np.ndarray) -> Proposals:
        check_image(frame, image)
        t0 = time.perf_counter()
        pred, protos, lb = self.raw_outputs(image)
        t1 = time.perf_counter()
        self.n_classes = class_count(pred, protos, self.model_path)
        out = decode_predictions(frame, pred, protos, lb, image.shape[:2], self.cfg, n_classes=self.n_classes,
                                 name=PROPOSER_NAME)
        if self.n_classes == 80:  # a COCO model given as FastSAM: its classes are not used here
            out.posterior = None
        self.last_timings_ms = {"network": 1e3 * (t1 - t0), "decode": 1e3 * (time.perf_counter() - t1)}
        return out


def fastsam_model(cfg: ProposalConfig, frame_size: tuple[int, int]) -> ModelBatch:
    """The registry's factory of ``fastsam`` (``proposals.fastsam``): one network run a frame."""
    fastsam = FastSamProposer(cfg.fastsam, frame_size=frame_size)
    return lambda frames, images: [[fastsam(f, im)] for f, im in zip(frames, images)]
