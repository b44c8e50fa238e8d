"""Sparse scene flow from corner features matched around a stereo quad.

Per frame, corners are detected in the left image and matched into the right image
(:func:`stereo_features`). Between two frames, each previous stereo feature is matched
around the quad left(t−1) → right(t−1) → right(t) → left(t) → left(t−1) with pyramidal
Lucas–Kanade (sub-pixel by construction) and kept only when the cycle closes
(:func:`match_quad`), as libviso2 did in the original. Matches are triangulated in both
frames; :func:`scene_flow` removes the egomotion to leave each point's own 3D motion.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mining.geometry.config import FlowConfig
from mining.types import SceneFlow, StereoCalib


@dataclass
class StereoFeatures:
    """One frame's grey images and its left corners matched into the right image."""

    left: np.ndarray  # (H, W) uint8 grey
    right: np.ndarray
    uv_left: np.ndarray  # (N, 2) float32
    uv_right: np.ndarray  # (N, 2) float32, same rows as uv_left


@dataclass
class QuadMatches:
    """Features matched in all four images of a quad whose cycle closed."""

    uv_prev_left: np.ndarray  # (N, 2)
    uv_prev_right: np.ndarray
    uv_left: np.ndarray
    uv_right: np.ndarray

    def __len__(self) -> int:
        return len(self.uv_left)


