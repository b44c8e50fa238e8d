"""CLEAR MOT metrics (Bernardin & Stiefelhagen 2008) with TrackEval's matching rule.

Per frame, ground-truth and tracker detections are matched one-to-one; a pair can match
only if its similarity S ≥ threshold (box IoU ≥ 0.5 on KITTI). The matching

1. keeps, where possible, the correspondences of the previous frame (a gt id matched to the
   same tracker id one frame earlier): such pairs get a bonus larger than any sum of
   similarities, so the Hungarian algorithm never trades one of them for better overlap;
2. among the rest maximises the total similarity (the Hungarian algorithm).

Counts over the sequence:

* TP, FN, FP — matched gt, unmatched gt, unmatched tracker detections;
* IDSW — a gt id matched to a tracker id other than the one it was last matched to
  (any number of frames earlier);
* Frag — times a gt track resumes being matched after an interruption;
* MT / PT / ML — gt ids matched in > 80 %, 20–80 %, < 20 % of the frames they are present in.

    MOTA = (TP − FP − IDSW) / (TP + FN)     MODA = (TP − FP) / (TP + FN)
    MOTP = mean similarity of the TPs       sMOTA = (Σ S − FP − IDSW) / (TP + FN)

Across sequences all counts (MT/PT/ML included) add up. Inputs as in ``hota.py``.
The ratios use max(1, denominator), as TrackEval does, so a sequence without ground truth
has MOTA = −FP (TrackEval leaves such a sequence's own MOTA at 0; combined numbers agree).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

MATCH_THRESHOLD = 0.5  # REFERENCE (KITTI MOT): a match needs box IoU ≥ 0.5
MOSTLY_TRACKED = 0.8  # REFERENCE (CLEAR MOT, TrackEval): MT means tracked in > 80 % of frames
MOSTLY_LOST = 0.2  # REFERENCE (CLEAR MOT, TrackEval): ML means tracked in < 20 % of frames
_CONTINUATION_BONUS = 1000.0  # ours: exceeds any sum of similarities in a frame (each ≤ 1)
_EPS = np.finfo(float).eps

SUM_FIELDS = ("TP", "FN", "FP", "IDSW", "MT", "PT", "ML", "Frag", "MOTP_sum", "Frames")


def clear_sums(gt_ids: Sequence[np.ndarray], tracker_ids: Sequence[np.ndarray],
               similarity: Sequence[np.ndarray], threshold: float = MATCH_THRESHOLD) -> dict[str, float]:
    """Summable CLEAR counts of one sequence (see ``SUM_FIELDS``)."""
    n_gt = 1 + max((int(x.max()) for x in gt_ids if len(x)), default=-1)
    sums = dict.fromkeys(SUM_FIELDS, 0.0)
    sums["Frames"] = len(gt_ids)
    present = np.zeros(n_gt)  # frames each gt id is present in
    tracked = np.zeros(n_gt)  # frames each gt id is matched in
    starts = np.zeros(n_gt)  # times each gt id starts being matched (first time included)
    last_match = np.full(n_gt, -1)  # tracker id each gt id was last matched to, ever
    prev_match = np.full(n_gt, -1)  # tracker id each gt id was matched to in the previous frame

    for g, p, s in zip(gt_ids, tracker_ids, similarity):
        present[g] += 1
        if len(g) == 0 or len(p) == 0:
            sums["FN"] += len(g)
            sums["FP"] += len(p)
            # As in TrackEval, a frame without gt or without tracker detections leaves the
            # previous-frame correspondences in place: they may continue in the next frame.
            continue
        continues = p[None, :] == prev_match[g][:, None]
        score = _CONTINUATION_BONUS * continues + s
        score[s < threshold - _EPS] = 0
        rows, cols = linear_sum_assignment(score, maximize=True)
        ok = score[rows, cols] > _EPS
        rows, cols = rows[ok], cols[ok]
        mg, mp = g[rows], p[cols]

        sums["IDSW"] += int(np.sum((last_match[mg] >= 0) & (last_match[mg] != mp)))
        tracked[mg] += 1
        was_tracked = prev_match >= 0
        last_match[mg] = mp
        prev_match[:] = -1
        prev_match[mg] = mp
        starts += (prev_match >= 0) & ~was_tracked

        sums["TP"] += len(rows)
        sums["FN"] += len(g) - len(rows)
        sums["FP"] += len(p) - len(rows)
        sums["MOTP_sum"] += float(s[rows, cols].sum())

    ratio = tracked[present > 0] / present[present > 0]
    sums["MT"] = int(np.sum(ratio > MOSTLY_TRACKED))
    sums["PT"] = int(np.sum(ratio >= MOSTLY_LOST)) - sums["MT"]
    sums["ML"] = n_gt - sums["MT"] - sums["PT"]
    sums["Frag"] = float(np.sum(starts[starts > 0] - 1))
    return sums


def combine_clear_sums(per_sequence: Sequence[dict[str, float]]) -> dict[str, float]:
    """Add the counts of several sequences."""
    return {k: sum(s[k] for s in per_sequence) for k in SUM_FIELDS}


def clear_metrics(sums: dict[str, float]) -> dict[str, float]:
    """Final CLEAR MOT metrics from summed counts."""
    tp, fn, fp, idsw = sums["TP"], sums["FN"], sums["FP"], sums["IDSW"]
    n_gt_dets = max(1.0, tp + fn)
    n_gt_ids = max(1.0, sums["MT"] + sums["PT"] + sums["ML"])
    return {
        "MOTA": (tp - fp - idsw) / n_gt_dets,
        "MOTP": sums["MOTP_sum"] / max(1.0, tp),
        "MODA": (tp - fp) / n_gt_dets,
        "sMOTA": (sums["MOTP_sum"] - fp - idsw) / n_gt_dets,
        "Recall": tp / n_gt_dets,
        "Precision": tp / max(1.0, tp + fp),
        "TP": int(tp), "FN": int(fn), "FP": int(fp), "IDSW": int(idsw), "Frag": int(sums["Frag"]),
        "MT": int(sums["MT"]), "PT": int(sums["PT"]), "ML": int(sums["ML"]),
        "MTR": sums["MT"] / n_gt_ids, "PTR": sums["PT"] / n_gt_ids, "MLR": sums["ML"] / n_gt_ids,
        "Frames": int(sums["Frames"]),
    }
