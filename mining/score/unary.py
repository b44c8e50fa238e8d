"""The tube's unary score: motion, mask-consistency and objectness log-likelihood ratios.

For each inlier after the first (REFERENCE.md "Scoring"; paper Eq. 2–8):

* motion:     ln N(footpoint; prediction) − ln(1/K_motion)  (null: clutter uniform over the ground)
* mask:       ln IoU(predicted, observed) − ln(1/K_mask)     (null: no overlap beyond chance)
* objectness: ln score − ln(1/K_obj)                         (null: segmentation clutter)

score = β·(α·motion + (1−α)·mask) + (1−β)·objectness. The sums run over the whole tube,
so longer tubes score higher.
"""

from __future__ import annotations

import numpy as np

from mining.score.config import ScoreConfig
from mining.types import Tube, TubeScore


def llr(x: np.ndarray, k: float, floor: float) -> float:
    """Σ ln(x) − ln(1/K) over the values."""
    x = np.clip(np.asarray(x, np.float64), floor, None)
    return float(np.sum(np.log(x) + np.log(k)))


def score_tube(tube: Tube, cfg: ScoreConfig | None = None) -> TubeScore:
    cfg = cfg or ScoreConfig()
    inl = [f for f in tube.frames if f.observed][1:]
    motion = llr([f.motion_density for f in inl], cfg.motion_k, cfg.floor)
    mask = llr([f.mask_iou for f in inl], cfg.mask_k, cfg.floor)
    obj = llr([f.objectness for f in inl], cfg.objectness_k, cfg.floor)
    total = cfg.beta * (cfg.alpha * motion + (1 - cfg.alpha) * mask) + (1 - cfg.beta) * obj
    return TubeScore(motion, mask, obj, total)
