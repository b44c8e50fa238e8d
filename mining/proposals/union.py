"""Combine and trim per-frame proposal sets.

``union`` merges the outputs of several proposers for one frame. Two proposals of
*different* proposers whose masks overlap by more than ``iou_threshold`` are taken to be
the same object and merge into one row: the earlier proposer's (``"onnx+stereo"``: the
learned one's objectness and posterior stand, the stereo proposer adds what the network
missed). A proposer's own rows are never merged with each other: its NMS is its own business.
Each row keeps the name of the proposer that made it.

Classes in a union with a classifier (issue 10). A class-agnostic proposal that no learned
proposal covers is evidence: the detector looked at that region and found no COCO object.
It gets the posterior "unknown" with evidence weight

    w = P(the detector finds a COCO object of this size) = 1 / (1 + exp(−(ln h − ln h50) / s)),

h the proposal's box height in pixels (``DetectabilityConfig``: fitted by ``mine bench
classify`` on labelled objects of training data), so a tiny far region the detector could
not have resolved says little and a large one says much (``mining.score.category``
accumulates the weights). A covered one takes the covering learned row's posterior.

Better mask. When a merged pair's later (class-agnostic) mask is the better one, the
merged row keeps it (with the earlier row's objectness and posterior). With no mask truth
at run time, "better" is agreement with the object's own depth: R = the pixels of either
mask whose disparity lies within the object's depth band around the median disparity of
the pixels both masks share (an object ``depth_band_m`` deep, plus ``band_noise_px`` of
disparity noise); the later mask wins when its IoU with R is higher by ``better_mask_margin``. A learned mask that bleeds
onto background, or a stereo mask that lost half the object, loses against the other.

Fields one proposer lacks: posterior — NaN rows, "no class information" (a stereo-only
union has none to give); position / size — NaN rows, the convention of ``Proposals`` for
"not measured".

``filter_by_box_area_and_count`` is the image-only part of the REFERENCE proposal filter
(box area < 100 px² dropped, best 300 by score kept); the 3D parts need localisation.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from pycocotools import mask as mask_utils

from mining.errors import InputError
from mining.masks import mask_iou
from mining.proposals.config import UnionConfig
from mining.types import UNKNOWN_CLASS, Proposals


def detectability(height_px: np.ndarray, cfg: UnionConfig) -> np.ndarray:
    """P(the learned proposer finds a COCO object of this box height), the logistic above."""
    h = np.maximum(np.asarray(height_px, np.float64), 1e-3)
    z = (np.log(h) - np.log(cfg.detect_h50_px)) / cfg.detect_log_scale
    return 1.0 / (1.0 + np.exp(-z))


def depth_agreement(a: dict, b: dict, disparity: np.ndarray, cfg: UnionConfig, bf: float) -> tuple[float, float]:
    """IoU of masks ``a`` and ``b`` with their depth-consistent region R (module docstring)."""
    ma, mb = mask_utils.decode(a).astype(bool), mask_utils.decode(b).astype(bool)
    both = ma & mb
    shared = disparity[both]
    shared = shared[np.isfinite(shared) & (shared > 0)]
    if shared.size == 0:
        return float("nan"), float("nan")
    d0 = float(np.median(shared))
    band = d0 * d0 * cfg.depth_band_m / bf + cfg.band_noise_px
    either = ma | mb
    d = np.where(either, disparity, np.nan)
    valid = np.isfinite(d) & (d > 0)  # pixels without disparity say nothing either way
    with np.errstate(invalid="ignore"):
        region = valid & (np.abs(d - d0) <= band)
    nr = region.sum()

    def iou(m):
        m = m & valid
        inter = (m & region).sum()
        return float(inter / (m.sum() + nr - inter)) if (m.sum() + nr - inter) else 0.0
    return iou(ma), iou(mb)


def baseline_focal(disparity: np.ndarray | None, depth: np.ndarray | None) -> float:
    """b·f from the geometry stage's maps (depth = b·f / disparity)."""
    if disparity is None or depth is None:
        return float("nan")
    d, z = disparity[::8, ::8], depth[::8, ::8]  # one product per valid pixel would do: a sparse grid is plenty
    ok = np.isfinite(d) & np.isfinite(z) & (d > 0)
    return float(np.median(d[ok] * z[ok])) if ok.any() else float("nan")


