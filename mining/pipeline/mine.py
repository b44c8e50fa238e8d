"""Tubes → judge: generate tubes over tracking frames, then score, classify and co-select them.

``judge`` is the one step after tube generation (score → category → co-selection); a
window judges its own tubes and the stitcher judges a sequence's stitched tubes with it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np

from mining.config import JobConfig
from mining.score.call import call_tubes
from mining.score.unary import score_tube, unary_total, unary_version, unary_weights
from mining.select.coselect import co_select
from mining.tubes.generate import TubeGenerator
from mining.tubes.link import link_fragments
from mining.types import MinedTube, TrackingFrame, Tube, TubeScore


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
    weights = unary_weights(cfg.score, proposer or cfg.proposals.proposer)
    version = unary_version(cfg.score, weights)
    scores = [score_tube(t, cfg.score, weights, version) for t in tubes]
    cats, offered = call_tubes(tubes, cfg.score, proposer or cfg.proposals.proposer)
    selected = np.zeros(len(tubes), bool)
    idx = np.flatnonzero(offered)
    if len(idx):
        # a tube called unknown pays select.unknown_price on top of ε1 (the stored score stays the unary's)
        unary_minus = np.array([scores[i].total - (cfg.select.unknown_price if cats[i].call == "unknown" else 0.0)
                                for i in idx])
        selected[idx] = co_select([tubes[i] for i in idx], unary_minus, cfg.select,
                                  "reference" if weights is None else "calibrated")
    return [MinedTube(t, s, c, bool(m)) for t, s, c, m in zip(tubes, scores, cats, selected)]


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
