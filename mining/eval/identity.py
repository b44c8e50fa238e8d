"""Identity metrics IDF1, IDR, IDP (Ristani et al., ECCV-W 2016), as TrackEval computes them.

Each ground-truth id is assigned to at most one tracker id, once for the whole sequence.
For an assignment, a detection of gt id g is an identity true positive (IDTP) in a frame
where the assigned tracker id p is present with similarity S ≥ threshold; every other gt
detection is an IDFN and every other tracker detection an IDFP. The assignment minimises
IDFN + IDFP, which is the same as maximising the IDTPs:

    IDTP = max over one-to-one id assignments of Σ_(g,p) m(g, p),
    m(g, p) = number of frames in which g and p are both present with S ≥ threshold,

found with the Hungarian algorithm. Then IDFN = |gt dets| − IDTP, IDFP = |tracker dets| − IDTP,

    IDF1 = 2·IDTP / (2·IDTP + IDFP + IDFN),   IDR = IDTP / (IDTP + IDFN),   IDP = IDTP / (IDTP + IDFP).

Across sequences the counts add up. Inputs as in ``hota.py``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

MATCH_THRESHOLD = 0.5  # REFERENCE (KITTI MOT / Ristani et al.): IoU ≥ 0.5 makes a pair an identity match

SUM_FIELDS = ("IDTP", "IDFN", "IDFP")


def identity_sums(gt_ids: Sequence[np.ndarray], tracker_ids: Sequence[np.ndarray],
                  similarity: Sequence[np.ndarray], threshold: float = MATCH_THRESHOLD) -> dict[str, int]:
    """IDTP, IDFN, IDFP of one sequence."""
    n_gt = 1 + max((int(x.max()) for x in gt_ids if len(x)), default=-1)
    n_tr = 1 + max((int(x.max()) for x in tracker_ids if len(x)), default=-1)
    m = np.zeros((n_gt, n_tr))
    for g, p, s in zip(gt_ids, tracker_ids, similarity):
        rows, cols = np.nonzero(s >= threshold)
        np.add.at(m, (g[rows], p[cols]), 1)
    rows, cols = linear_sum_assignment(m, maximize=True)
    idtp = int(m[rows, cols].sum())
    n_gt_dets = sum(len(x) for x in gt_ids)
    n_tr_dets = sum(len(x) for x in tracker_ids)
    return {"IDTP": idtp, "IDFN": n_gt_dets - idtp, "IDFP": n_tr_dets - idtp}


def combine_identity_sums(per_sequence: Sequence[dict[str, int]]) -> dict[str, int]:
    """Add the counts of several sequences."""
    return {k: sum(s[k] for s in per_sequence) for k in SUM_FIELDS}


def identity_metrics(sums: dict[str, int]) -> dict[str, float]:
    """IDF1, IDR, IDP from summed counts (each 0 when its denominator is 0)."""
    tp, fn, fp = sums["IDTP"], sums["IDFN"], sums["IDFP"]
    return {
        "IDF1": tp / max(1.0, tp + 0.5 * fp + 0.5 * fn),
        "IDR": tp / max(1.0, tp + fn),
        "IDP": tp / max(1.0, tp + fp),
        "IDTP": int(tp), "IDFN": int(fn), "IDFP": int(fp),
    }
