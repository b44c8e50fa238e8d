"""Tube scoring settings: the "4DGVT" unary of REFERENCE.md "Scoring"."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from mining.checks import Fraction, OneOf, Positive, Signed


@dataclass
class ScoreConfig:
    objectness_k: Positive = 10.0  # REFERENCE: objectness LLR ln(x) − ln(1/K), K = 10 (paper's β)
    motion_k: Positive = 1000.0  # REFERENCE: motion LLR, K = 1000 (paper's 1/A_GP)
    mask_k: Positive = 500.0  # REFERENCE: mask LLR, K = 500 (paper's α)
    alpha: Fraction = 0.5  # REFERENCE: score = β·(α·motion + (1−α)·mask) + (1−β)·objectness
    beta: Fraction = 0.5  # REFERENCE: as above
    floor: Positive = 1e-6  # ours: a term's x is clipped here so ln(0) cannot occur
    # "reference" = the weighted sum above (REFERENCE.md); "calibrated" = ours: a log-odds fit on
    # synthetic truth per proposer (mining/score/calibrated.py; weights below, from `mine bench calibrate`),
    # refused for a proposer without weights; "auto" = calibrated where the proposer has weights, else reference
    model: Annotated[str, OneOf(("reference", "calibrated", "auto"))] = "reference"
    # proposer → term → weight of θ = w₀ + Σ_t w·φ_t (mining.score.calibrated.TERMS)
    calibrated: dict[str, dict[str, Signed]] = field(default_factory=dict)
    # Known / unknown / unclassified (mining/tubes/category.py).
    known_log_margin: Signed = -1.0  # paper: argmax over the 81 entries is 0; −1 by `mine bench classify` on synthetic training seeds 0000–0002 (balanced accuracy 0.745 → 0.863)
    min_class_evidence: float = 1.0  # ours: classified only with ≥ one frame-equivalent of classifier evidence
