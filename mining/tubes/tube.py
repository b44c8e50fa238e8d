"""A video object tube: the frames it spans, what was observed and what was predicted."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mining.tubes.kalman import TubeFilter
from mining.tubes.warp import MaskPoints


@dataclass
class TubeFrame:
    """One frame of a tube: an observation (inlier) or the tube's prediction in a gap."""

    frame: int
    t_ns: int
    observed: bool
    obs_index: int  # row in that frame's Observations; −1 when predicted
    rle: dict  # observed mask, or the predicted mask in a gap
    box: np.ndarray  # (4,) x1, y1, x2, y2
    footpoint_world: np.ndarray  # (3,) filtered footpoint, world (segment) frame
    velocity_world: np.ndarray  # (3,) filtered velocity on the ground plane, m/s
    size: np.ndarray  # (3,) filtered width, height, length
    position_cam: np.ndarray  # (3,) observed 3D position in this frame's camera (predicted in a gap)
    objectness: float  # the proposal's score; NaN when predicted
    mask_iou: float  # IoU(predicted mask, observed mask); NaN for a tube's first inlier and in gaps
    motion_density: float  # Gaussian density of the observed footpoint under the prediction; NaN likewise
    posterior: np.ndarray | None = None  # the observation's 81-way class posterior


@dataclass
class Tube:
    tube_id: int
    segment: int
    frames: list[TubeFrame] = field(default_factory=list)
    # Tracking state, used while the tube is live.
    kf: TubeFilter | None = None
    points: MaskPoints | None = None  # 3D points of the last observed mask (world)
    last_observed_t_ns: int = 0
    gap: int = 0  # frames since the last observation
    end_reason: str = ""

    @property
    def n_inliers(self) -> int:
        return sum(1 for f in self.frames if f.observed)

    @property
    def first_frame(self) -> int:
        return self.frames[0].frame

    @property
    def last_frame(self) -> int:
        return self.frames[-1].frame

    def frame_map(self) -> dict[int, TubeFrame]:
        return {f.frame: f for f in self.frames}

    def inlier_key(self) -> tuple[tuple[int, int], ...]:
        """(frame, observation) of every inlier: two tubes with the same key explain the same data."""
        return tuple((f.frame, f.obs_index) for f in self.frames if f.observed)

    def trim(self) -> None:
        """Drop trailing predicted frames: a tube ends at its last observation."""
        while self.frames and not self.frames[-1].observed:
            self.frames.pop()
