"""Object or clutter: the evidence that a tube no classifier recognises is an object (issue 29).

A tube called *unknown* says only that the classifier did not recognise it; vegetation,
verges, facades and masks spilling over the background are not recognised either (issue
29's funnel: half the tubes called unknown were clutter). Before a tube enters the unknown
set it must look like an object. The evidence is what the tube already carries, per
observed frame (``mining.types.TubeFrame``), summarised over the tube:

* **persistence**: ln of its observed frames, and their share of its span;
* **3D shape stability**: the spread over frames of ln(mask area × z²) (the mask's area in
  m² up to the focal length²: a rigid object keeps it, a segment that grows and shrinks with
  the background does not), of the box's ln aspect ratio and of the filtered ln 3D extent;
* **compactness**: the mask's share of its box, and the median filtered ln width, height and
  length (metres);
* **the classifier's view**: the share of frames with a classifier's own row and their mean
  max class score; the mean detectability weight of the class-agnostic rows
  (``mining.proposals.union``: a large region the detector looked at);
* **motion and place**: ln of the median ground speed, ln median depth, ln median box height
  (px), the share of frames whose box touches the left or right image border, the footpoint's
  spread on the ground (metres) and the box bottom's distance from the image's bottom edge
  (share of the image height: ground support seen from the camera);
* **association**: the mean ln mask IoU of the warped prediction (the REFERENCE mask term's
  evidence).

The log-odds of "object" is linear in these, θ = w₀ + w·ψ(T), fitted by ``mine bench
calibrate --calling`` (logistic regression on the candidate tubes of synthetic training seeds
labelled object against part or clutter, unknown objects weighted up to the known ones,
leave one seed out); the weights are ``ScoreConfig.object_evidence``.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from pycocotools import mask as mask_utils

from mining.types import Tube, max_class_score

OBJECT_FEATURES = ("ln_observed", "observed_share", "sd_ln_area_3d", "sd_ln_aspect", "mean_fill", "classifier_share",
                   "mean_class_score", "mean_detectability", "ln_speed", "ln_depth", "ln_height_px", "border_share",
                   "mean_ln_mask_iou", "ln_width", "ln_height", "ln_length", "sd_ln_size", "sd_footpoint",
                   "bottom_gap")
OBJECT_TERMS = ("bias", *OBJECT_FEATURES)
MIN_SIZE_M = 0.05  # ours, as mining.score.calibrated: extents below 5 cm are depth noise
MIN_DEPTH_M = 1.0  # ours: depths are clipped here before the log (nothing is tracked closer: tubes.min_depth_m 1.3)
MIN_IOU = 1e-3  # ours: a mask IoU of 0 is clipped here before the log
SPEED_OFFSET_MPS = 0.1  # ours: ln(speed + 0.1 m/s), so a static object (speed ≈ 0 up to noise) stays finite
BORDER_PX = 2.0  # ours, as tubes.view_edge_px: a box side within 2 px of the image border touches it


def object_evidence(tube: Tube) -> np.ndarray:
    """ψ(T): the tube's evidence in OBJECT_FEATURES order (module docstring)."""
    obs = [f for f in tube.frames if f.observed]
    n = len(obs)
    area = np.maximum(np.array([mask_utils.area(f.rle) for f in obs], np.float64), 1.0)
    b = np.array([f.box for f in obs], np.float64).reshape(n, 4)
    bw, bh = np.maximum(b[:, 2] - b[:, 0], 1.0), np.maximum(b[:, 3] - b[:, 1], 1.0)
    z = np.clip(np.nan_to_num(np.array([f.position_cam[2] for f in obs], np.float64), nan=MIN_DEPTH_M), MIN_DEPTH_M,
                None)
    scores, detect = [], []
    for f in obs:
        if f.posterior is None or not np.isfinite(f.posterior).all() or not f.class_weight > 0:
            continue
        s = max_class_score(f.posterior)
        (scores if s > 0 else detect).append(s if s > 0 else f.class_weight)
    h, w = obs[0].rle["size"]
    speed = np.array([np.linalg.norm(np.asarray(f.velocity_world, np.float64)[[0, 2]]) for f in obs])
    iou = np.array([f.mask_iou for f in obs[1:]], np.float64)
    ln_size = np.log(np.clip(np.nan_to_num(np.array([f.size for f in obs], np.float64).reshape(n, 3),
                                           nan=MIN_SIZE_M), MIN_SIZE_M, None))
    foot = np.array([f.footpoint_world for f in obs], np.float64).reshape(n, 3)
    speed_med = np.nanmedian(speed) if np.isfinite(speed).any() else 0.0
    foot_sd = np.nanstd(foot[:, [0, 2]], axis=0).mean() if np.isfinite(foot).any() else 0.0
    return np.array([
        np.log(n), n / len(tube.frames), np.log(area * z ** 2).std(), np.log(bw / bh).std(), float(np.mean(area / (bw * bh))),
        len(scores) / n, float(np.mean(scores)) if scores else 0.0, float(np.mean(detect)) if detect else 0.0,
        np.log(speed_med + SPEED_OFFSET_MPS), np.log(np.median(z)), np.log(np.median(bh)),
        float(np.mean((b[:, 0] <= BORDER_PX) | (b[:, 2] >= w - BORDER_PX))),
        float(np.mean(np.log(np.clip(np.nan_to_num(iou, nan=MIN_IOU), MIN_IOU, 1.0)))) if len(iou) else 0.0,
        *np.median(ln_size, axis=0), float(ln_size.std(axis=0).mean()), float(foot_sd),
        float((h - np.median(b[:, 3])) / h),
    ], np.float64)


def object_log_odds(tube: Tube, weights: Mapping[str, float]) -> float:
    """θ = w₀ + w·ψ(T), the tube's log-odds of being an object (a missing weight is 0)."""
    w = np.array([float(weights.get(k, 0.0)) for k in OBJECT_TERMS])
    return float(w @ np.concatenate([[1.0], object_evidence(tube)]))
