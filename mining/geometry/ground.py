"""Ground plane by RANSAC on the stereo point cloud, then least-squares refinement.

Candidates are points more than ``min_below_camera_m`` below the camera (y down) and
within ``max_lateral_m`` sideways; on KITTI the road lies ≈1.65 m below the camera, so
the 1.0 m cut keeps the road and drops most of what stands on it. The plane must be
within ``max_tilt_deg`` of horizontal (normal near the camera y axis).
"""

from __future__ import annotations

import numpy as np

from mining.geometry.config import GroundConfig
from mining.types import GroundPlane, StereoCalib


def ground_candidates(disparity: np.ndarray, calib: StereoCalib, cfg: GroundConfig) -> np.ndarray:
    """(N, 3) camera points from a subsampled disparity image that may lie on the ground."""
    step = cfg.pixel_step
    sub = disparity[::step, ::step]
    v, u = np.nonzero(np.isfinite(sub))
    d = sub[v, u].astype(np.float64)
    z = calib.bf / d
    X = calib.backproject(u * step, v * step, z)
    keep = (X[:, 1] > cfg.min_below_camera_m) & (np.abs(X[:, 0]) < cfg.max_lateral_m) & (z <= cfg.max_depth_m)
    return X[keep]


def _plane_up(normal: np.ndarray, d: float) -> tuple[np.ndarray, float]:
    """Orient the plane so that its normal points up (−y in camera coordinates)."""
    return (-normal, -d) if normal[1] > 0 else (normal, d)


def fit_ground_plane(points: np.ndarray, cfg: GroundConfig) -> GroundPlane:
    """RANSAC plane through candidate ground points; ok=False with a reason on failure."""
    n = len(points)
    if n < cfg.min_points:
        return GroundPlane(None, float("nan"), 0, False, f"too few ground candidates: {n} < {cfg.min_points}")
    rng = np.random.default_rng(cfg.seed)
    if n > cfg.max_points:
        points = points[rng.choice(n, cfg.max_points, replace=False)]
    # Score hypotheses on a fixed random subset (the full set only for the refinement).
    score_pts = points[rng.choice(len(points), min(len(points), cfg.score_points), replace=False)]
    cos_tilt = np.cos(np.radians(cfg.max_tilt_deg))

    best_count, best = -1, None
    done, needed = 0, cfg.iterations
    while done < needed:
        k = min(cfg.batch, needed - done)
        tri = points[rng.integers(0, len(points), size=(k, 3))]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(normal, axis=1)
        good = norm > 1e-9
        normal[good] /= norm[good, None]
        good &= np.abs(normal[:, 1]) >= cos_tilt  # roughly perpendicular to the camera y axis
        d = -np.einsum("ki,ki->k", normal, tri[:, 0])
        counts = (np.abs(score_pts @ normal.T + d) <= cfg.inlier_distance_m).sum(axis=0)
        counts[~good] = -1
        i = int(np.argmax(counts))
        if counts[i] > best_count:
            best_count, best = int(counts[i]), (normal[i], d[i])
            # Adaptive stopping (ours): enough iterations for the confidence at this inlier ratio.
            ratio = max(best_count / len(score_pts), 1e-6)
            needed = min(cfg.iterations, int(np.ceil(np.log(1 - cfg.confidence) / np.log(1 - ratio**3))) if ratio < 1 else 1)
        done += k
    if best is None or best_count < 3:
        return GroundPlane(None, float("nan"), 0, False, "no plane within the tilt limit")

    normal, d = best
    for _ in range(2):  # least-squares refinement over the inliers (total least squares via SVD)
        inl = np.abs(points @ normal + d) <= cfg.inlier_distance_m
        if inl.sum() < 3:
            return GroundPlane(None, float("nan"), int(inl.sum()), False, "refinement lost the inliers")
        c = points[inl].mean(axis=0)
        normal = np.linalg.svd(points[inl] - c, full_matrices=False)[2][2]
        d = -float(normal @ c)
    normal, d = _plane_up(normal, d)
    inliers = int((np.abs(points @ normal + d) <= cfg.inlier_distance_m).sum())
    if -normal[1] < cos_tilt:
        return GroundPlane(None, float("nan"), inliers, False, "refined plane tilted beyond the limit")
    return GroundPlane(normal, float(d), inliers, True)


def estimate_ground(disparity: np.ndarray, calib: StereoCalib, cfg: GroundConfig) -> GroundPlane:
    """Ground plane of one frame from its disparity image."""
    return fit_ground_plane(ground_candidates(disparity, calib, cfg), cfg)