def bucket_select(uv: np.ndarray, bucket_px: int, per_bucket: int) -> np.ndarray:
    """Indices of at most ``per_bucket`` rows per ``bucket_px`` square, earliest rows first.

    Rows are assumed ordered by preference (e.g. corner strength), so spreading the
    features over the image keeps the strongest of each cell.
    """
    if len(uv) == 0:
        return np.zeros(0, np.int64)
    cell = (uv[:, 1] // bucket_px).astype(np.int64) * 100_000 + (uv[:, 0] // bucket_px).astype(np.int64)
    order = np.argsort(cell, kind="stable")
    sorted_cell = cell[order]
    starts = np.r_[0, np.flatnonzero(np.diff(sorted_cell)) + 1]
    rank = np.arange(len(order)) - np.repeat(starts, np.diff(np.r_[starts, len(order)]))
    return np.sort(order[rank < per_bucket])


def _lk(
    src: np.ndarray, dst: np.ndarray, pts: np.ndarray, guess: np.ndarray, cfg: FlowConfig, levels: int
) -> tuple[np.ndarray, np.ndarray]:
    """Track ``pts`` from grey image ``src`` into ``dst`` starting at ``guess``; (positions, ok)."""
    if len(pts) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    # (OpenCV's Python binding takes no pre-built pyramids here, so each call builds its own.)
    out, status, _ = cv2.calcOpticalFlowPyrLK(
        src,
        dst,
        pts.reshape(-1, 1, 2).astype(np.float32),
        guess.reshape(-1, 1, 2).astype(np.float32).copy(),
        winSize=(cfg.lk_window, cfg.lk_window),
        maxLevel=levels,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, cfg.lk_iterations, 0.01),
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    return out.reshape(-1, 2), status.reshape(-1).astype(bool)


def _stereo_ok(uv_left: np.ndarray, uv_right: np.ndarray, cfg: FlowConfig) -> np.ndarray:
    """Left/right match on the same row (rectified) with a disparity inside the search range."""
    disp = uv_left[:, 0] - uv_right[:, 0]
    return (np.abs(uv_left[:, 1] - uv_right[:, 1]) <= cfg.disparity_tolerance_px) & (disp > 0) & (disp <= cfg.max_disparity_px)


def detect_corners(gray: np.ndarray, cfg: FlowConfig) -> np.ndarray:
    """FAST corners, strongest first, thinned by an NMS window and spread by bucketing."""
    keypoints = cv2.FastFeatureDetector_create(cfg.fast_threshold, True).detect(gray)
    if not keypoints:
        return np.zeros((0, 2), np.float32)
    # Strongest first (a stable sort: equal responses keep the detector's order), read out in
    # one call rather than point by point (~4,000 corners a KITTI frame).
    response = np.fromiter((k.response for k in keypoints), np.float64, len(keypoints))
    pts = cv2.KeyPoint_convert(keypoints)[np.argsort(-response, kind="stable")]
    pts = pts[bucket_select(pts, cfg.nms_window, 1)]  # strongest corner per NMS cell
    return pts[bucket_select(pts, cfg.bucket_size_px, cfg.detect_bucket_max)]


def stereo_features(
    left_gray: np.ndarray, right_gray: np.ndarray, disparity: np.ndarray, cfg: FlowConfig
) -> StereoFeatures:
    """Detect corners in the left image and match them into the right image.

    The dense disparity gives LK its starting point, so large disparities need no deep
    pyramid; corners without a valid dense disparity are dropped (occluded or ambiguous).
    """
    uv = detect_corners(left_gray, cfg)
    d0 = disparity[np.clip(np.round(uv[:, 1]).astype(int), 0, disparity.shape[0] - 1),
                   np.clip(np.round(uv[:, 0]).astype(int), 0, disparity.shape[1] - 1)]
    uv = uv[np.isfinite(d0)]
    d0 = d0[np.isfinite(d0)]
    guess = uv - np.c_[d0, np.zeros_like(d0)].astype(np.float32)
    uv_r, ok = _lk(left_gray, right_gray, uv, guess, cfg, cfg.lk_levels_stereo)
    ok &= _stereo_ok(uv, uv_r, cfg)
    return StereoFeatures(left_gray, right_gray, uv[ok], uv_r[ok])


def triangulate(uv_left: np.ndarray, uv_right: np.ndarray, calib: StereoCalib) -> np.ndarray:
    """(N, 3) camera points from rectified left/right pixel pairs."""
    disp = np.asarray(uv_left[:, 0], np.float64) - uv_right[:, 0]
    z = calib.bf / disp
    return calib.backproject(uv_left[:, 0], uv_left[:, 1], z)


def project_stereo(points: np.ndarray, calib: StereoCalib) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) camera points → left and right pixel coordinates."""
    uv_left = calib.project(points)
    uv_right = uv_left.copy()
    uv_right[:, 0] -= calib.bf / points[:, 2]
    return uv_left, uv_right


def _in_range(points: np.ndarray, cfg: FlowConfig) -> np.ndarray:
    return (points[:, 2] > 0) & (points[:, 2] <= cfg.max_depth_m) & (np.abs(points[:, 0]) <= cfg.max_lateral_m)


def match_quad(
    prev: StereoFeatures,
    cur: StereoFeatures,
    calib: StereoCalib,
    cfg: FlowConfig,
    T_guess: np.ndarray | None = None,
) -> QuadMatches:
    """Match the previous frame's stereo features around the quad; keep closed cycles.

    ``T_guess`` (e.g. the last egomotion, constant-velocity assumption) predicts where each
    feature lands, so LK starts close and fast motion near the camera still converges.
    """
    uv_pl, uv_pr = prev.uv_left, prev.uv_right
    X_prev = triangulate(uv_pl, uv_pr, calib)
    keep = _in_range(X_prev, cfg)
    uv_pl, uv_pr, X_prev = uv_pl[keep], uv_pr[keep], X_prev[keep]
    if T_guess is not None and len(X_prev):
        X_pred = X_prev @ T_guess[:3, :3].T + T_guess[:3, 3]
        front = X_pred[:, 2] > 0.5
        pred_l, pred_r = project_stereo(np.where(front[:, None], X_pred, X_prev), calib)
        pred_l, pred_r = pred_l.astype(np.float32), pred_r.astype(np.float32)
    else:
        pred_l, pred_r = uv_pl, uv_pr

    # right(t−1) → right(t) → left(t) → left(t−1): the cycle starts from the cached left↔right match.
    temporal = cfg.lk_levels if T_guess is None else cfg.lk_levels_predicted
    uv_r, ok1 = _lk(prev.right, cur.right, uv_pr, pred_r, cfg, temporal)
    uv_l, ok2 = _lk(cur.right, cur.left, uv_r, uv_r + (pred_l - pred_r), cfg, cfg.lk_levels_stereo)
    back, ok3 = _lk(cur.left, prev.left, uv_l, uv_l - (pred_l - uv_pl), cfg, temporal)
    ok = ok1 & ok2 & ok3 & _stereo_ok(uv_l, uv_r, cfg)
    ok &= np.linalg.norm(back - uv_pl, axis=1) <= cfg.outlier_tolerance_px  # the cycle closes
    ok &= np.linalg.norm(uv_l - uv_pl, axis=1) <= cfg.match_radius_px
    h, w = cur.left.shape[:2]
    ok &= (uv_l[:, 0] >= 0) & (uv_l[:, 0] <= w - 1) & (uv_l[:, 1] >= 0) & (uv_l[:, 1] <= h - 1)
    ok &= (uv_r[:, 0] >= 0) & (uv_r[:, 1] >= 0) & (uv_r[:, 1] <= h - 1)
    if ok.any():
        ok[ok] &= _in_range(triangulate(uv_l[ok], uv_r[ok], calib), cfg)
    return QuadMatches(uv_pl[ok], uv_pr[ok], uv_l[ok], uv_r[ok])


def scene_flow(
    matches: QuadMatches, calib: StereoCalib, T_cur_prev: np.ndarray | None, inlier_threshold_px: float
) -> SceneFlow:
    """Triangulate the matches in both frames and remove the egomotion.

    ``motion = X_t − T_cur_prev · X_{t−1}`` in the current camera frame; a point is an
    inlier (static) when the egomotion reprojects it within the threshold in both images.
    Without an egomotion, motion is NaN and no point is an inlier.
    """
    X_prev = triangulate(matches.uv_prev_left, matches.uv_prev_right, calib)
    X_cur = triangulate(matches.uv_left, matches.uv_right, calib)
    n = len(matches)
    if T_cur_prev is None:
        motion = np.full((n, 3), np.nan)
        inlier = np.zeros(n, bool)
    else:
        moved = X_prev @ T_cur_prev[:3, :3].T + T_cur_prev[:3, 3]
        motion = X_cur - moved
        pl, pr = project_stereo(moved, calib)
        err = np.maximum(np.linalg.norm(pl - matches.uv_left, axis=1), np.linalg.norm(pr - matches.uv_right, axis=1))
        inlier = (moved[:, 2] > 0) & (err <= inlier_threshold_px)
    return SceneFlow(
        uv_prev=matches.uv_prev_left.astype(np.float64),
        uv=matches.uv_left.astype(np.float64),
        disparity_prev=(matches.uv_prev_left[:, 0] - matches.uv_prev_right[:, 0]).astype(np.float64),
        disparity=(matches.uv_left[:, 0] - matches.uv_right[:, 0]).astype(np.float64),
        points_prev=X_prev,
        points=X_cur,
        motion=motion,
        inlier=inlier,
    )
