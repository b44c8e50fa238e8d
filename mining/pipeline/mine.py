"""Tubes → judge: generate tubes over tracking frames, then score, classify and co-select them.

``judge`` is the one step after tube generation (score → category → co-selection); a
window judges its own tubes and the stitcher judges a sequence's stitched tubes with it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from mining.config import JobConfig
from mining.score.call import call_tubes
from mining.score.unary import score_tube, unary_total, unary_version, unary_weights
from mining.select.coselect import co_select
from mining.tubes.generate import TubeGenerator
from mining.tubes.link import link_fragments
from mining.types import MinedTube, TrackingFrame, Tube, TubeCategory, TubeScore


def unary(cfg: JobConfig, proposer: str | None = None) -> Callable[[Tube], TubeScore]:
    """The job's unary score: REFERENCE, or calibrated for its proposer (``score.model``).

    ``proposer`` names the evidence when it is not ``cfg.proposals.proposer``'s (detections-only
    mode: ``mining.pipeline.detections.DETECTIONS``, which has no calibrated weights).
    """
    weights = unary_weights(cfg.score, proposer or cfg.proposals.proposer)
    version = unary_version(cfg.score, weights)
    return lambda tube: score_tube(tube, cfg.score, weights, version)


def judge(tubes: list[Tube], cfg: JobConfig, proposer: str | None = None) -> list[MinedTube]:
    """Each tube's unary score and call (``mining.score.call``: known, unknown, unclassified, or
    clutter not offered), and the co-selection over the tubes offered, at the price and overlap
    weight of the unary that scored them (``select.price`` and ``select.overlap_weight``)."""
    each = judge_each(tubes, cfg, proposer)
    selected = np.zeros(len(tubes), bool)
    idx = np.flatnonzero(each.offered)
    if len(idx):
        selected[idx] = co_select([tubes[i] for i in idx], each.cost[idx], cfg.select, each.model)
    return [MinedTube(t, s, c, bool(m)) for t, s, c, m in zip(tubes, each.scores, each.calls, selected)]


@dataclass
class Judged:
    """What ``judge`` finds of each tube alone, before co-selection weighs them together."""

    scores: list[TubeScore]
    calls: list[TubeCategory]
    offered: np.ndarray  # bool per tube: offered to co-selection
    cost: np.ndarray  # the unary co-selection weighs (select.unknown_price taken off an unknown tube's)
    model: str  # the unary's kind, as co_select names it


def judge_each(tubes: list[Tube], cfg: JobConfig, proposer: str | None = None) -> Judged:
    """``judge`` up to co-selection: every value here is one tube's own (the stitch judges a
    sequence's tubes group by group with it, and co-selects them all at the end)."""
    weights = unary_weights(cfg.score, proposer or cfg.proposals.proposer)
    version = unary_version(cfg.score, weights)
    scores = [score_tube(t, cfg.score, weights, version) for t in tubes]
    cats, offered = call_tubes(tubes, cfg.score, proposer or cfg.proposals.proposer)
    # a tube called unknown pays select.unknown_price on top of ε1 (the stored score stays the unary's)
    cost = np.array([s.total - (cfg.select.unknown_price if c.call == "unknown" else 0.0) for s, c in zip(scores, cats)],
                    np.float64)
    return Judged(scores, cats, offered, cost, "reference" if weights is None else "calibrated")


def tube_generator(cfg: JobConfig, first_id: int = 0, proposer: str | None = None) -> TubeGenerator:
    """The job's tube generator, ranking tubes for tube NMS by their unary score."""
    weights = unary_weights(cfg.score, proposer or cfg.proposals.proposer)
    return TubeGenerator(cfg.tubes, lambda tube: unary_total(tube, cfg.score, weights), first_id=first_id)


def mine_tubes(frames: Iterable[TrackingFrame], cfg: JobConfig, first_id: int = 0,
               proposer: str | None = None, link: bool = True) -> list[MinedTube]:
    """Generate tubes over frames given in time order, link fragments (``link``: off for a
    window, whose tubes the stitcher links), then judge them (``proposer``: see ``unary``)."""
    gen = tube_generator(cfg, first_id, proposer)
    for frame in frames:
        gen.step(frame)
    tubes = gen.finish()
    return judge(with_links(tubes, cfg) if link else tubes, cfg, proposer)


def with_links(tubes: list[Tube], cfg: JobConfig) -> list[Tube]:
    """The tubes and, after them, the joined tube of every chain of fragments of one object
    (``mining.tubes.link``; none with ``tubes.link_fragments`` off). Ids continue after the
    largest given; a sequence's whole set of tubes, never a window's."""
    first_id = max((t.tube_id for t in tubes), default=-1) + 1
    return tubes + [joined for joined, _ in link_fragments(tubes, cfg.tubes, first_id)]
