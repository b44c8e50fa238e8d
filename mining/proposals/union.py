"""Combine and trim per-frame proposal sets.

``union`` merges the outputs of several proposers for one frame. Two proposals of
*different* proposers whose masks overlap by more than ``iou_threshold`` are taken to be
the same object and only the one with the higher objectness stays (a proposer's own rows
are never merged with each other: its NMS is its own business). Each row keeps the name of
the proposer that made it.

Fields one proposer lacks:

* posterior — rows from a proposer without classes are NaN: "no class information". A
  tube's posterior averages only the rows that have classes (a uniform row would still
  vote, and its argmax is an arbitrary class). Putting the mass on ``UNKNOWN_CLASS`` instead
  would claim the object is *not* one of the 80 classes, which the proposer never said.
* position / size — NaN rows, the convention of ``Proposals`` for "not measured".

``filter_by_box_area_and_count`` is the image-only part of the REFERENCE proposal filter
(box area < 100 px² dropped, best 300 by score kept); the 3D parts need localisation.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mining.errors import InputError
from mining.masks import mask_iou
from mining.proposals.config import ProposalFilterConfig
from mining.types import Proposals


def union(proposals_list: Sequence[Proposals], iou_threshold: float) -> Proposals:
    """One frame's proposals from several proposers, deduplicated by mask IoU (module doc).

    Rows come out sorted by objectness, best first.
    """
    if not proposals_list:
        raise ValueError("union of no proposal sets")
    frame = proposals_list[0].frame
    sizes = set()
    for p in proposals_list:
        if p.frame != frame:
            raise InputError(f"cannot unite proposals of frame {p.frame} with frame {frame}", frame=frame)
        if len(p.proposer) != len(p):
            raise InputError(f"a proposal set names {len(p.proposer)} proposers for {len(p)} rows", frame=frame)
        sizes.update(tuple(r["size"]) for r in p.rles)
    if len(sizes) > 1:
        raise InputError(f"proposal masks of different frame sizes {sorted(sizes)}", frame=frame)

    group = np.repeat(np.arange(len(proposals_list)), [len(p) for p in proposals_list])
    merged = Proposals.cat(proposals_list)
    rles = merged.rles
    # Earlier proposers win duplicates ("onnx+stereo": the learned masks and classes stand,
    # the stereo proposer adds what the network missed); within one proposer, objectness.
    # Objectness of different proposers is not on one scale, so it cannot decide between them.
    order = np.lexsort((-merged.objectness, group))
    iou = mask_iou(rles, rles)  # one batched call over all pairs
    same = iou > iou_threshold
    same &= group[:, None] != group[None, :]
    alive = np.ones(len(rles), bool)
    keep = []
    for i in order:
        if alive[i]:
            keep.append(i)
            alive &= ~same[i]
    keep = np.asarray(keep, np.int64)
    return merged.take(keep[np.argsort(-merged.objectness[keep], kind="stable")])


def filter_by_box_area_and_count(proposals: Proposals, cfg: ProposalFilterConfig) -> Proposals:
    """Drop boxes smaller than ``min_box_area_px``, then keep the ``max_proposals`` best by objectness."""
    b = proposals.boxes.reshape(-1, 4).astype(np.float64)
    area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    big = np.flatnonzero(area >= cfg.min_box_area_px)
    order = big[np.argsort(-proposals.objectness[big], kind="stable")]
    return proposals.take(order[: cfg.max_proposals])
