"""Join fragments of one object into one tube before selection (issue 18, scope 2).

Tube generation gives an object several tubes when its proposals change under it: the ONNX
model's mask in some frames, the stereo proposer's in others, a tube that ends when its
gate misses while another, started from the other proposal a few frames before, carries
on. Each such fragment covers part of the object's frames; co-selection then picks one
per stretch of time, so a track is cut into short selected tubes (on synthetic truth, of
the candidate tubes on one object one after another, about three in four overlap the one
before in time; one in four starts after a gap).

Two tubes are **fragments of one object** when one continues the other in time and, in
at least ``link_agree_share`` of the frames both observed (and at least ``link_min_common``
of them), their masks agree: mask IoU > ``link_mask_iou`` (REFERENCE's association gate:
the same test a tube's own next mask must pass). Not every common frame: two proposals of
one object (a detector's mask and a stereo segment) disagree in a frame where one of them
spills over or is cut. The earlier tube (A) hands over to the later (B) at the
last frame both observed: the joined tube is A up to that frame and B after it, so every
frame keeps the evidence one tube's own filter gave it. Links are one-to-one (each tube
has at most one successor and one predecessor: the candidate with the most frames in
common, then the higher mean IoU), and chains of links are joined into one tube.

The joined tube is **added** as a candidate beside its fragments: co-selection's overlap
term then keeps either the joined tube or fragments of it, by their scores, so a wrong
join costs a candidate, not an object.

Linking runs on a sequence's whole set of tubes (``mine_tubes``, and the stitcher after
windows are stitched), never inside a window, so it does not depend on where window
borders fall.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mining.boxes import paired_box_iou
from mining.masks import mask_iou
from mining.tubes.config import TubeConfig
from mining.types import Tube


@dataclass(frozen=True)
class Link:
    """A continues into b (indices into the tube list), handing over after frame ``handover``."""

    a: int
    b: int
    handover: int
    common: int  # frames both observed
    mean_iou: float


def candidate_links(tubes: Sequence[Tube], cfg: TubeConfig) -> list[Link]:
    """Every pair of tubes where the later continues the earlier and their masks agree in
    enough of the frames both observed (see the module docstring)."""
    observed = [{f.frame: f for f in t.frames if f.observed} for t in tubes]
    spans = np.array([(t.first_frame, t.last_inlier.frame) for t in tubes], np.int64).reshape(-1, 2)
    links = []
    order = np.argsort(spans[:, 0], kind="stable")
    for ia, a in enumerate(order):
        a_first, a_last = spans[a]
        for b in order[ia + 1:]:
            b_first, b_last = spans[b]
            if b_first > a_last:
                break  # sorted by first frame: no later tube overlaps a
            if b_first <= a_first or b_last <= a_last or tubes[a].segment != tubes[b].segment:
                continue  # b must start after a and continue past a's end
            common = sorted(set(observed[a]) & set(observed[b]))
            if len(common) < cfg.link_min_common:
                continue
            boxes_a = np.array([observed[a][f].box for f in common])
            boxes_b = np.array([observed[b][f].box for f in common])
            if (paired_box_iou(boxes_a, boxes_b) <= 0).any():
                continue  # disjoint boxes in a common frame: masks cannot agree there
            ious = mask_iou([observed[a][f].rle for f in common], [observed[b][f].rle for f in common]).diagonal()
            if np.mean(ious > cfg.link_mask_iou) < cfg.link_agree_share:
                continue
            links.append(Link(int(a), int(b), common[-1], len(common), float(ious.mean())))
    return links


def one_to_one(links: list[Link]) -> list[Link]:
    """Each tube keeps at most one successor and one predecessor: the links with the most
    frames in common first (then the higher mean IoU, then the earlier pair)."""
    chosen, has_next, has_prev = [], set(), set()
    for link in sorted(links, key=lambda k: (-k.common, -k.mean_iou, k.a, k.b)):
        if link.a in has_next or link.b in has_prev:
            continue
        chosen.append(link)
        has_next.add(link.a)
        has_prev.add(link.b)
    return chosen


def join_chain(tubes: Sequence[Tube], chain: list[Link]) -> Tube:
    """One tube from a chain of links a₀→a₁→…: each tube up to its handover, the last one whole."""
    frames = []
    after = -np.inf
    for link in chain:
        frames += [f for f in tubes[link.a].frames if after < f.frame <= link.handover]
        after = link.handover
    last = tubes[chain[-1].b]
    frames += [f for f in last.frames if f.frame > after]
    return Tube(tube_id=-1, segment=last.segment, frames=frames, end_reason=last.end_reason)


def link_fragments(tubes: Sequence[Tube], cfg: TubeConfig, first_id: int) -> list[tuple[Tube, list[int]]]:
    """The joined tube of every chain of fragments (ids from ``first_id``) with the indices
    of its fragments; the fragments themselves stay candidates (the caller keeps them)."""
    if not cfg.link_fragments or len(tubes) < 2:
        return []
    nxt = {k.a: k for k in one_to_one(candidate_links(tubes, cfg))}
    starts = set(nxt) - {k.b for k in nxt.values()}
    out = []
    for a in sorted(starts, key=lambda i: (tubes[i].first_frame, i)):
        chain = [nxt[a]]
        while chain[-1].b in nxt:
            chain.append(nxt[chain[-1].b])
        joined = join_chain(tubes, chain)
        joined.tube_id = first_id + len(out)
        out.append((joined, [chain[0].a] + [k.b for k in chain]))
    return out
