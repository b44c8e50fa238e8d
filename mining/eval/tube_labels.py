"""What each candidate tube is, against exact ground truth: object, part, clutter or ignored.

The training labels of the calibrated unary (``mining.score.calibrated``, ``mine bench
calibrate``). Unlike the synthetic protocol's one-to-one matching (``mining.eval.synthetic``,
where a duplicate that lost the matching counts as clutter), a tube is labelled by itself,
since the unary judges a tube alone and co-selection's overlap term removes duplicates.

Per observed frame of the tube inside the truth's frames (``FunnelProtocol`` constants):

* **object**: mask IoU ≥ ``iou_threshold`` with an evaluated ground-truth object;
* **ignored**: IoU ≥ ``iou_threshold`` only with an ignored object (under ``min_visible_px``
  or beyond ``max_depth_m``): a real object the protocol does not score;
* **part**: at least ``part_ioa`` of the tube's mask lies inside one object (any), IoU below
  the threshold: a wheel arch, a car's side;
* **clutter**: none of these (background, vegetation, facades, and masks spilling over).

The tube's label is its most frequent frame label (ties: object, ignored, part, clutter);
``object_track`` is the track id it most often covers as an object.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from mining.eval.funnel import FunnelProtocol
from mining.eval.synthetic import GtFrame, gt_frame
from mining.masks import mask_ioa, mask_iou
from mining.types import FrameTruth, Tube

LABELS = ("object", "ignored", "part", "clutter")  # tie order
_EPS = np.finfo(float).eps


@dataclass(frozen=True)
class TubeLabel:
    label: str  # one of LABELS, or "outside" when no observed frame lies in the truth's frames
    frames: int  # observed frames compared with truth
    share: float  # share of those frames with the tube's label
    object_track: int | None  # the track it covers most often as an object
    object_known: bool | None = None  # whether that track's category is one of the 80 COCO classes


def label_tubes(tubes: Sequence[Tube], truths: Mapping[int, FrameTruth | GtFrame],
                p: FunnelProtocol = FunnelProtocol()) -> dict[int, TubeLabel]:
    """tube id → its label (see the module docstring)."""
    by_frame: dict[int, list[tuple[int, dict]]] = {}
    for t in tubes:
        for f in t.frames:
            if f.observed and f.frame in truths:
                by_frame.setdefault(f.frame, []).append((t.tube_id, f.rle))
    votes: dict[int, list[str]] = {t.tube_id: [] for t in tubes}
    tracks: dict[int, Counter] = {t.tube_id: Counter() for t in tubes}
    known: dict[int, bool] = {}
    thr, part = p.iou_threshold - _EPS, p.part_ioa - _EPS
    for frame, dets in sorted(by_frame.items()):
        gt = gt_frame(truths[frame])
        evaluated = gt.areas >= p.min_visible_px
        if p.max_depth_m is not None:
            evaluated &= gt.depth <= p.max_depth_m
        rles = [r for _, r in dets]
        iou = mask_iou(gt.rles, rles) if len(gt.rles) else np.zeros((0, len(rles)))  # (gt, tubes)
        inside = mask_ioa(rles, gt.rles) if len(gt.rles) else np.zeros((len(rles), 0))  # (tubes, gt): share of the tube in gt
        for j, (tid, _) in enumerate(dets):
            on = iou[:, j] >= thr
            if (on & evaluated).any():
                g = int(np.argmax(np.where(evaluated, iou[:, j], -1.0)))
                votes[tid].append("object")
                tracks[tid][int(gt.track_ids[g])] += 1
                known[int(gt.track_ids[g])] = bool(gt.known[g])
            elif on.any():
                votes[tid].append("ignored")
            elif inside.shape[1] and inside[j].max() >= part:
                votes[tid].append("part")
            else:
                votes[tid].append("clutter")
    out = {}
    for tid, v in votes.items():
        if not v:
            out[tid] = TubeLabel("outside", 0, float("nan"), None)
            continue
        count = Counter(v)
        label = max(LABELS, key=lambda k: (count[k], -LABELS.index(k)))
        track = tracks[tid].most_common(1)[0][0] if tracks[tid] else None
        out[tid] = TubeLabel(label, len(v), count[label] / len(v), track, None if track is None else known[track])
    return out
