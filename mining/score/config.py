"""Tube scoring settings: the "4DGVT" unary of REFERENCE.md "Scoring"."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from mining.checks import Fraction, OneOf, Positive, Signed


# The calibrated unary's weights per proposer: `mine bench calibrate [--set proposals.proposer=…]` with the
# defaults (synthetic seeds 0000–0006, 100 frames each, tubes.association "innovation", 2 px jitter; unknown
# objects' tubes weighted up to the known ones'). The seeds 0007–0009 were never used: they are the test.
CALIBRATED: dict[str, dict[str, float]] = {
    # issue 29: refit with the COCO model's generic candidates on (proposals.onnx_generic) and the stereo proposer's
    # colour refinement; 1017 object tubes, 2731 part or clutter; leave-one-seed-out AUC 0.87 (REFERENCE 0.77)
    "onnx+stereo": {"bias": -0.907361, "frame": 0.0684956, "ln_mask_iou": 0.293972, "ln_motion": -0.0546869,
                    "ln_objectness": 0.0225384, "ln_width": 0.0382886, "ln_height": -0.206496,
                    "ln_length": 0.0140287, "ln_width_sq": -0.0585653, "ln_height_sq": -0.0654904,
                    "ln_length_sq": -0.0269371, "known_mass": 0.555992},
    # 456 object tubes (54 on unknown objects), 1145 part or clutter; leave-one-seed-out AUC 0.90
    "stereo": {"bias": -0.897388, "frame": 0.402084, "ln_mask_iou": 0.477829, "ln_motion": -0.0442557,
               "ln_objectness": 8.66293, "ln_width": 0.035429, "ln_height": -0.098054, "ln_length": 0.0183818,
               "ln_width_sq": -0.101705, "ln_height_sq": 0.101927, "ln_length_sq": -0.029515, "known_mass": 0.0},
}


# The calibrated confidence of the classifier's own rows (mining/score/category.py, RowConfidence): two logistics in
# (1, logit s, ln h, ln z, logit s·ln h, logit s·ln z) of a row's max class score s, box height h (px) and depth z (m),
# fit by `mine bench calibrate --calling` on the observed tube frames of synthetic seeds 0000–0006 (100 frames each,
# onnx+stereo with the COCO YOLOv8n-seg int8 model, its generic candidates and the colour-refined stereo masks: issue 29)
# labelled by the truth they overlap (mask IoU ≥ 0.5). 27,682 rows (17,035 on known objects, 844 on unknown ones, 9,803
# on nothing); leave-one-seed-out AUC 0.77–0.89 (on an object), 0.92–0.98 for known | object (the max score alone:
# 0.76–0.94).
ROW_ON_OBJECT: dict[str, float] = {  # P(the row lies on an object, known or not)
    "bias": -0.723345, "logit_score": -0.214962, "ln_height": 0.448603, "ln_depth": 0.326904,
    "logit_x_ln_height": 0.147091, "logit_x_ln_depth": 0.135951}
ROW_KNOWN: dict[str, float] = {  # P(known | on an object) at equal priors (unknown objects' rows weighted up)
    "bias": -44.8634, "logit_score": -5.77047, "ln_height": 7.0155, "ln_depth": 7.02652,
    "logit_x_ln_height": 0.993633, "logit_x_ln_depth": 1.00393}
# The object evidence of a tube called unknown (mining/score/clutter.py), per proposer: logistic in OBJECT_FEATURES
# on the candidate tubes of the same seeds, object against part or clutter (unknown objects weighted up);
# leave-one-seed-out AUC 0.88–0.93.
OBJECT_EVIDENCE: dict[str, dict[str, float]] = {
    "onnx+stereo": {"bias": -5.0881, "ln_observed": 0.802692, "observed_share": 1.39358, "sd_ln_area_3d": 0.746381,
                    "sd_ln_aspect": -0.352434, "mean_fill": 4.06766, "classifier_share": 1.12267,
                    "mean_class_score": 3.72333, "mean_detectability": -0.337726, "ln_speed": 0.302688,
                    "ln_depth": 1.15759, "ln_height_px": -0.162569, "border_share": -1.69733,
                    "mean_ln_mask_iou": 2.71204, "ln_width": 0.822326, "ln_height": -0.604381, "ln_length": -0.128404,
                    "sd_ln_size": 0.276823, "sd_footpoint": -0.424078, "bottom_gap": -10.7877},
}


@dataclass
class KnownMargin:
    """The margin ln P[best known] − ln P[unknown] a tube's posterior must exceed to be called
    known, by ``score.class_confidence`` (the classifier's rows as given, or calibrated)."""

    reference: Signed = -1.0  # paper: argmax over the 81 entries is 0; ours: −1, calibrated by `mine bench classify` on synthetic training seeds 0000–0002 (docs/RESULTS.md)
    calibrated: Signed = -1.0  # ours: the margin with calibrated rows, best balanced accuracy of tubes on objects (0.919) on seeds 0000–0006 (`mine bench calibrate --calling`; −1 in every fold)


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

    # Known / unknown / unclassified (mining/score/category.py, the rule in mining/score/call.py).
    known_margin: KnownMargin = field(default_factory=KnownMargin)  # was score.known_log_margin and score.known_log_margin_calibrated (issue 38)
    min_class_evidence: float = 1.0  # ours: classified only with ≥ one frame-equivalent of classifier evidence
    # "calibrated" = ours (issue 29): a classifier's own row is read through ROW_ON_OBJECT / ROW_KNOWN before the
    # posterior accumulates (a far small pedestrian at 0.25 is a known object the detector is unsure of, not unknown),
    # decided at known_margin.calibrated; "reference" = the paper's row as the classifier gives it (unknown mass
    # 1 − max p), decided at known_margin.reference
    class_confidence: Annotated[str, OneOf(("reference", "calibrated"))] = "calibrated"
    row_on_object: dict[str, Signed] = field(default_factory=lambda: dict(ROW_ON_OBJECT))  # weights of P(row on an object), by mining.score.category.ROW_FEATURES
    row_known: dict[str, Signed] = field(default_factory=lambda: dict(ROW_KNOWN))  # weights of P(known | on an object), likewise
    row_proposers: tuple[str, ...] = ("onnx", "onnx+stereo")  # ours: the jobs whose classifier rows these weights were fit on (the ONNX YOLO-seg decoder's); other classifiers (torch, detections) keep their rows as given
    # Object or clutter before the unknown set (issue 29; mining/score/clutter.py): a tube called unknown whose object
    # evidence gives P(object) < unknown_min_object is "unclassified" = ours, the default: it stays selected but is not
    # called unknown (selection is the unary's judgement; the unknown set is what researchers export, and dropping
    # cost unknown objects: docs/RESULTS.md); "drop" = not offered to co-selection (a candidate in the catalogue,
    # unselected); "off" = no gate (before issue 29). A proposer without OBJECT_EVIDENCE weights has no gate.
    unknown_gate: Annotated[str, OneOf(("off", "drop", "unclassified"))] = "unclassified"
    unknown_min_object: Fraction = 0.5  # ours: more likely an object than not; best mean F1 of the unknown set of 0.5–0.9, leave-one-seed-out on seeds 0000–0006 (`mine bench calibrate --calling`)
    # proposer → term → weight of the object evidence (mining.score.clutter.OBJECT_TERMS); a job table changes the terms
    # it names and keeps OBJECT_EVIDENCE's others
    object_evidence: dict[str, dict[str, Signed]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        given = self.calibrated or {}
        self.calibrated = {p: {**CALIBRATED.get(p, {}), **given.get(p, {})} for p in {**CALIBRATED, **given}}
        given = self.object_evidence or {}
        self.object_evidence = {p: {**OBJECT_EVIDENCE.get(p, {}), **given.get(p, {})}
                                for p in {**OBJECT_EVIDENCE, **given}}
