"""Known, unknown or unclassified: a tube's class from the frames where a classifier looked.

The paper gives every proposal an 81-way posterior (80 COCO classes + unknown) and calls a
tube *unknown* when that posterior, accumulated over the tube, is not one of the 80 classes.
A proposer without classes (the stereo proposer alone) says nothing either way, so such a
tube is *unclassified*, not unknown.

Accumulation. Each observed frame f carries its observation's posterior p_f (81,) and an
evidence weight w_f (``Proposals.class_weights``): 1 for a classifier's own rows; for a
class-agnostic proposal that the classifier looked at and did not find (``onnx+stereo``),
p_f is all "unknown" and w_f the probability that the detector would have found a COCO
object of that size there (``mining.proposals.union``); 0 where no classifier looked. The
tube's posterior is the weighted mean

    P = Σ_f w_f p_f / Σ_f w_f,

over the frames with w_f > 0 (``classified_frames``; Σ w_f is the ``evidence``).

Calibrated rows (issue 29, ``score.class_confidence = "calibrated"``). A classifier's own row
says "unknown" with mass 1 − max p, so a far small pedestrian found at 0.25 in every frame
accumulates into an unknown tube. With a ``RowConfidence`` the row is read instead through two
logistics of its max class score, box height and depth, fitted on labelled rows of synthetic
training seeds (``mine bench calibrate --calling``): the known classes share P(known | on an
object) in the ratios of the row's scores, "unknown" the rest, and the row weighs P(on an
object) (a row on background says little either way). Class-agnostic rows keep their own.

Decision (the whole rule, the object gate included: ``mining.score.call``). A tube no
classifier looked at (``classified_frames`` 0) is unclassified: known = None, category None.
Otherwise, with k* the most probable of the 80 classes, the tube is known as k* when

    ln P[k*] − ln P[unknown] > margin,   margin ≥ 0,

and unknown otherwise (the margin: ``score.known_margin``'s entry for the rows' reading,
``mining.score.call``). A margin of 0 is the paper's argmax over the 81 entries; it is never
negative, so a tube called known has its class more probable than unknown, and P[unknown] < 0.5.
However little evidence a tube carries, its call is what its stored posterior says (the
evidence is stored beside it); ``mine bench classify`` measures margins on training data.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from mining.formats.coco import COCO_CLASSES
from mining.types import UNKNOWN_CLASS, Tube, TubeCategory, TubeFrame, max_class_score

UNCLASSIFIED = TubeCategory(None, None, float("nan"), None, None, 0, 0.0)

# The evidence of a classifier's own row, in the order of the calibrated confidence's weights.
ROW_FEATURES = ("bias", "logit_score", "ln_height", "ln_depth", "logit_x_ln_height", "logit_x_ln_depth")
MIN_SCORE = 1e-3  # ours: max class scores are clipped to [1e-3, 1 − 1e-3] before the logit (a score of 0 or 1 is none)


@dataclass(frozen=True)
class RowConfidence:
    """The calibrated confidence of a classifier's own row (issue 29), two logistics in
    ``row_features``: ``on_object`` = P(the row lies on an object, known or not) and ``known``
    = P(that object is one of the 80 classes | it is an object). Weights by ROW_FEATURES name
    (a missing name weighs 0); fitted by ``mine bench calibrate --calling``."""

    on_object: Mapping[str, float]
    known: Mapping[str, float]

    def __call__(self, score: float, height_px: float, depth_m: float) -> tuple[float, float]:
        """(P(on an object), P(known | on an object)) of one row."""
        x = row_features(np.array([score]), np.array([height_px]), np.array([depth_m]))[0]
        return tuple(float(1.0 / (1.0 + np.exp(-(x @ _vector(w))))) for w in (self.on_object, self.known))


def _vector(weights: Mapping[str, float]) -> np.ndarray:
    return np.array([float(weights.get(k, 0.0)) for k in ROW_FEATURES])


def row_features(score: np.ndarray, height_px: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
    """(N, len(ROW_FEATURES)) evidence of classifier rows: max class score, box height (px), depth (m)."""
    s = np.clip(np.asarray(score, np.float64), MIN_SCORE, 1.0 - MIN_SCORE)
    logit = np.log(s / (1.0 - s))
    ln_h = np.log(np.clip(np.nan_to_num(np.asarray(height_px, np.float64), nan=1.0), 1.0, None))
    ln_z = np.log(np.clip(np.nan_to_num(np.asarray(depth_m, np.float64), nan=1.0), 1.0, None))
    return np.column_stack([np.ones(len(s)), logit, ln_h, ln_z, logit * ln_h, logit * ln_z])


def frame_class_evidence(f: TubeFrame, confidence: RowConfidence | None = None) -> tuple[np.ndarray, float] | None:
    """(posterior, weight) a tube frame adds to its tube's class, None where no classifier looked.

    With ``confidence``, a classifier's own row (max class score > 0) is replaced by its
    calibrated reading: the known classes share P(known | object) in the ratios of the row's
    scores, "unknown" holds the rest, and the row weighs P(on an object) times its weight, so a
    row on background says little either way. Class-agnostic rows keep their own.
    """
    if not f.observed or f.posterior is None or not np.isfinite(f.posterior).all():
        return None
    w = float(f.class_weight)
    if not w > 0:
        return None
    post = np.asarray(f.posterior, np.float64)
    score = max_class_score(post) if confidence is not None else 0.0
    if score <= 0:
        return post, w
    on_object, known = confidence(score, float(f.box[3] - f.box[1]), float(f.position_cam[2]))
    classes = post[:UNKNOWN_CLASS] / post[:UNKNOWN_CLASS].sum()
    return np.concatenate([known * classes, [1.0 - known]]), w * on_object


def accumulate_posterior(tube: Tube, confidence: RowConfidence | None = None) -> tuple[np.ndarray | None, int, float]:
    """The evidence-weighted mean posterior of the observed frames, their count and Σ weights
    (``confidence``: the classifier's rows as calibrated, ``frame_class_evidence``)."""
    rows, weights = [], []
    for f in tube.frames:
        ev = frame_class_evidence(f, confidence)
        if ev is None or not ev[1] > 0:
            continue
        rows.append(ev[0])
        weights.append(ev[1])
    if not rows:
        return None, 0, 0.0
    w = np.asarray(weights, np.float64)
    mean = (np.asarray(rows, np.float64) * w[:, None]).sum(axis=0) / w.sum()
    return mean, len(rows), float(w.sum())


def decide(posterior: np.ndarray, log_margin: float) -> tuple[bool, int]:
    """(known, best of the 80 classes) for an accumulated posterior (module docstring)."""
    best = int(np.argmax(posterior[:UNKNOWN_CLASS]))
    p_known, p_unknown = float(posterior[best]), float(posterior[UNKNOWN_CLASS])
    if p_known <= 0:
        return False, best
    known = p_unknown <= 0 or np.log(p_known) - np.log(p_unknown) > log_margin
    return bool(known), best


def tube_category(tube: Tube, log_margin: float = 0.0, confidence: RowConfidence | None = None) -> TubeCategory:
    """The tube's class call by the module docstring's decision (``log_margin`` ≥ 0)."""
    mean, n, evidence = accumulate_posterior(tube, confidence)
    if mean is None:
        return TubeCategory(None, None, float("nan"), None, None, n, evidence)
    known, best = decide(mean, log_margin)
    if known:
        return TubeCategory(mean, COCO_CLASSES[best], float(mean[best]), True, COCO_CLASSES[best], n, evidence)
    return TubeCategory(mean, "unknown", float(mean[UNKNOWN_CLASS]), False, COCO_CLASSES[best], n, evidence)
