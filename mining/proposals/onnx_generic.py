"""Generic candidates from what the COCO ONNX model already computes (issue 29, scope item 1).

The YOLO-seg decoder (``yolo_seg``, as the ``onnx`` proposer runs it) keeps anchors whose
best class score is ≥ ``onnx.score_threshold``; an object of no COCO class often scores below it everywhere,
yet the anchor's box and mask coefficients still describe *something*. These candidates
are the anchors below that cut, down to ``onnx_generic.min_score``, decoded with the very
same rules (class-agnostic NMS, masks from the prototypes) by ``decode_predictions``
itself, and then **marked as generic**:

* their proposer name is ``"onnx_generic"``;
* they carry no class posterior (``posterior`` None): a score of 0.003 for "chair" says
  that no class fits, not that it is a chair, so the union treats them as class-agnostic
  rows (covered by a learned row → merged into it; uncovered → evidence for unknown,
  weighted by detectability, as the stereo proposer's rows);
* objectness is the anchor's best class score, the model's own (low) belief.

They are built only when ``proposals.onnx_generic.enabled`` (off: today's behaviour,
nothing computed). In a union they come last (after ``stereo``), so they only add
objects no other proposer found, and the network runs once for both ONNX parts
(``onnx_yolo.onnx_model``).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from mining.proposals.config import OnnxConfig, OnnxGenericConfig
from mining.proposals.yolo_seg import N_COCO, Letterbox, decode_predictions
from mining.types import Proposals

PROPOSER_NAME = "onnx_generic"


def generic_candidates(frame: int, pred: np.ndarray, protos: np.ndarray, lb: Letterbox, frame_hw: tuple[int, int],
                       onnx_cfg: OnnxConfig, cfg: OnnxGenericConfig) -> Proposals:
    """The generic candidates of one frame's network outputs (module docstring), best score first."""
    score = pred[4:4 + N_COCO].max(axis=0)
    below = np.flatnonzero(score < onnx_cfg.score_threshold)  # the decoder's own rows stay its own
    decode_cfg = replace(onnx_cfg, score_threshold=cfg.min_score, nms_iou=cfg.nms_iou,
                         max_proposals=cfg.max_proposals)
    out = decode_predictions(frame, pred[:, below], protos, lb, frame_hw, decode_cfg)
    out.posterior = None
    out.proposer = [PROPOSER_NAME] * len(out)
    return out
