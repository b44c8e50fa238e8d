"""Tube scoring settings: the "4DGVT" unary of REFERENCE.md "Scoring"."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from mining.checks import Fraction, OneOf, Positive, Signed


# The calibrated unary's weights per proposer: `mine bench calibrate [--set proposals.proposer=…]` with the
# defaults (synthetic seeds 0000–0006, 100 frames each, tubes.association "innovation", 2 px jitter; unknown
# objects' tubes weighted up to the known ones'). The seeds 0007–0009 were never used: they are the test.
CALIBRATED: dict[str, dict[str, float]] = {
    # 782 object tubes (89 on unknown objects), 1559 part or clutter; leave-one-seed-out AUC 0.88 (REFERENCE 0.71)
    "onnx+stereo": {"bias": -0.712515, "frame": -0.0172806, "ln_mask_iou": 0.127038, "ln_motion": -0.0295287,
                    "ln_objectness": -0.0443859, "ln_width": 0.0724101, "ln_height": -0.200128,
                    "ln_length": -0.0443384, "ln_width_sq": -0.056526, "ln_height_sq": 0.00794187,
                    "ln_length_sq": -0.0471565, "known_mass": 0.664979},
    # 456 object tubes (54 on unknown objects), 1145 part or clutter; leave-one-seed-out AUC 0.90
    "stereo": {"bias": -0.897388, "frame": 0.402084, "ln_mask_iou": 0.477829, "ln_motion": -0.0442557,
               "ln_objectness": 8.66293, "ln_width": 0.035429, "ln_height": -0.098054, "ln_length": 0.0183818,
               "ln_width_sq": -0.101705, "ln_height_sq": 0.101927, "ln_length_sq": -0.029515, "known_mass": 0.0},
}


@dataclass
class ScoreConfig:
    objectness_k: Positive = 10.0  # REFERENCE: objectness LLR ln(x) − ln(1/K), K = 10 (paper's β)
    motion_k: Positive = 1000.0  # REFERENCE: motion LLR, K = 1000 (paper's 1/A_GP)
    mask_k: Positive = 500.0  # REFERENCE: mask LLR, K = 500 (paper's α)
    alpha: Fraction = 0.5  # REFERENCE: score = β·(α·motion + (1−α)·mask) + (1−β)·objectness
    beta: Fraction = 0.5  # REFERENCE: as above
    floor: Positive = 1e-6  # ours: a term's x is clipped here so ln(0) cannot occur
    # "reference" = the weighted sum above (REFERENCE.md); "calibrated" = ours: a log-odds fit on
    # synthetic truth per proposer (mining/score/calibrated.py; weights in CALIBRATED, from `mine bench calibrate`),
    # refused for a proposer without weights; "auto" = ours, the default: calibrated where the proposer has
    # weights, else reference (held out: less clutter and higher HOTA on every seed, docs/RESULTS.md)
    model: Annotated[str, OneOf(("reference", "calibrated", "auto"))] = "auto"
    # proposer → term → weight of θ = w₀ + Σ_t w·φ_t (mining.score.calibrated.TERMS); a table in a job config
    # changes the terms it names and keeps CALIBRATED's others (to drop a proposer's weights: model = "reference")
    calibrated: dict[str, dict[str, Signed]] = field(default_factory=dict)

    # Known / unknown / unclassified (mining/tubes/category.py).
    known_log_margin: Signed = -1.0  # paper: argmax over the 81 entries is 0; ours: −1, calibrated by `mine bench classify` on synthetic training seeds 0000–0002 (docs/RESULTS.md)
    min_class_evidence: float = 1.0  # ours: classified only with ≥ one frame-equivalent of classifier evidence

    def __post_init__(self) -> None:
        given = self.calibrated or {}
        self.calibrated = {p: {**CALIBRATED.get(p, {}), **given.get(p, {})} for p in {**CALIBRATED, **given}}
