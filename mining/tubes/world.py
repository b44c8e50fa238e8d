"""A frame's observations in the world (segment) frame, computed once per frame."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mining.tubes.warp import MaskPoints, mask_points
from mining.types import TrackingFrame


@dataclass
class WorldObservations:
    frame: TrackingFrame
    footpoint: np.ndarray  # (N, 3)
    covariance: np.ndarray  # (N, 3, 3)
    velocity: np.ndarray  # (N, 3), NaN rows without flow
    velocity_covariance: np.ndarray  # (N, 3, 3)
    usable: np.ndarray  # (N,) bool: has a footpoint
    boxes: np.ndarray  # (N, 4) float64
    view_edge_px: float = -1.0  # TubeConfig.view_edge_px: the masks' sides the image border cut (< 0: none)
    # World points of observation j's mask, made on first use: every tube and start
    # candidate that takes j shares them.
    _points: dict[int, MaskPoints | None] = field(default_factory=dict)

    @staticmethod
    def of(frame: TrackingFrame, view_edge_px: float = -1.0) -> WorldObservations:
        o = frame.observations
        R, t = frame.pose[:3, :3], frame.pose[:3, 3]
        foot = o.footpoint @ R.T + t
        cov = R @ o.covariance @ R.T
        vel = o.velocity @ R.T
        vcov = R @ o.velocity_covariance @ R.T
        return WorldObservations(frame, foot, cov, vel, vcov, np.isfinite(foot).all(axis=1),
                                 np.asarray(o.proposals.boxes, np.float64).reshape(-1, 4), view_edge_px)

    def __len__(self) -> int:
        return len(self.footpoint)

    def points(self, j: int) -> MaskPoints | None:
        """World points of observation j's mask (None: too few to warp)."""
        if j not in self._points:
            obs, frame = self.frame.observations, self.frame
            pts = None if obs.points is None else obs.points[j]
            grid = 1 if obs.grid is None else obs.grid[j]
            self._points[j] = mask_points(pts, grid, obs.proposals.boxes[j], obs.position[j], frame.calib, frame.pose,
                                          self.view_edge_px)
        return self._points[j]

    def velocity_or_none(self, j: int) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Observation j's velocity and its covariance, or (None, None) without flow."""
        if np.isfinite(self.velocity[j]).all():
            return self.velocity[j], self.velocity_covariance[j]
        return None, None
