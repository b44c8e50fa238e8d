"""The tube's unary score: motion, mask-consistency and objectness log-likelihood ratios.

For each inlier after the first (REFERENCE.md "Scoring"; paper Eq. 2–8):

* motion:     ln N(footpoint; prediction) − ln(1/K_motion)  (null: clutter uniform over the ground)
* mask:       ln IoU(predicted, observed) − ln(1/K_mask)     (null: no overlap beyond chance)
* objectness: ln score − ln(1/K_obj)                         (null: segmentation clutter)

score = β·(α·motion + (1−α)·mask) + (1−β)·objectness. The sums run over the whole tube,
so longer tubes score higher.

With ``score.model = "calibrated"`` the total is instead the tube's log-odds of being an
object, with weights fit on synthetic truth for the job's proposer (``mining.score.calibrated``);
the three terms above are still reported, for display and the recall funnel.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping

import numpy as np

from mining.errors import ConfigError
from mining.score.calibrated import GROUPS, TERMS, calibrated_score, grouped_terms, tube_evidence
from mining.score.config import ScoreConfig
from mining.types import Tube, TubeScore


def llr(x: np.ndarray, k: float, floor: float) -> float:
    """Σ ln(x) − ln(1/K) over the values."""
    x = np.clip(np.asarray(x, np.float64), floor, None)
    return float(np.sum(np.log(x) + np.log(k)))


def unary_weights(cfg: ScoreConfig, proposer: str) -> Mapping[str, float] | None:
    """The calibrated weights for ``proposer``, or None for the REFERENCE score (``model``
    "reference", or "auto" for a proposer without weights).

    ConfigError when ``model = "calibrated"`` has no weights for the proposer (weights fit for
    one proposer's evidence do not hold for another's: never substituted) or names a term
    that does not exist.
    """
    if cfg.model == "reference":
        return None
    weights = cfg.calibrated.get(proposer)
    if weights is None and cfg.model == "auto":
        return None
    if weights is None:
        raise ConfigError(f"score.model = 'calibrated' has no weights for proposer {proposer!r} "
                          f"(score.calibrated has {sorted(cfg.calibrated) or 'none'}): fit them with "
                          f"`mine bench calibrate --set proposals.proposer='\"{proposer}\"'`, or set "
                          f"score.model = \"reference\"")
    unknown = sorted(set(weights) - set(TERMS))
    if unknown:
        raise ConfigError(f"score.calibrated.{proposer}: unknown term(s) {unknown}; known: {list(TERMS)}")
    return weights


def unary_groups(cfg: ScoreConfig, proposer: str) -> tuple[str, ...] | None:
    """The groups of terms the run's scores split their total by (``TubeScore.terms``: the calibrated
    unary's ``GROUPS``), or None under REFERENCE's (its three terms)."""
    return None if unary_weights(cfg, proposer) is None else tuple(GROUPS)


def unary_version(cfg: ScoreConfig, weights: Mapping[str, float] | None) -> str:
    """``<model>-<12 hex>``: the unary and a hash of every parameter its total depends on (the
    calibrated weights, or REFERENCE's K, α, β; the floor). Stored beside each score, so scores of
    two catalogues compare only where it agrees (job.json holds the parameters themselves)."""
    if weights is None:
        model, params = "reference", {"alpha": cfg.alpha, "beta": cfg.beta, "motion_k": cfg.motion_k,
                                      "mask_k": cfg.mask_k, "objectness_k": cfg.objectness_k, "floor": cfg.floor}
    else:
        model, params = "calibrated", {"weights": {k: float(v) for k, v in weights.items()}, "floor": cfg.floor}
    text = json.dumps(params, sort_keys=True, allow_nan=False)
    return f"{model}-{hashlib.sha256(text.encode()).hexdigest()[:12]}"


def score_tube(tube: Tube, cfg: ScoreConfig | None = None, weights: Mapping[str, float] | None = None,
               version: str | None = None) -> TubeScore:
    """The three REFERENCE terms and the total: theirs (``weights`` None) or the calibrated log-odds;
    ``version``: ``unary_version(cfg, weights)`` when the caller made it once for many tubes."""
    cfg = cfg or ScoreConfig()
    version = unary_version(cfg, weights) if version is None else version
    inl = [f for f in tube.frames if f.observed][1:]
    motion = llr([f.motion_density for f in inl], cfg.motion_k, cfg.floor)
    mask = llr([f.mask_iou for f in inl], cfg.mask_k, cfg.floor)
    obj = llr([f.objectness for f in inl], cfg.objectness_k, cfg.floor)
    if weights is None:
        total = cfg.beta * (cfg.alpha * motion + (1 - cfg.alpha) * mask) + (1 - cfg.beta) * obj
        return TubeScore(motion, mask, obj, total, version=version)
    evidence = tube_evidence(tube, cfg.floor)  # one pass over the frames for the total and its groups
    return TubeScore(motion, mask, obj, calibrated_score(tube, weights, cfg.floor, evidence), "calibrated",
                     grouped_terms(tube, weights, cfg.floor, evidence), version)


def unary_total(tube: Tube, cfg: ScoreConfig | None = None, weights: Mapping[str, float] | None = None) -> float:
    """``score_tube(tube, cfg, weights).total`` alone: tube NMS ranks its tubes by it every frame, and
    the calibrated total needs neither the three REFERENCE terms nor its groups (nor a version)."""
    if weights is None:
        return score_tube(tube, cfg, version="").total
    return calibrated_score(tube, weights, (cfg or ScoreConfig()).floor)


def unary_line(cfg: ScoreConfig, proposer: str) -> str:
    """Which unary a run scores with, for its report (``auto`` is never silent)."""
    if unary_weights(cfg, proposer) is None:
        why = "" if cfg.model == "reference" else f" (score.model = {cfg.model!r}: no calibrated weights for {proposer!r})"
        return f"unary: REFERENCE (β·(α·motion + (1−α)·mask) + (1−β)·objectness){why}"
    return f"unary: calibrated log-odds for proposer {proposer!r} (score.calibrated; score.model = {cfg.model!r})"
