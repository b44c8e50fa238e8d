"""``mine eval recall --funnel``: the recall funnel (``mining/eval/funnel.py``) on KITTI labels.

KITTI tracking labels are boxes, not masks, so the funnel compares boxes (box IoU ≥ 0.5;
a proposal's or a tube frame's box is its mask's) and a label's depth is the z of its 3D
location. The driver runs the pipeline over the frames, keeps each frame's proposals (the
recall@N of ``mine eval recall`` reads them too), before and after the geometric filter,
mines tubes from the tracking frames and hands everything to ``evaluate_funnel``.
"""

from __future__ import annotations

from collections.abc import Iterator

from mining.config import JobConfig
from mining.eval.funnel import StageFrame, evaluate_funnel, stage_frame
from mining.eval.recall import kitti_truths
from mining.formats.kitti_tracking import KittiTrackingRows
from mining.pipeline.frames import frame_records
from mining.pipeline.mine import mine_tubes
from mining.progress import Ticker
from mining.score.unary import unary_groups
from mining.sources.base import Source
from mining.types import MinedTube, Proposals, SequencePlan, TrackingFrame


def run_kitti_funnel(source: Source, plan: SequencePlan, start: int, stop: int, cfg: JobConfig,
                     rows: KittiTrackingRows, **protocol) -> tuple[list[Proposals], list[int], list[MinedTube], dict]:
    """Mine plan positions [start, stop) and measure the funnel against the labels ``rows``.

    ``protocol`` takes ``evaluate_funnel``'s keyword arguments (``similarity`` is "box").
    Returns each frame's proposals (before the geometric filter) and index, the mined tubes
    (candidates included) and the funnel.
    """
    props: list[Proposals] = []
    frames: list[int] = []
    stages: dict[str, dict[int, StageFrame]] = {"proposed": {}, "observed": {}}
    ticker = Ticker(f"{plan.dataset} {plan.sequence}", stop - start)

    def tracking() -> Iterator[TrackingFrame]:
        for k, rec in enumerate(frame_records(source, plan, start, stop, cfg)):
            ticker.tick(k)
            props.append(rec.proposals)
            frames.append(rec.frame.index)
            stages["proposed"][rec.frame.index] = stage_frame(rec.proposals)
            stages["observed"][rec.frame.index] = stage_frame(rec.tracking.observations.proposals)
            yield rec.tracking

    mined = mine_tubes(tracking(), cfg)
    ticker.close()
    truths = kitti_truths(rows, frames, (plan.calib.height, plan.calib.width))
    funnel = evaluate_funnel(truths, mined, stages, alpha=cfg.score.alpha, beta=cfg.score.beta,
                             groups=unary_groups(cfg.score, cfg.proposals.proposer), **({"similarity": "box"} | protocol))
    return props, frames, mined, funnel
