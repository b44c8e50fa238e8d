"""Proposal recall at N (REFERENCE "Evaluation protocols"), as the original evaluation computes it.

Per labelled frame, proposals are ranked by objectness (best first); a ground-truth box is
recalled at N when one of the first N proposals overlaps it with box IoU > 0.5. Recall@N is
the fraction of all ground-truth boxes recalled, pooled over frames, reported separately for
known objects (one of the 80 COCO classes covers them) and unknown ones. A frame with fewer
than N proposals counts with all it has; a labelled frame without proposals recalls nothing.

KITTI has no "unknown" category: ``Misc`` is the closest (objects of no listed type), so
known = the types COCO covers (Car, Van, Truck → car/truck; Pedestrian, Person → person;
Cyclist → person + bicycle; Tram → train) and unknown = Misc. DontCare regions are not
ground truth and are left out.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mining.errors import InputError
from mining.boxes import box_iou
from mining.eval.synthetic import GtFrame
from mining.formats.kitti_tracking import KittiTrackingRows
from mining.masks import areas, box_rle
from mining.types import Proposals

RECALL_IOU = 0.5  # REFERENCE: proposal recall counts box IoU > 0.5
DEFAULT_NS = (1, 5, 10, 20, 50, 100, 300, 500)  # ours: N values reported (the original plots up to 1000)
KITTI_KNOWN = frozenset({"Car", "Van", "Truck", "Pedestrian", "Person", "Cyclist", "Tram"})  # ours: COCO-covered types
KITTI_UNKNOWN = frozenset({"Misc"})  # ours: KITTI's only catch-all type
KITTI_IGNORED = frozenset({"DontCare"})  # KITTI: regions without labels, not objects


def ranked_boxes(proposals: Proposals | np.ndarray) -> np.ndarray:
    """(N, 4) boxes best first: Proposals are sorted by objectness, a plain array is taken as ranked."""
    if isinstance(proposals, Proposals):
        order = np.argsort(-np.asarray(proposals.objectness), kind="stable")
        return np.asarray(proposals.boxes, np.float64).reshape(-1, 4)[order]
    return np.asarray(proposals, np.float64).reshape(-1, 4)


def first_hit_rank(proposal_boxes: np.ndarray, gt_boxes: np.ndarray, iou: float = RECALL_IOU) -> np.ndarray:
    """For each ground-truth box, the rank of the first proposal with box IoU > ``iou`` (inf if none)."""
    gt = np.asarray(gt_boxes, np.float64).reshape(-1, 4)
    rank = np.full(len(gt), np.inf)
    if len(proposal_boxes) == 0:
        return rank
    hits = box_iou(gt, proposal_boxes) > iou
    any_hit = hits.any(axis=1)
    rank[any_hit] = hits[any_hit].argmax(axis=1)
    return rank


def recall_at_n(proposals_per_frame: Sequence[Proposals | np.ndarray], gt_boxes_per_frame: Sequence[np.ndarray],
                gt_known_per_frame: Sequence[np.ndarray], ns: Sequence[int] = DEFAULT_NS,
                iou: float = RECALL_IOU) -> dict:
    """Recall@N over labelled frames, for all, known and unknown ground truth.

    The three sequences run over the same frames. Returns ``{"all" | "known" | "unknown":
    {N: recall}, "n_all" | "n_known" | "n_unknown": number of ground-truth boxes}``; a recall
    over no boxes is NaN.
    """
    if not (len(proposals_per_frame) == len(gt_boxes_per_frame) == len(gt_known_per_frame)):
        raise ValueError("proposals, ground-truth boxes and known flags must cover the same frames")
    ranks, known = [], []
    for props, gt, kn in zip(proposals_per_frame, gt_boxes_per_frame, gt_known_per_frame):
        gt = np.asarray(gt, np.float64).reshape(-1, 4)
        kn = np.asarray(kn, bool).reshape(-1)
        if len(kn) != len(gt):
            raise ValueError(f"{len(gt)} ground-truth boxes but {len(kn)} known flags")
        ranks.append(first_hit_rank(ranked_boxes(props), gt, iou))
        known.append(kn)
    rank = np.concatenate(ranks) if ranks else np.zeros(0)
    kn = np.concatenate(known) if known else np.zeros(0, bool)
    out: dict = {}
    for name, sel in (("all", np.ones_like(kn)), ("known", kn), ("unknown", ~kn)):
        r = rank[sel]
        out[name] = {int(n): (float(np.mean(r < n)) if r.size else float("nan")) for n in ns}
        out[f"n_{name}"] = int(r.size)
    return out


def format_recall(r: dict) -> str:
    """``recall_at_n``'s result as a table: a row each for known, unknown and all objects, a column per N."""
    ns = sorted(r["all"])
    lines = [f"  {'objects':<8} {'count':>6} " + " ".join(f"{'@' + str(n):>6}" for n in ns)]
    for name in ("known", "unknown", "all"):
        lines.append(f"  {name:<8} {r['n_' + name]:>6} " + " ".join(f"{r[name][n]:6.3f}" for n in ns))
    return "\n".join(lines)


def kitti_ground_truth(rows: KittiTrackingRows, frames: Sequence[int],
                       types: set[str] | frozenset[str] | None = None) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per-frame ground-truth boxes and known flags from KITTI tracking labels.

    DontCare is left out; ``types`` (optional) keeps only those types, e.g. {"Car"}. A type
    outside KITTI_KNOWN | KITTI_UNKNOWN | KITTI_IGNORED is an error, not a guess.
    """
    strange = set(np.unique(rows.type).tolist()) - KITTI_KNOWN - KITTI_UNKNOWN - KITTI_IGNORED
    if strange:
        i = int(np.flatnonzero(np.isin(rows.type, sorted(strange)))[0])
        raise InputError(f"KITTI type {rows.type[i]!r} is neither known, unknown nor DontCare", rows.path,
                         int(rows.frame[i]))
    use = ~np.isin(rows.type, list(KITTI_IGNORED))
    if types is not None:
        use &= np.isin(rows.type, list(types))
    boxes, known = [], []
    for f in frames:
        sel = use & (rows.frame == f)
        boxes.append(rows.box[sel])
        known.append(np.isin(rows.type[sel], list(KITTI_KNOWN)))
    return boxes, known


def kitti_truths(rows: KittiTrackingRows, frames: Sequence[int], size: tuple[int, int]) -> dict[int, GtFrame]:
    """Per-frame ground truth of KITTI tracking labels in the synthetic protocol's form, for the
    recall funnel (``funnel.py``, with ``similarity="box"``): each label's box as its mask and
    its box area as its visible pixels, the z of its 3D location (bottom centre, rectified
    camera; the centre has the same z) as its depth; known and unknown as ``kitti_ground_truth``.
    ``size`` is the image's (height, width)."""
    boxes, known = kitti_ground_truth(rows, frames)
    use = ~np.isin(rows.type, list(KITTI_IGNORED))
    h, w = size
    out = {}
    for f, b, kn in zip(frames, boxes, known):
        sel = use & (rows.frame == f)
        b = np.asarray(b, np.float64).reshape(-1, 4)
        rles = [box_rle(x, h, w) for x in b]
        out[int(f)] = GtFrame(track_ids=rows.track_id[sel].astype(np.int64), known=np.asarray(kn, bool),
                              categories=[str(x) for x in rows.type[sel]], rles=rles, areas=areas(rles),
                              boxes=b, depth=rows.location[sel, 2].astype(np.float64), size=(h, w))
    return out
