"""Tubes → score → select → known/unknown over a run of tracking frames."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from mining.config import JobConfig
from mining.score.unary import TubeScore, score_tube
from mining.select.coselect import co_select
from mining.tubes.category import TubeCategory, tube_category
from mining.tubes.generate import TubeGenerator
from mining.tubes.tube import Tube
from mining.types import TrackingFrame


@dataclass
class MinedTube:
    tube: Tube
    score: TubeScore
    category: TubeCategory
    selected: bool


def mine_tubes(frames: Iterable[TrackingFrame], cfg: JobConfig, first_id: int = 0) -> list[MinedTube]:
    """Generate, score and co-select tubes over frames given in time order."""
    gen = TubeGenerator(cfg.tubes, cfg.score, first_id=first_id)
    for frame in frames:
        gen.step(frame)
    tubes = gen.finish()
    scores = [score_tube(t, cfg.score) for t in tubes]
    selected = co_select(tubes, np.array([s.total for s in scores]), cfg.select)
    return [MinedTube(t, s, tube_category(t, cfg.score.known_threshold), bool(m))
            for t, s, m in zip(tubes, scores, selected)]
