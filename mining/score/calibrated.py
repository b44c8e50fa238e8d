"""The calibrated unary: a tube's log-odds of being an object, a likelihood ratio fit on truth.

The REFERENCE unary (``mining.score.unary``) adds three hand-weighted log-likelihood ratios
per frame. Its weights (α, β, K) were never fit, and its mask term cannot tell a hedge from
a car: a stable segment of vegetation earns ln(IoU·500) ≈ +5.5 a frame like an object
(issue 18's funnel: the mask term carried 69 of 70 selected clutter tubes on one seed).

Here each observed frame after a tube's first contributes a linear log-likelihood ratio in
per-frame evidence φ_t, and the tube adds a constant:

    θ(T) = w₀ + Σ_t w · φ_t(T)

    φ_t = (1, ln IoU_t, ln m_t, ln o_t, ln w_t, ln h_t, ln l_t, (ln w_t)², (ln h_t)², (ln l_t)², k_t)

* ``1``: per-frame prior (a longer tube of the same kind carries more evidence either way);
* ``ln IoU_t``, ``ln m_t``, ``ln o_t``: the REFERENCE terms' evidence (mask IoU of the
  warped prediction, motion density of the footpoint, objectness), each clipped at ``floor``;
* ``ln w/h/l`` and their squares: the filtered 3D extent (width, height, depth extent of the
  mask's points, metres, at least ``min_size_m``). Quadratic in log-size is the log-ratio of
  two Gaussians over log-size: objects are compact and of bounded size, vegetation, verges
  and facades stretch along the road or are thin;
* ``k_t``: the classifier's mass on the 80 known classes (1 − P(unknown); 0 where no
  classifier looked): an object a COCO detector recognises, or background it calls nothing.

θ is natural-log odds: with ε1 = 0 a tube alone is selected when it is more likely an
object than not. Because a frame's evidence depends on the proposer (the stereo proposer's
objectness is not a detector's score), the weights are fit per proposer
(``mine bench calibrate``: logistic regression on the candidate tubes of synthetic training
seeds, labelled object / part / clutter against exact truth, chosen by leave-one-seed-out
cross-validation) and live in ``ScoreConfig.calibrated``.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from mining.types import UNKNOWN_CLASS, Tube

# The evidence terms, in φ's order; "bias" is the tube's constant w₀ (not summed over frames).
FEATURES = ("frame", "ln_mask_iou", "ln_motion", "ln_objectness", "ln_width", "ln_height", "ln_length",
            "ln_width_sq", "ln_height_sq", "ln_length_sq", "known_mass")
TERMS = ("bias", *FEATURES)
MIN_SIZE_M = 0.05  # ours: extents below 5 cm are depth noise, not shape (log-size would run to −∞)


def frame_evidence(tube: Tube, floor: float) -> np.ndarray:
    """φ_t of each observed frame after the first, (n, len(FEATURES)); the inliers the REFERENCE sums over."""
    inl = [f for f in tube.frames if f.observed][1:]
    n = len(inl)
    if not n:
        return np.zeros((0, len(FEATURES)))
    terms = np.array([(f.mask_iou, f.motion_density, f.objectness) for f in inl], np.float64)
    ln_terms = np.log(np.clip(np.nan_to_num(terms, nan=floor), floor, None))
    size = np.array([f.size for f in inl], np.float64).reshape(n, 3)
    ln_size = np.log(np.clip(np.where(np.isfinite(size), size, MIN_SIZE_M), MIN_SIZE_M, None))
    known = np.array([float(np.clip(1.0 - f.posterior[UNKNOWN_CLASS], 0.0, 1.0))
                      if f.posterior is not None and f.class_weight > 0 else 0.0 for f in inl])
    return np.column_stack([np.ones(n), ln_terms, ln_size, ln_size ** 2, known])


def tube_evidence(tube: Tube, floor: float) -> np.ndarray:
    """(1, Σ_t φ_t): the tube's evidence vector in TERMS order; θ = w · this."""
    return np.concatenate([[1.0], frame_evidence(tube, floor).sum(axis=0)])


def weight_vector(weights: Mapping[str, float]) -> np.ndarray:
    """Named weights → a vector in TERMS order (a missing name weighs 0)."""
    return np.array([float(weights.get(k, 0.0)) for k in TERMS])


def calibrated_score(tube: Tube, weights: Mapping[str, float], floor: float,
                     evidence: np.ndarray | None = None) -> float:
    """θ(T) = w₀ + Σ_t w · φ_t: the tube's log-odds of being an object (``evidence``: the tube's
    ``tube_evidence``, when the caller has it already)."""
    return float(weight_vector(weights) @ (tube_evidence(tube, floor) if evidence is None else evidence))


# The terms grouped as a reader asks "what carried this tube": each group's share of θ.
GROUPS = {
    "prior": ("bias", "frame"),
    "motion": ("ln_motion",),
    "mask": ("ln_mask_iou",),
    "objectness": ("ln_objectness",),
    "shape": ("ln_width", "ln_height", "ln_length", "ln_width_sq", "ln_height_sq", "ln_length_sq"),
    "class": ("known_mass",),
}


def grouped_terms(tube: Tube, weights: Mapping[str, float], floor: float,
                  evidence: np.ndarray | None = None) -> dict[str, float]:
    """θ split by GROUPS: each group's Σ w_k·(Σ_t φ_t)_k; the values add up to θ (``evidence`` as in
    ``calibrated_score``)."""
    contrib = dict(zip(TERMS, weight_vector(weights) * (tube_evidence(tube, floor) if evidence is None else evidence)))
    return {g: float(sum(contrib[k] for k in keys)) for g, keys in GROUPS.items()}
