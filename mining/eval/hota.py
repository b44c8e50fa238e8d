"""HOTA: Higher Order Tracking Accuracy (Luiten et al., IJCV 2020), as TrackEval reports it.

For a localisation threshold α a ground-truth detection and a tracker detection may match
when their similarity S ≥ α. With TP, FN, FP the matched / unmatched detections:

    DetA_α = |TP| / (|TP| + |FN| + |FP|)
    A(c)   = |TPA(c)| / (|TPA(c)| + |FNA(c)| + |FPA(c)|)      for each TP c = (gt id g, tracker id p)
           = n(g, p) / (n(g) + n(p) − n(g, p))                 n: detection / match counts over the sequence
    AssA_α = mean of A(c) over all TPs
    HOTA_α = sqrt(DetA_α · AssA_α)

and the reported HOTA is the mean over α = 0.05, 0.10, …, 0.95. DetRe/DetPr, AssRe/AssPr and
LocA (mean S of the TPs) follow the same paper.

Matching. The paper matches each frame with the Hungarian algorithm maximising
"1/ε + A_max(c) + ε·S" over pairs with S ≥ α. TrackEval (whose numbers we must reproduce)
uses one matching for all α: it maximises A_max(c)·S, where A_max is a Jaccard score of
the two ids computed before matching from all frames, counting each pair with its
"soft" overlap S / (row sum + column sum − S) of the frame's similarity matrix; pairs with
S < α are then dropped. We do the same.

Across sequences the detection counts add up and AssA (likewise AssRe, AssPr, LocA) is the
TP-weighted mean: the sums over TPs are kept and divided at the end.

Inputs (per frame t): ``gt_ids[t]`` and ``tracker_ids[t]`` are 0-based contiguous ids,
``similarity[t]`` is the (len(gt_ids[t]), len(tracker_ids[t])) similarity matrix.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

# REFERENCE (HOTA paper / TrackEval): α = 0.05 … 0.95 in steps of 0.05 (19 thresholds).
ALPHAS = np.round(np.arange(1, 20) * 0.05, 2)
_EPS = np.finfo(float).eps  # comparisons with a tolerance of one ulp, as TrackEval does

# Sums that add up across sequences, one value per α.
SUM_FIELDS = ("TP", "FN", "FP", "ass_sum", "ass_re_sum", "ass_pr_sum", "loc_sum")


def _id_counts(ids: Sequence[np.ndarray]) -> tuple[np.ndarray, int]:
    n = 1 + max((int(x.max()) for x in ids if len(x)), default=-1)
    counts = np.zeros(n)
    for x in ids:
        counts[x] += 1
    return counts, n


def hota_sums(gt_ids: Sequence[np.ndarray], tracker_ids: Sequence[np.ndarray],
              similarity: Sequence[np.ndarray]) -> dict[str, np.ndarray]:
    """Per-α summable counts of one sequence (see ``SUM_FIELDS``)."""
    sums = {k: np.zeros(len(ALPHAS)) for k in SUM_FIELDS}
    gt_count, n_gt = _id_counts(gt_ids)  # n(g)
    tr_count, n_tr = _id_counts(tracker_ids)  # n(p)

    # A_max: id-level Jaccard from soft per-frame overlaps, before any matching.
    soft_matches = np.zeros((n_gt, n_tr))
    for g, p, s in zip(gt_ids, tracker_ids, similarity):
        if s.size == 0:
            continue
        union = s.sum(axis=0, keepdims=True) + s.sum(axis=1, keepdims=True) - s
        soft = np.divide(s, union, out=np.zeros_like(s), where=union > _EPS)
        soft_matches[g[:, None], p[None, :]] += soft
    denominator = gt_count[:, None] + tr_count[None, :] - soft_matches
    a_max = np.divide(soft_matches, denominator, out=np.zeros_like(soft_matches), where=denominator > 0)

    # Frame-by-frame matching, once for all α: the matched pairs and their similarity.
    matched_g, matched_p, matched_s = [], [], []
    for g, p, s in zip(gt_ids, tracker_ids, similarity):
        if len(g) == 0 or len(p) == 0:
            continue
        rows, cols = linear_sum_assignment(a_max[g[:, None], p[None, :]] * s, maximize=True)
        matched_g.append(g[rows])
        matched_p.append(p[cols])
        matched_s.append(s[rows, cols])
    matched_g = np.concatenate(matched_g or [np.empty(0, int)])
    matched_p = np.concatenate(matched_p or [np.empty(0, int)])
    matched_s = np.concatenate(matched_s or [np.empty(0)])

    n_gt_dets, n_tr_dets = gt_count.sum(), tr_count.sum()
    for a, alpha in enumerate(ALPHAS):
        tp = matched_s >= alpha - _EPS  # a matched pair is a TP at α only if S ≥ α
        sums["TP"][a] = tp.sum()
        sums["FN"][a] = n_gt_dets - tp.sum()
        sums["FP"][a] = n_tr_dets - tp.sum()
        sums["loc_sum"][a] = matched_s[tp].sum()
        # n(g, p): TPs of each id pair. Each of them scores A(c), so the sum over TPs weights A(c) by n(g, p).
        n_gp = np.bincount(matched_g[tp] * n_tr + matched_p[tp], minlength=n_gt * n_tr).reshape(n_gt, n_tr)
        sums["ass_sum"][a] = (n_gp * n_gp / np.maximum(1, gt_count[:, None] + tr_count[None, :] - n_gp)).sum()
        sums["ass_re_sum"][a] = (n_gp * n_gp / np.maximum(1, gt_count[:, None])).sum()
        sums["ass_pr_sum"][a] = (n_gp * n_gp / np.maximum(1, tr_count[None, :])).sum()
    return sums


def combine_hota_sums(per_sequence: Sequence[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Add the summable counts of several sequences."""
    return {k: sum((s[k] for s in per_sequence), np.zeros(len(ALPHAS))) for k in SUM_FIELDS}


def hota_metrics(sums: dict[str, np.ndarray]) -> dict[str, float]:
    """Final HOTA metrics (means over α) from summed counts."""
    tp, fn, fp = sums["TP"], sums["FN"], sums["FP"]
    det_re = tp / np.maximum(1, tp + fn)
    det_pr = tp / np.maximum(1, tp + fp)
    det_a = tp / np.maximum(1, tp + fn + fp)
    ass_a = sums["ass_sum"] / np.maximum(1, tp)
    ass_re = sums["ass_re_sum"] / np.maximum(1, tp)
    ass_pr = sums["ass_pr_sum"] / np.maximum(1, tp)
    # With no TP at all TrackEval reports LocA = 1 (nothing was mislocalised).
    loc_a = np.divide(sums["loc_sum"], tp, out=np.ones(len(ALPHAS)), where=tp > 0)
    hota = np.sqrt(det_a * ass_a)
    return {
        "HOTA": float(hota.mean()),
        "DetA": float(det_a.mean()),
        "AssA": float(ass_a.mean()),
        "DetRe": float(det_re.mean()),
        "DetPr": float(det_pr.mean()),
        "AssRe": float(ass_re.mean()),
        "AssPr": float(ass_pr.mean()),
        "LocA": float(loc_a.mean()),
        "HOTA(0)": float(hota[0]),  # at α = 0.05
    }