def union(proposals_list: Sequence[Proposals], iou_threshold: float, cfg: UnionConfig | None = None,
          disparity: np.ndarray | None = None, depth: np.ndarray | None = None) -> Proposals:
    """One frame's proposals from several proposers, deduplicated by mask IoU (module doc).

    With ``cfg``, class-agnostic rows get the classifier's evidence and, with the frame's
    ``disparity`` and ``depth`` maps too, a merged pair keeps the better mask. Rows come out
    sorted by objectness, best first.
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
    # Earlier proposers win duplicates; within one proposer, objectness. Objectness of
    # different proposers is not on one scale, so it cannot decide between them.
    order = np.lexsort((-merged.objectness, group))
    iou = mask_iou(rles, rles)  # one batched call over all pairs
    same = iou > iou_threshold
    same &= group[:, None] != group[None, :]
    alive = np.ones(len(rles), bool)
    keep, partner = [], []
    for i in order:
        if alive[i]:
            keep.append(i)
            dup = np.flatnonzero(alive & same[i])
            # the best-overlapping later row is the candidate for a better mask
            partner.append(int(dup[np.argmax(iou[i, dup])]) if dup.size else -1)
            alive &= ~same[i]
    keep_a = np.asarray(keep, np.int64)
    out = merged.take(keep_a)
    if cfg is not None:
        out = _classify_agnostic(out, proposals_list, group[keep_a], cfg)
        if cfg.better_mask and disparity is not None:
            _keep_better_masks(out, merged, keep_a, np.asarray(partner, np.int64), disparity, depth, cfg)
    return out.take(np.argsort(-out.objectness, kind="stable"))


def _classify_agnostic(p: Proposals, parts: Sequence[Proposals], group: np.ndarray, cfg: UnionConfig) -> Proposals:
    """Rows of class-agnostic proposers, uncovered by a classifier: "unknown", weighted by detectability."""
    classifying = np.array([q.posterior is not None for q in parts])
    if not classifying.any() or classifying.all() or p.posterior is None:
        return p
    agnostic = ~classifying[group]
    post = p.posterior.copy()
    weight = p.class_weights()
    post[agnostic] = 0.0
    post[agnostic, UNKNOWN_CLASS] = 1.0
    h = p.boxes[agnostic, 3] - p.boxes[agnostic, 1]
    weight[agnostic] = detectability(h, cfg)
    p.posterior, p.class_weight = post.astype(np.float32), weight.astype(np.float32)
    return p


def _keep_better_masks(out: Proposals, merged: Proposals, keep: np.ndarray, partner: np.ndarray,
                       disparity: np.ndarray, depth: np.ndarray | None, cfg: UnionConfig) -> None:
    bf = baseline_focal(disparity, depth)
    if not np.isfinite(bf):
        return
    for row, (i, j) in enumerate(zip(keep, partner)):
        if j < 0:
            continue
        a, b = depth_agreement(merged.rles[i], merged.rles[j], disparity, cfg, bf)
        if b > a + cfg.better_mask_margin:
            out.rles[row] = merged.rles[j]
            out.boxes[row] = merged.boxes[j]


def filter_by_box_area_and_count(proposals: Proposals, min_box_area_px: float, max_proposals: int) -> Proposals:
    """Drop boxes smaller than ``min_box_area_px``, then keep the ``max_proposals`` best by objectness
    (the caller gives the values: the filter's settings are ``[localise.filters]``, a later stage's)."""
    b = proposals.boxes.reshape(-1, 4).astype(np.float64)
    area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    big = np.flatnonzero(area >= min_box_area_px)
    order = big[np.argsort(-proposals.objectness[big], kind="stable")]
    return proposals.take(order[:max_proposals])
