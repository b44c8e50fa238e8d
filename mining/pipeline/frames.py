"""Per-frame work of the image pipeline: geometry → proposals → localise → TrackingFrame.

Poses chain the egomotion within a *segment*. A failed egomotion is never replaced: it
ends the segment, the next frame starts a new one with its own world frame, and tubes
do not cross the border. A frame whose ground plane failed uses the last good plane
moved by the egomotion (``ground_age`` counts the frames since it was measured); with
no plane at all the frame's proposals cannot be placed on the ground and are dropped.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from mining.config import JobConfig
from mining.geometry.stage import GeometryStage
from mining.localise.localise import geometric_filter, localise
from mining.proposals.make import Proposer, make_proposer
from mining.sources.base import Source
from mining.types import FrameGeometry, GroundPlane, Proposals, SequencePlan, StereoFrame, TrackingFrame


@dataclass
class FrameRecord:
    """What the pipeline knows about a frame besides its tracking input (for the catalogue)."""

    frame: StereoFrame
    geometry: FrameGeometry
    proposals: Proposals  # before the geometric filter
    ground: GroundPlane  # the plane used (measured or carried)
    ground_age: int  # 0 = measured in this frame
    tracking: TrackingFrame


def move_plane(plane: GroundPlane, T_cur_prev: np.ndarray) -> GroundPlane:
    """The plane n·X + d = 0 of the previous camera, expressed in the current camera."""
    R, t = T_cur_prev[:3, :3], T_cur_prev[:3, 3]
    n = R @ plane.normal
    return GroundPlane(n, float(plane.d - n @ t), plane.inliers, True, "carried from an earlier frame")


def tracking_frames(source: Source, plan: SequencePlan, start: int, stop: int, cfg: JobConfig,
                    proposer: Proposer | None = None) -> Iterator[FrameRecord]:
    stage: GeometryStage | None = None
    pose = np.eye(4)
    segment = 0
    ground: GroundPlane | None = None
    ground_age = 0
    prev_t = None
    for frame in source.read(plan, start, stop):
        if stage is None:
            stage = GeometryStage(frame.calib, cfg.geometry)
            proposer = proposer or make_proposer(cfg.proposals, (frame.calib.height, frame.calib.width))
        geom = stage.run(frame)
        ego = geom.egomotion
        if ego is not None:
            if ego.ok:
                pose = pose @ np.linalg.inv(ego.T_cur_prev)
            else:
                segment += 1
                pose = np.eye(4)
        if geom.ground.ok:
            ground, ground_age = geom.ground, 0
        elif ground is not None and ego is not None and ego.ok:
            ground, ground_age = move_plane(ground, ego.T_cur_prev), ground_age + 1
        else:
            ground = None
        props = proposer(frame, geom)
        dt = None if prev_t is None else (frame.t_ns - prev_t) / 1e9
        prev_t = frame.t_ns
        plane = ground or GroundPlane(None, 0.0, 0, False, geom.ground.reason)
        obs = localise(props, geom.depth, frame.calib, plane, geom.flow if ego is not None and ego.ok else None,
                       dt, frame.t_ns, cfg.localise)
        obs = obs.take(geometric_filter(obs, plane, cfg.proposals.filters))
        tf = TrackingFrame(frame.index, frame.t_ns, frame.calib, pose.copy(), segment, obs, geom.depth)
        yield FrameRecord(frame, geom, props, plane, ground_age, tf)
