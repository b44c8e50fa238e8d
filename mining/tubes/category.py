"""Known or unknown: a tube's class from its observations' averaged 81-way posterior.

The paper calls a tube *unknown* when it is not confidently one of the 80 COCO classes.
The original stored no calibrated known-ness (REFERENCE.md ⚠); we keep the averaged
posterior, its argmax category and probability, and a ``known`` flag with an explicit
threshold. Tubes whose proposer has no classes (e.g. the stereo proposer) get no
posterior and are unknown.
"""

from __future__ import annotations

import numpy as np

from mining.proposals.coco import COCO_CLASSES
from mining.types import UNKNOWN_CLASS, Tube, TubeCategory


def tube_category(tube: Tube, known_threshold: float) -> TubeCategory:
    rows = [f.posterior for f in tube.frames
            if f.observed and f.posterior is not None and np.isfinite(f.posterior).all()]
    if not rows:
        return TubeCategory(None, "unknown", float("nan"), False, "unknown")
    mean = np.mean(np.asarray(rows, np.float64), axis=0)
    best = int(np.argmax(mean))
    prob = float(mean[best])
    best_known = COCO_CLASSES[int(np.argmax(mean[:UNKNOWN_CLASS]))]
    if best == UNKNOWN_CLASS:
        return TubeCategory(mean, "unknown", prob, False, best_known)
    return TubeCategory(mean, COCO_CLASSES[best], prob, prob >= known_threshold, best_known)
