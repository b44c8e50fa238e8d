"""The per-frame driver of the image pipeline: geometry → proposals → localise → TrackingFrame.

Every per-frame loop of the project runs through ``FrameLoop`` (``mine track``, the
windows' observe step, the benchmarks and the tests), so the rules below hold everywhere:

* **Pose segments.** Poses chain the egomotion within a *segment* (``PoseChain``,
  ``mining/geometry/poses.py``). A frame without a trusted egomotion from the frame before
  it starts a new segment with its own world frame, and tubes never cross the border. That is a failed egomotion
  (never replaced by the identity) and a frame that does not follow the one before it:
  a recording gap (``SequencePlan.gaps``: a RobotCar chunk not downloaded, a dropped MCAP
  frame) or a missing window.
* **Geometry state.** Both breaks drop what links a frame to the ones before it: the
  motion prior that guides matching (``GeometryStage``), the carried ground plane, and
  flow (velocities need a trusted egomotion). A recording gap resets the geometry stage
  altogether (``GeometryStage.reset``): no features are matched and no egomotion is
  estimated across it. After a failed egomotion the previous frame's features stay: the
  next frame is matched to them afresh, with no prior.
* **Ground.** A frame whose ground plane failed uses the last good plane moved by the
  egomotion (``move_plane``; ``ground_age`` counts the frames since it was measured); with no plane at
  all the frame's proposals cannot be placed on the ground and are dropped.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from mining.config import JobConfig
from mining.geometry.config import GeometryConfig
from mining.geometry.poses import PoseChain, move_plane
from mining.geometry.stage import GeometryStage
from mining.localise.localise import geometric_filter, localise
from mining.pipeline.proposal_stage import ModelStage, ahead
from mining.proposals.make import FrameProposer, Proposer, make_proposer
from mining.sources.base import Source
from mining.types import (FrameGeometry, GroundPlane, Observations, Proposals, SequencePlan, StereoFrame,
                          TrackingFrame)


@dataclass
class FrameRecord:
    """What the pipeline knows about a frame besides its tracking input (for the catalogue)."""

    frame: StereoFrame
    position: int | None  # position in the sequence plan (None when the caller fed frames itself)
    geometry: FrameGeometry
    proposals: Proposals  # before the geometric filter
    localised: Observations  # every proposal localised, before the geometric filter
    ground: GroundPlane  # the plane used (measured or carried)
    ground_age: int  # 0 = measured in this frame
    tracking: TrackingFrame  # the observations that passed the geometric filter, with the pose

    @property
    def egomotion_T(self) -> np.ndarray | None:
        """The frame's trusted egomotion T_cur_prev, None when it failed or is absent."""
        ego = self.geometry.egomotion
        return ego.T_cur_prev if ego is not None and ego.ok else None


