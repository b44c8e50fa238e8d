"""Mask prediction by 3D warping (paper Eq. 1; REFERENCE.md "Extend").

A tube carries the 3D points of its last observed mask, in world coordinates. The
predicted mask at a later frame moves them by the tube's filtered velocity × the time
since that observation, brings them into the current camera (the pose carries the
egomotion), projects them and closes holes with a 9×9 box. Without depth
(detections-only mode) the points are the observed box's corners at the object's depth,
and the prediction is the box around their projections.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from mining.masks import box_rle, crop_rle
from mining.types import StereoCalib


@dataclass
class MaskPoints:
    """3D points of an observed mask (world frame) and how they were sampled."""

    points: np.ndarray  # (N, 3) world
    grid: int  # pixel spacing of the sample grid: each point stands for grid × grid pixels
    boxlike: bool  # True: corners of a box (no depth), predict a box
    # Sides (x1, y1, x2, y2) of the observed box that the image border cut: there the
    # points end because the view did, not the object (``view_sides``).
    open_sides: np.ndarray = field(default_factory=lambda: np.zeros(4, bool))


def view_sides(box: np.ndarray, calib: StereoCalib, edge_px: float) -> np.ndarray:
    """(4,) bool: which sides (x1, y1, x2, y2) of ``box`` lie within ``edge_px`` of the
    image border (none when ``edge_px`` < 0)."""
    if edge_px < 0:
        return np.zeros(4, bool)
    return np.array([box[0] <= edge_px, box[1] <= edge_px,
                     box[2] >= calib.width - edge_px, box[3] >= calib.height - edge_px])


def mask_points(points_cam: np.ndarray | None, grid: int, box: np.ndarray, position_cam: np.ndarray,
                calib: StereoCalib, pose: np.ndarray, view_edge_px: float = -1.0) -> MaskPoints | None:
    """World points of an observed mask from its localised 3D points (``points_cam``).

    Without points (no depth: detections-only mode) the box's corners at the object's
    depth stand for the mask. ``view_edge_px`` marks the box's sides at the image border
    (``view_sides``; < 0: none).
    """
    R, t = pose[:3, :3], pose[:3, 3]
    sides = view_sides(box, calib, view_edge_px)
    if points_cam is None:
        z = float(position_cam[2])
        if not np.isfinite(z) or z <= 0:
            return None
        u = np.array([box[0], box[2], box[2], box[0]])
        v = np.array([box[1], box[1], box[3], box[3]])
        cam = calib.backproject(u, v, np.full(4, z))
        return MaskPoints(cam @ R.T + t, 1, True, sides)
    if len(points_cam) < 3:
        return None
    return MaskPoints(points_cam.astype(np.float64) @ R.T + t, int(grid), False, sides)


def _pixels(cam: np.ndarray, calib: StereoCalib) -> tuple[np.ndarray, np.ndarray]:
    """``calib.project(cam)``'s two columns, the same arithmetic, as contiguous arrays (the warps
    reduce each column; a strided column of a stacked (N, 2) array costs more)."""
    z = cam[:, 2]
    return calib.fx * cam[:, 0] / z + calib.cx, calib.fy * cam[:, 1] / z + calib.cy


def predict_box(mp: MaskPoints, shift_world: np.ndarray, pose: np.ndarray, calib: StereoCalib,
                min_depth_m: float = 0.1) -> np.ndarray | None:
    """Box around the warped points, clipped to the image (no mask is drawn)."""
    R, t = pose[:3, :3], pose[:3, 3]
    cam = (mp.points + shift_world - t) @ R
    cam = cam[cam[:, 2] > min_depth_m]
    if len(cam) == 0:
        return None
    uv = calib.project(cam)
    pad = 0 if mp.boxlike else mp.grid / 2
    box = np.array([max(uv[:, 0].min() - pad, 0), max(uv[:, 1].min() - pad, 0),
                    min(uv[:, 0].max() + pad + 1, calib.width), min(uv[:, 1].max() + pad + 1, calib.height)])
    return box if box[2] > box[0] and box[3] > box[1] else None


def predict_boxes(mps: list[MaskPoints], shifts_world: np.ndarray, pose: np.ndarray, calib: StereoCalib,
                  min_depth_m: float = 0.1) -> np.ndarray:
    """``predict_box`` for many point sets at once: (C, 4), NaN rows where it gives None.
    All points move, project and reduce to per-set min/max in one pass."""
    out = np.full((len(mps), 4), np.nan)
    if not mps:
        return out
    R, t = pose[:3, :3], pose[:3, 3]
    seg = np.repeat(np.arange(len(mps)), [len(m.points) for m in mps])
    cam = (np.concatenate([m.points for m in mps]) + shifts_world[seg] - t) @ R
    front = cam[:, 2] > min_depth_m
    if not front.all():  # (usually all are: no copy then)
        cam, seg = cam[front], seg[front]
    if seg.size == 0:
        return out
    u, v = _pixels(cam, calib)
    starts = np.flatnonzero(np.concatenate(([True], seg[1:] != seg[:-1])))
    owner = seg[starts]
    pad = np.array([0 if m.boxlike else m.grid / 2 for m in mps])[owner]
    box = np.stack([np.maximum(np.minimum.reduceat(u, starts) - pad, 0),
                    np.maximum(np.minimum.reduceat(v, starts) - pad, 0),
                    np.minimum(np.maximum.reduceat(u, starts) + pad + 1, calib.width),
                    np.minimum(np.maximum.reduceat(v, starts) + pad + 1, calib.height)], axis=1)
    good = (box[:, 2] > box[:, 0]) & (box[:, 3] > box[:, 1])
    out[owner[good]] = box[good]
    return out


def predict_mask(mp: MaskPoints, shift_world: np.ndarray, pose: np.ndarray, calib: StereoCalib,
                 close_px: int, min_depth_m: float = 0.1) -> tuple[dict, np.ndarray] | None:
    """Predicted (RLE, box) in the camera of ``pose``; None when nothing lands in the image."""
    R, t = pose[:3, :3], pose[:3, 3]
    cam = (mp.points + shift_world - t) @ R  # world → camera: Rᵀ(p − t)
    front = cam[:, 2] > min_depth_m
    if not front.all():
        cam = cam[front]
    if len(cam) == 0:
        return None
    uf, vf = _pixels(cam, calib)
    W, H = calib.width, calib.height
    if mp.boxlike:
        box = np.array([uf.min(), vf.min(), uf.max(), vf.max()])
        clipped = np.array([max(box[0], 0), max(box[1], 0), min(box[2], W), min(box[3], H)])
        if clipped[2] <= clipped[0] or clipped[3] <= clipped[1]:
            return None
        return box_rle(clipped, H, W), clipped
    u = np.round(uf).astype(np.int64)
    v = np.round(vf).astype(np.int64)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    if not inside.all():
        if not inside.any():
            return None
        u, v = u[inside], v[inside]
    pad = close_px + mp.grid
    x0, y0 = max(0, u.min() - pad), max(0, v.min() - pad)
    x1, y1 = min(W, u.max() + pad + 1), min(H, v.max() + pad + 1)
    crop = np.zeros((y1 - y0, x1 - x0), np.uint8)
    crop[v - y0, u - x0] = 1
    if mp.grid > 1:  # each sample stands for a grid × grid patch
        crop = cv2.dilate(crop, _square(mp.grid))
    crop = cv2.morphologyEx(crop, cv2.MORPH_CLOSE, _square(close_px))
    bx, by, bw, bh = cv2.boundingRect(crop)  # of the non-zero pixels (a uint8 image, not a point set)
    if bw == 0:
        return None
    box = np.array([x0 + bx, y0 + by, x0 + bx + bw, y0 + by + bh], np.float64)
    return crop_rle(crop.astype(bool), x0, y0, H, W), box


_SQUARES: dict[int, np.ndarray] = {}


def _square(k: int) -> np.ndarray:
    """A k × k structuring element, made once per size (a mask warp runs hundreds of times a frame)."""
    if k not in _SQUARES:
        _SQUARES[k] = np.ones((k, k), np.uint8)
    return _SQUARES[k]
