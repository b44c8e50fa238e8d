"""One window's work, as pure functions of the source, the window and the job config.

A window runs in two steps so that its context frames are computed once, by the
window that owns them as core frames:

1. **observe** (geometry → proposals → localise) over the window's *core* frames. The
   geometry stage carries state across two frames (the previous frame's features and
   the last motion, which predicts the next matches), so the step first replays the
   ``WARMUP_FRAMES`` frames before the core; a frame's observations are then the same
   whatever window computes them.
2. **track** (tubes → score → select) over the *context*, from the observations of its
   own core and its neighbours' cores. Poses are chained from the frames' egomotions,
   starting at the context's first frame; a failed egomotion, a missing neighbour or a
   recording gap starts a new pose segment, and tubes never cross one.

Neither step knows about Ray: the executors in ``mining/pipeline/executors.py`` call them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mining.config import JobConfig
from mining.errors import InputError
from mining.geometry.poses import chain_poses
from mining.pipeline.frames import frame_records
from mining.pipeline.mine import mine_tubes
from mining.pipeline.proposal_stage import ModelStage
from mining.proposals.make import Proposer
from mining.sources.base import Source
from mining.types import MinedTube, Observations, SequencePlan, StereoCalib, TrackingFrame, Window

WARMUP_FRAMES = 2  # ours: GeometryStage state spans two frames (features of t−1, motion of t−1 predicting t)


@dataclass
class ObservedFrame:
    """What the observe step keeps of a frame: enough to track and to fill the frames table."""

    position: int  # position in the sequence plan
    index: int  # the source's frame index
    t_ns: int
    calib: StereoCalib
    T_cur_prev: np.ndarray | None  # (4, 4) egomotion from the previous frame; None when failed or absent
    egomotion_ok: bool | None  # None: no previous frame (sequence start, after a recording gap)
    egomotion_inliers: int
    egomotion_rmse_px: float
    ground_ok: bool
    ground_age: int | None  # frames since the plane used was measured; None: no plane
    n_proposals: int
    observations: Observations


def observe_window(source: Source, plan: SequencePlan, window: Window, cfg: JobConfig,
                   proposer: Proposer | None = None,
                   on_frame: Callable[[int], None] | None = None,
                   models: ModelStage | None = None) -> list[ObservedFrame]:
    """Geometry, proposals and localisation for the window's core frames; ``on_frame(k)``
    after each (k core frames done), for progress. ``models``: a proposal stage running the
    proposer's model parts (``proposer`` is then one without them)."""
    s, e = window.core
    start = max(0, s - WARMUP_FRAMES)
    try:
        return _observe(source, plan, start, s, e, cfg, proposer, on_frame, models)
    except InputError as err:
        if err.frame is None or start == s or err.frame not in plan.frames[start:s]:
            raise
    # A bad warm-up frame belongs to the window before, which fails on it; this window
    # starts without a previous frame (its first egomotion is absent, a new pose segment).
    return _observe(source, plan, s, s, e, cfg, proposer, on_frame, models)


def _observe(source: Source, plan: SequencePlan, start: int, s: int, e: int, cfg: JobConfig,
             proposer: Proposer | None, on_frame: Callable[[int], None] | None = None,
             models: ModelStage | None = None) -> list[ObservedFrame]:
    out = []
    for rec in frame_records(source, plan, start, e, cfg, proposer, models):
        if rec.position >= s:
            ego = rec.geometry.egomotion
            obs = rec.tracking.observations
            out.append(ObservedFrame(
                position=rec.position, index=rec.frame.index, t_ns=rec.frame.t_ns, calib=rec.frame.calib,
                T_cur_prev=rec.egomotion_T,
                egomotion_ok=None if ego is None else bool(ego.ok),
                egomotion_inliers=0 if ego is None else int(ego.inliers),
                egomotion_rmse_px=float("nan") if ego is None else float(ego.rmse_px),
                ground_ok=bool(rec.geometry.ground.ok),
                ground_age=rec.ground_age if rec.ground.ok else None,
                n_proposals=len(rec.proposals),
                observations=obs,
            ))
            if on_frame is not None:
                on_frame(len(out))
    return out


def track_window(frames: list[ObservedFrame],
                 cfg: JobConfig) -> tuple[list[MinedTube], list[tuple[np.ndarray, int]]]:
    """Tubes, scores and co-selection over a window's context frames (in plan order); no
    linking of fragments, which the stitcher does over the whole sequence. Also the
    camera-to-world pose and segment of each frame it chained (``chain_poses``), for the
    catalogue's rows: nothing chains them a second time."""
    poses = chain_poses([f.position for f in frames], [f.T_cur_prev for f in frames])
    tracking = (TrackingFrame(f.index, f.t_ns, f.calib, pose, segment, f.observations, None)
                for f, (pose, segment) in zip(frames, poses))
    return mine_tubes(tracking, cfg, link=False), poses  # fragments are linked over the stitched sequence
