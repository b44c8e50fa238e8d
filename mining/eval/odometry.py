"""Odometry drift in the style of the KITTI odometry benchmark, for short sequences.

KITTI measures drift over path segments of 100–800 m. Our real test sequences are a few
to a few hundred metres long, so segments are counted in frames instead: every start
frame i and every span of ``min_frames`` or more frames. For each segment the relative
pose error E = inv(ΔT_true) · ΔT_est gives

* translation error in % = |t(E)| / path length × 100,
* rotation error in deg/m = angle(R(E)) / path length.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class OdometryErrors:
    translation_pct: float  # mean over segments
    rotation_deg_per_m: float  # mean over segments
    segments: int  # segments evaluated
    skipped: int  # segments skipped because an estimated pose is missing (NaN)


def path_lengths(poses: np.ndarray) -> np.ndarray:
    """Cumulative distance travelled along camera-to-world poses, metres."""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def rotation_angle(R: np.ndarray) -> float:
    """Angle of a rotation matrix, radians."""
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def odometry_errors(estimate: np.ndarray, truth: np.ndarray, min_frames: int = 5, min_path_m: float = 1.0) -> OdometryErrors:
    """Drift of ``estimate`` against ``truth`` (both (N, 4, 4) camera-to-world)."""
    if estimate.shape != truth.shape:
        raise ValueError(f"pose arrays differ in shape: {estimate.shape} vs {truth.shape}")
    dist = path_lengths(truth)
    t_err, r_err, skipped = [], [], 0
    n = len(truth)
    for i in range(n):
        for j in range(i + min_frames, n):
            length = dist[j] - dist[i]
            if length < min_path_m:  # a standing car has no drift per metre to speak of
                continue
            if not (np.isfinite(estimate[i]).all() and np.isfinite(estimate[j]).all()):
                skipped += 1
                continue
            d_true = np.linalg.inv(truth[i]) @ truth[j]
            d_est = np.linalg.inv(estimate[i]) @ estimate[j]
            E = np.linalg.inv(d_true) @ d_est
            t_err.append(np.linalg.norm(E[:3, 3]) / length * 100.0)
            r_err.append(np.degrees(rotation_angle(E[:3, :3])) / length)
    if not t_err:
        return OdometryErrors(float("nan"), float("nan"), 0, skipped)
    return OdometryErrors(float(np.mean(t_err)), float(np.mean(r_err)), len(t_err), skipped)
