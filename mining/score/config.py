"""Tube scoring settings: the "4DGVT" unary of REFERENCE.md "Scoring"."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from mining.checks import Fraction, OneOf, Positive, Signed
from mining.score.fits import OBJECT_FIT, UNARY_FIT, proposer_weights, row_weights


# The fitted weights: package data with their provenance (command, commit, seeds, samples, AUC), read from
# mining/score/fits/*.toml (mining/score/fits.py) and written there by the bench that fits them.
# The calibrated unary's weights per proposer ([unary] of fits/<proposer>.toml; `mine bench calibrate --write`).
CALIBRATED: dict[str, dict[str, float]] = proposer_weights(UNARY_FIT)
# The calibrated confidence of the classifier's own rows (mining/score/category.py, RowConfidence; fits/rows.toml,
# `mine bench calibrate --calling --write`): P(the row lies on an object, known or not) and P(known | on an object)
# at equal priors.
ROW_ON_OBJECT, ROW_KNOWN = row_weights()
# The object evidence of a tube called unknown (mining/score/clutter.py) per proposer ([object_evidence] of
# fits/<proposer>.toml; `mine bench calibrate --calling --write`).
OBJECT_EVIDENCE: dict[str, dict[str, float]] = proposer_weights(OBJECT_FIT)


@dataclass
class KnownMargin:
    """The margin ln P[best known] − ln P[unknown] a tube's posterior must exceed to be called
    known, by ``score.class_confidence`` (the classifier's rows as given, or calibrated). A job
    refuses a negative one (``config._check_job``); a recorded job of before issue 39 holds −1."""

    reference: Signed = 0.0  # paper: the argmax over the 81 entries (0); never negative (mining/score/call.py), so a known call's class always beats unknown (−1 before issue 39)
    calibrated: Signed = 0.0  # likewise with calibrated rows (`mine bench calibrate --calling` picks it among margins ≥ 0; −1 before issue 39)


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
    # "calibrated" = ours (issue 29): a classifier's own row is read through ROW_ON_OBJECT / ROW_KNOWN before the
    # posterior accumulates (a far small pedestrian at 0.25 is a known object the detector is unsure of, not unknown),
    # decided at known_margin.calibrated; "reference" = the paper's row as the classifier gives it (unknown mass
    # 1 − max p), decided at known_margin.reference
    class_confidence: Annotated[str, OneOf(("reference", "calibrated"))] = "calibrated"
    row_on_object: dict[str, Signed] = field(default_factory=lambda: dict(ROW_ON_OBJECT))  # weights of P(row on an object), by mining.score.category.ROW_FEATURES
    row_known: dict[str, Signed] = field(default_factory=lambda: dict(ROW_KNOWN))  # weights of P(known | on an object), likewise
    row_proposers: tuple[str, ...] = ("onnx", "onnx+stereo")  # ours: the jobs whose classifier rows these weights were fit on (the ONNX YOLO-seg decoder's); other classifiers (torch, detections) keep their rows as given
    # Object or clutter before the unknown set (issue 29; mining/score/clutter.py): a tube unknown wins whose object
    # evidence gives P(object) (stored: object_prob) < unknown_min_object is called "clutter" (issue 39: its own call,
    # never folded into unclassified). "call" = ours, the default: it stays offered to co-selection (selection is the
    # unary's judgement; the unknown set is what researchers export, and dropping cost unknown objects:
    # docs/RESULTS.md); "drop" = not offered to co-selection (a candidate in the catalogue, unselected); "off" = no
    # gate (before issue 29). A proposer without OBJECT_EVIDENCE weights has no gate.
    unknown_gate: Annotated[str, OneOf(("off", "drop", "call"))] = "call"
    unknown_min_object: Fraction = 0.5  # ours: more likely an object than not (issue 29: best mean F1 of the unknown set, leave-one-seed-out on seeds 0000–0006; issue 39: 0.7 by 0.022 of F1, but tubes on unknown objects called unknown 0.88 → 0.72: 0.5 kept, docs/RESULTS.md)
    # proposer → term → weight of the object evidence (mining.score.clutter.OBJECT_TERMS); a job table changes the terms
    # it names and keeps OBJECT_EVIDENCE's others
    object_evidence: dict[str, dict[str, Signed]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        given = self.calibrated or {}
        self.calibrated = {p: {**CALIBRATED.get(p, {}), **given.get(p, {})} for p in {**CALIBRATED, **given}}
        given = self.object_evidence or {}
        self.object_evidence = {p: {**OBJECT_EVIDENCE.get(p, {}), **given.get(p, {})}
                                for p in {**OBJECT_EVIDENCE, **given}}
