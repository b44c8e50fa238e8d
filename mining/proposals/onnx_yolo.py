"""Image-level mask proposals from a YOLO-seg-family ONNX model (onnxruntime, CPU).

The model runs at the frame's own aspect ratio (letterboxed to multiples of 32), after a
one-off conversion to float at that size (``onnx_convert``). Its outputs are decoded as the
family's (``yolo_seg``: the model card's rules, class-agnostic NMS, masks inside the box) with
the 80 COCO classes: each proposal carries an 81-way class posterior, the unknown mass
1 − max p (``yolo_seg.class_posterior``).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mining.proposals.config import OnnxConfig, ProposalConfig
from mining.proposals.onnx_convert import converted_model
from mining.proposals.onnx_generic import generic_candidates
from mining.proposals.registry import ModelBatch
from mining.proposals.yolo_seg import (Letterbox, cache_folder, check_image, decode_predictions, execution_providers,
                                       letterbox_image, model_file, new_session, plan_letterbox)
from mining.types import Proposals

PROPOSER_NAME = "onnx"


class OnnxProposer:
    """Loads the (converted) model once and turns frames into ``Proposals``.

    Meant to live as a long-lived worker (a Ray actor): conversion and session creation
    happen in the constructor when the frame size is known, else on the first frame.
    """

    def __init__(self, cfg: OnnxConfig, frame_size: tuple[int, int] | None = None):
        self.model_path = model_file(cfg.model_path, "onnx", "a YOLO-seg ONNX model", "ONNX model")
        self.cfg = cfg
        self.cache_dir = cache_folder(cfg.cache_dir)
        self._sessions: dict[tuple[int, int], object] = {}
        self.converted_paths: dict[tuple[int, int], Path] = {}  # input size → converted float model
        self.last_timings_ms: dict[str, float] = {}
        fixed = isinstance(cfg.input_height, int) and isinstance(cfg.input_width, int)
        if frame_size is not None or fixed:
            self._session(plan_letterbox(cfg, frame_size or (cfg.input_height, cfg.input_width)).input_hw)

    def _session(self, input_hw: tuple[int, int]):
        if input_hw not in self._sessions:
            path = converted_model(self.model_path, self.cache_dir, *input_hw)
            self.converted_paths[input_hw] = path
            sess = new_session(path, self.cfg.intra_op_num_threads, execution_providers(self.cfg.device))
            self._sessions[input_hw] = (sess, sess.get_inputs()[0].name)
        return self._sessions[input_hw]

    def batch_axis(self, input_hw: tuple[int, int]) -> bool:
        """Whether the model takes several images per run: its input's first axis is not fixed
        (YOLO exports usually fix it at 1, with the 1 also inside their reshapes)."""
        sess, _ = self._session(input_hw)
        return not isinstance(sess.get_inputs()[0].shape[0], int)

    def raw_outputs(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray, Letterbox]:
        """Run the network: (116, N) predictions, (32, h/4, w/4) prototypes and the letterbox."""
        lb = plan_letterbox(self.cfg, image.shape[:2])
        sess, name = self._session(lb.input_hw)
        out0, out1 = sess.run(None, {name: letterbox_image(image, lb, self.cfg.pad_value)})
        return out0[0], out1[0], lb

    def raw_outputs_batch(self, frames: Sequence[int], images: Sequence[np.ndarray],
                          ) -> list[tuple[np.ndarray, np.ndarray, Letterbox]]:
        """``raw_outputs`` of each image: one run for all where the model has a batch axis and the
        images share a size, else one run per image (the same outputs either way, tested)."""
        for frame, image in zip(frames, images):
            check_image(frame, image)
        lbs = [plan_letterbox(self.cfg, im.shape[:2]) for im in images]
        if len(images) > 1 and len({lb.input_hw for lb in lbs}) == 1 and self.batch_axis(lbs[0].input_hw):
            sess, name = self._session(lbs[0].input_hw)
            x = np.concatenate([letterbox_image(im, lb, self.cfg.pad_value) for im, lb in zip(images, lbs)])
            out0, out1 = sess.run(None, {name: x})
            return [(out0[i], out1[i], lb) for i, lb in enumerate(lbs)]
        return [self.raw_outputs(im) for im in images]

    def __call__(self, frame: int, image: np.ndarray) -> Proposals:
        check_image(frame, image)
        t0 = time.perf_counter()
        pred, protos, lb = self.raw_outputs(image)
        t1 = time.perf_counter()
        out = decode_predictions(frame, pred, protos, lb, image.shape[:2], self.cfg, name=PROPOSER_NAME)
        self.last_timings_ms = {"network": 1e3 * (t1 - t0), "decode": 1e3 * (time.perf_counter() - t1)}
        return out


def onnx_model(cfg: ProposalConfig, frame_size: tuple[int, int]) -> ModelBatch:
    """The registry's factory of ``onnx`` (``proposals.onnx``): per frame its proposals, and beside them
    the generic candidates of the same network run where ``proposals.onnx_generic.enabled``."""
    model = OnnxProposer(cfg.onnx, frame_size=frame_size)
    generic = cfg.onnx_generic.enabled

    def onnx(frames: list[int], images: list[np.ndarray]) -> list[list[Proposals]]:
        out = []
        for frame, image, (pred, protos, lb) in zip(frames, images, model.raw_outputs_batch(frames, images)):
            hw = image.shape[:2]
            own = decode_predictions(frame, pred, protos, lb, hw, cfg.onnx)
            out.append([own, generic_candidates(frame, pred, protos, lb, hw, cfg.onnx, cfg.onnx_generic)]
                       if generic else [own])
        return out
    return onnx
