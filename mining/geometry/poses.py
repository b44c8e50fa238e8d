"""Camera poses from egomotions, and the ground plane carried from one camera to the next.

An egomotion ``T_cur_prev`` (4×4) maps points of the previous camera into the current one;
a pose is camera-to-world, so ``pose_cur = pose_prev · T_cur_prev⁻¹``. Two policies for a
frame with no egomotion to trust (failed, absent after a recording gap, or the frame before
it missing):

* ``PoseChain`` / ``chain_poses`` — the pipeline's: the frame starts a new *pose segment*
  whose world is its own camera; tubes never cross a segment border.
* ``chain_egomotion`` — KITTI odometry's single world: that pose and every later one are
  NaN, nothing links them to the first frame (evaluation and inspection).

``move_plane`` expresses a plane of the previous camera in the current one (a frame whose
own ground fit failed uses the last good plane, moved).

Pure arithmetic on numpy arrays: the frame loop, the window's track step, the stitcher
and the geometry inspection all chain here, so a pose means the same everywhere.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mining.types import GroundPlane


class PoseChain:
    """Camera-to-world poses chained from egomotions, one world frame per pose segment.

    ``step(T_cur_prev)`` takes each frame's egomotion from the frame before it, or None
    when there is none to trust (failed, absent after a gap, or the frame before is
    missing): the frame then starts a new segment whose world is its own camera. The
    first frame's egomotion is not used: its world is its camera.
    """

    def __init__(self) -> None:
        self.pose = np.eye(4)
        self.segment = 0
        self._first = True

    def step(self, T_cur_prev: np.ndarray | None) -> tuple[np.ndarray, int]:
        if self._first:
            self._first = False
        elif T_cur_prev is not None:
            self.pose = self.pose @ np.linalg.inv(T_cur_prev)  # pose_cur = pose_prev · T_cur_prev⁻¹
        else:
            self.pose, self.segment = np.eye(4), self.segment + 1
        return self.pose.copy(), self.segment


def chain_poses(positions: Sequence[int], motions: Sequence[np.ndarray | None]) -> list[tuple[np.ndarray, int]]:
    """Camera-to-world pose and segment of each frame, chained from the first frame.

    ``motions[i]`` is frame i's egomotion T_cur_prev (None when failed or absent). A frame
    without one, or not the plan successor of the frame before it (``positions``: plan
    positions; a missing window), starts a new segment with its own world frame.
    """
    poses = PoseChain()
    return [poses.step(T if i == 0 or positions[i] == positions[i - 1] + 1 else None)
            for i, T in enumerate(motions)]


def chain_egomotion(transforms: list[np.ndarray | None]) -> np.ndarray:
    """Camera-to-world poses from per-frame egomotions ``T_cur_prev`` (first entry ignored).

    A failed egomotion (None) breaks the chain: that pose and every later one are NaN,
    because nothing links them to the first frame. They are never guessed.
    """
    poses = np.full((len(transforms), 4, 4), np.nan)
    if not transforms:
        return poses
    poses[0] = np.eye(4)
    for k in range(1, len(transforms)):
        T = transforms[k]
        if T is None or not np.isfinite(poses[k - 1]).all():
            continue
        poses[k] = poses[k - 1] @ np.linalg.inv(T)
    return poses


def move_plane(plane: GroundPlane, T_cur_prev: np.ndarray) -> GroundPlane:
    """The plane n·X + d = 0 of the previous camera, expressed in the current camera."""
    R, t = T_cur_prev[:3, :3], T_cur_prev[:3, 3]
    n = R @ plane.normal
    return GroundPlane(n, float(plane.d - n @ t), plane.inliers, True, "carried from an earlier frame")
