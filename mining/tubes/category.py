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

Decision. A tube with evidence below ``min_class_evidence`` (one frame-equivalent of a
classifier's own rows by default) is unclassified: known = None, category None. Otherwise,
with k* the most probable of the 80 classes, the tube is known as k* when

    ln P[k*] − ln P[unknown] > known_log_margin,

and unknown otherwise. ``known_log_margin`` = 0 is the paper's argmax over the 81 entries;
``mine bench classify`` measures whether another margin separates known from unknown
objects better on training data.
"""

from __future__ import annotations

import numpy as np

from mining.formats.coco import COCO_CLASSES
from mining.types import UNKNOWN_CLASS, Tube, TubeCategory

UNCLASSIFIED = TubeCategory(None, None, float("nan"), None, None, 0, 0.0)


def accumulate_posterior(tube: Tube) -> tuple[np.ndarray | None, int, float]:
    """The evidence-weighted mean posterior of the observed frames, their count and Σ weights."""
    rows, weights = [], []
    for f in tube.frames:
        if not f.observed or f.posterior is None or not np.isfinite(f.posterior).all():
            continue
        w = float(f.class_weight)
        if not w > 0:
            continue
        rows.append(f.posterior)
        weights.append(w)
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


def tube_category(tube: Tube, log_margin: float = 0.0, min_evidence: float = 1.0) -> TubeCategory:
    mean, n, evidence = accumulate_posterior(tube)
    if mean is None or evidence < min_evidence:
        return TubeCategory(None, None, float("nan"), None, None, n, evidence)
    known, best = decide(mean, log_margin)
    if known:
        return TubeCategory(mean, COCO_CLASSES[best], float(mean[best]), True, COCO_CLASSES[best], n, evidence)
    return TubeCategory(mean, "unknown", float(mean[UNKNOWN_CLASS]), False, COCO_CLASSES[best], n, evidence)