class FrameLoop:
    """One frame at a time, in time order: geometry → proposals → localise → TrackingFrame.

    ``step(frame)`` computes what it is not given: pass ``geometry`` (e.g. computed once
    for a benchmark) or ``proposals`` (e.g. a fixed set) to reuse them. Call
    ``recording_gap()`` before the first frame after a hole in the recording.
    """

    def __init__(self, cfg: JobConfig, proposer: Proposer | None = None):
        self.cfg = cfg
        self.proposer = proposer
        self.stage: GeometryStage | None = None
        self.poses = PoseChain()
        self._ground: GroundPlane | None = None
        self._ground_age = 0
        self._prev_t: int | None = None
        self._after_gap = False

    def recording_gap(self) -> None:
        """The next frame does not follow the last one: start a new segment, forget the geometry state."""
        if self.stage is not None:
            self.stage.reset()
        self._ground, self._ground_age, self._prev_t = None, 0, None
        self._after_gap = True

    def geometry(self, frame: StereoFrame) -> FrameGeometry:
        """The geometry stage on ``frame`` (its state carries to the next frame)."""
        if self.stage is None:
            self.stage = GeometryStage(frame.calib, self.cfg.geometry)
        return self.stage.run(frame)

    def step(self, frame: StereoFrame, geometry: FrameGeometry | None = None, proposals: Proposals | None = None,
             position: int | None = None, models: list[Proposals] | None = None) -> FrameRecord:
        """``models``: the proposer's model parts of this frame, run elsewhere (a proposal stage);
        the loop's proposer adds its frame parts (``FrameProposer.finish``)."""
        cfg = self.cfg
        geom = geometry if geometry is not None else self.geometry(frame)
        ego = geom.egomotion
        T = ego.T_cur_prev if ego is not None and ego.ok and not self._after_gap else None
        self._after_gap = False
        pose, segment = self.poses.step(T)
        if geom.ground.ok:
            self._ground, self._ground_age = geom.ground, 0
        elif self._ground is not None and T is not None:
            self._ground, self._ground_age = move_plane(self._ground, T), self._ground_age + 1
        else:
            self._ground = None
        if proposals is None:
            if self.proposer is None:
                size = (frame.calib.height, frame.calib.width)
                self.proposer = (make_proposer(cfg.proposals, size) if models is None
                                 else FrameProposer(cfg.proposals, size, models=False))
            proposals = self.proposer(frame, geom) if models is None else self.proposer.finish(frame, geom, models)
        dt = None if self._prev_t is None else (frame.t_ns - self._prev_t) / 1e9
        self._prev_t = frame.t_ns
        plane = self._ground or GroundPlane(None, 0.0, 0, False, geom.ground.reason)
        # Scene flow relates this frame to the one before only through a trusted egomotion.
        localised = localise(proposals, geom.depth, frame.calib, plane, geom.flow if T is not None else None,
                             dt, frame.t_ns, cfg.localise)
        obs = localised.take(geometric_filter(localised, plane, cfg.localise.filters))
        tracking = TrackingFrame(frame.index, frame.t_ns, frame.calib, pose, segment, obs, geom.depth)
        return FrameRecord(frame, position, geom, proposals, localised, plane, self._ground_age, tracking)


def plan_frames(source: Source, plan: SequencePlan, start: int, stop: int) -> Iterator[tuple[int, StereoFrame, bool]]:
    """(position, frame, after_gap) at plan positions [start, stop): ``after_gap`` is True for
    the first frame after a recording gap (never for the first frame read)."""
    gaps = set(plan.gaps)
    for position, frame in enumerate(source.read(plan, start, stop), start=max(0, start)):
        yield position, frame, position in gaps and position > start


def plan_geometry(source: Source, plan: SequencePlan, start: int, stop: int,
                  cfg: GeometryConfig) -> Iterator[tuple[int, StereoFrame, FrameGeometry, bool]]:
    """(position, frame, geometry, after_gap) over plan positions [start, stop): the geometry
    stage alone, reset at every recording gap (nothing is matched across one)."""
    stage: GeometryStage | None = None
    for position, frame, after_gap in plan_frames(source, plan, start, stop):
        if stage is None:
            stage = GeometryStage(frame.calib, cfg)
        if after_gap:
            stage.reset()
        yield position, frame, stage.run(frame), after_gap


def frame_records(source: Source, plan: SequencePlan, start: int, stop: int, cfg: JobConfig,
                  proposer: Proposer | None = None, stage: ModelStage | None = None) -> Iterator[FrameRecord]:
    """``FrameLoop`` over plan positions [start, stop), honouring the plan's recording gaps;
    with a ``stage`` the proposer's model parts run there, in batches sent ahead
    (``run.proposal_batch``, ``run.proposal_queue``), and ``proposer`` must be one without them."""
    loop = FrameLoop(cfg, proposer)
    if stage is None:
        for position, frame, after_gap in plan_frames(source, plan, start, stop):
            if after_gap:
                loop.recording_gap()
            yield loop.step(frame, position=position)
        return
    for position, frame, after_gap, models in ahead(plan_frames(source, plan, start, stop), stage,
                                                   cfg.run.proposal_batch, cfg.run.proposal_queue):
        if after_gap:
            loop.recording_gap()
        yield loop.step(frame, position=position, models=models)
