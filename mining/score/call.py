"""The call of a tube: known, unknown, unclassified, or clutter kept from co-selection.

Each tube is called from the job's score settings (``ScoreConfig``) and the proposer whose
evidence it carries (its rows' confidence and its object evidence were fit per proposer):

1. **Its class** (``mining.score.category``). The posteriors of the frames where a classifier
   looked are accumulated over the tube. With ``class_confidence = "calibrated"`` and a
   proposer in ``row_proposers`` (the jobs whose classifier rows the weights were fit on), a
   classifier's own row is first read through ``RowConfidence(row_on_object, row_known)`` and
   the decision is made at ``known_margin.calibrated``; otherwise the rows count as the
   classifier gives them, at ``known_margin.reference`` (``class_mode`` says which). A tube
   with less evidence than ``min_class_evidence`` is *unclassified* (known None); else it is
   *known* as its best class k* when ln P[k*] − ln P[unknown] exceeds the margin, *unknown*
   otherwise.
2. **The object gate** (``mining.score.clutter``), before the unknown set: where the proposer
   has ``object_evidence`` weights and ``unknown_gate`` is not "off", a tube called unknown
   whose object evidence gives P(object) < ``unknown_min_object`` is clutter. With
   ``unknown_gate = "unclassified"`` its call is withdrawn (category None, known None,
   probability NaN; its posterior, best class and evidence kept) and it is still offered to
   co-selection; with "drop" it keeps its call but is never offered to co-selection (a
   candidate in the catalogue, unselected, so it cannot suppress an overlapping object).
   Known and unclassified tubes pass the gate untouched.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

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
    return [tube_category(t, margin, cfg.min_class_evidence, conf) for t in tubes]


def object_gate(cfg: ScoreConfig, proposer: str) -> Callable[[Tube], bool] | None:
    """Whether a tube is likely an object (``unknown_gate``; None: no gate for this proposer)."""
    weights = cfg.object_evidence.get(proposer)
    if cfg.unknown_gate == "off" or not weights:
        return None
    p = cfg.unknown_min_object
    cut = np.log(p / (1.0 - p)) if 0 < p < 1 else (-np.inf if p <= 0 else np.inf)
    return lambda tube: object_log_odds(tube, weights) >= cut


def call_tubes(tubes: list[Tube], cfg: ScoreConfig, proposer: str) -> tuple[list[TubeCategory], np.ndarray]:
    """Each tube's call and whether it is offered to co-selection (bool per tube), by the rule
    of the module docstring."""
    cats = categories(tubes, cfg, proposer)
    offered = np.ones(len(tubes), bool)
    gate = object_gate(cfg, proposer)
    if gate is None:
        return cats, offered
    clutter = np.array([c.known is False and not gate(t) for t, c in zip(tubes, cats)], bool)
    if cfg.unknown_gate == "drop":
        offered &= ~clutter
    else:
        cats = [dataclasses.replace(c, category=None, probability=float("nan"), known=None) if x else c
                for c, x in zip(cats, clutter)]
    return cats, offered
