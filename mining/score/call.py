"""The call of a tube: known, unknown, clutter or unclassified, one rule read from what is stored.

Each tube is called from the job's score settings (``ScoreConfig``) and the proposer whose
evidence it carries (its rows' confidence and its object evidence were fit per proposer). The
rule, in the terms of the catalogue's columns (``class_posterior`` P, 80 COCO classes and
unknown; k* the most probable of the 80; ``object_prob``):

==============  ===============================================================  =====  ==========
call            when                                                             known  category
==============  ===============================================================  =====  ==========
unclassified    ``classified_frames`` = 0: no classifier looked at the tube      null   null
known           ln P[k*] − ln P[unknown] > ``known_margin`` (≥ 0)                true   k*, P[k*]
unknown         otherwise, and the object gate passes (or there is no gate)      false  "unknown"
clutter         otherwise, and the object gate says ``object_prob`` <            false  "unknown"
                ``unknown_min_object``: not an object, kept out of the unknown set
==============  ===============================================================  =====  ==========

1. **Its class** (``mining.score.category``). The posteriors of the frames where a classifier
   looked are accumulated over the tube, however little evidence they carry (the evidence is
   stored beside the call, ``class_evidence``). With ``class_confidence = "calibrated"`` and a
   proposer in ``row_proposers``, a classifier's own row is first read through
   ``RowConfidence(row_on_object, row_known)`` and the decision is made at
   ``known_margin.calibrated``; otherwise the rows count as the classifier gives them, at
   ``known_margin.reference`` (``class_mode`` says which). The margin is never negative, so a
   known call's class is always more probable than unknown (and P[unknown] < 0.5): the badge
   never contradicts the posterior stored beside it.
2. **The object gate** (``mining.score.clutter``): where the proposer has ``object_evidence``
   weights and ``unknown_gate`` is not "off", a tube unknown wins is judged: P(object) is
   stored (``object_prob``) and below ``unknown_min_object`` the tube is *clutter*. With
   ``unknown_gate = "call"`` it is still offered to co-selection (selection is the unary's
   judgement); with "drop" it is not (a candidate in the catalogue, unselected, so it cannot
   suppress an overlapping object). Known and unclassified tubes are not judged.

The unknown set (the catalogue's ``unknown_tubes``, the exports' "unknown", ``mine eval``'s
unknown set) is the selected tubes whose call is unknown.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
from scipy.special import expit

from mining.score.category import RowConfidence, tube_category
from mining.score.clutter import object_log_odds
from mining.score.config import ScoreConfig
from mining.types import Tube, TubeCategory


def class_mode(cfg: ScoreConfig, proposer: str) -> str:
    """"calibrated" when the classifier's rows are read through the calibrated confidence for
    this proposer (``class_confidence`` "calibrated" and the proposer in ``row_proposers``),
    else "reference": the entry of ``known_margin`` that decides."""
    return "calibrated" if cfg.class_confidence == "calibrated" and proposer in cfg.row_proposers else "reference"


def categories(tubes: list[Tube], cfg: ScoreConfig, proposer: str) -> list[TubeCategory]:
    """Each tube's known / unknown / unclassified call (step 1 of the module docstring)."""
    mode = class_mode(cfg, proposer)
    conf = RowConfidence(cfg.row_on_object, cfg.row_known) if mode == "calibrated" else None
    margin = getattr(cfg.known_margin, mode)
    return [tube_category(t, margin, conf) for t in tubes]


def object_gate(cfg: ScoreConfig, proposer: str) -> Callable[[Tube], float] | None:
    """P(object) of a tube by its object evidence (``unknown_gate``; None: no gate for this proposer)."""
    weights = cfg.object_evidence.get(proposer)
    if cfg.unknown_gate == "off" or not weights:
        return None
    return lambda tube: float(expit(object_log_odds(tube, weights)))


def call_tubes(tubes: list[Tube], cfg: ScoreConfig, proposer: str) -> tuple[list[TubeCategory], np.ndarray]:
    """Each tube's call and whether it is offered to co-selection (bool per tube), by the rule
    of the module docstring."""
    cats = categories(tubes, cfg, proposer)
    offered = np.ones(len(tubes), bool)
    gate = object_gate(cfg, proposer)
    if gate is None:
        return cats, offered
    for i, (t, c) in enumerate(zip(tubes, cats)):
        if c.known is False:
            p = gate(t)
            cats[i] = dataclasses.replace(c, object_prob=p, clutter=not p >= cfg.unknown_min_object)
    if cfg.unknown_gate == "drop":
        offered &= np.array([not c.clutter for c in cats], bool)
    return cats, offered
