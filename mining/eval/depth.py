"""Depth error against sparse ground truth (e.g. projected LiDAR): abs-rel, δ<1.25, coverage."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class DepthErrors:
    abs_rel: float  # mean |z − z*| / z* over points with an estimate
    delta_125: float  # share of points with max(z/z*, z*/z) < 1.25
    valid: float  # share of ground-truth points that have an estimate
    n_points: int  # ground-truth points evaluated


def depth_errors(estimate: np.ndarray, truth: np.ndarray, max_depth_m: float | None = None) -> DepthErrors:
    """Compare a dense depth map (NaN = none) with sparse truth (NaN = no point)."""
    gt = np.isfinite(truth) & (truth > 0)
    if max_depth_m is not None:
        gt &= truth <= max_depth_m
    z_true = truth[gt]
    z_est = estimate[gt]
    has = np.isfinite(z_est) & (z_est > 0)
    if not has.any():
        return DepthErrors(float("nan"), float("nan"), 0.0, int(gt.sum()))
    zt, ze = z_true[has], z_est[has]
    ratio = np.maximum(ze / zt, zt / ze)
    return DepthErrors(
        abs_rel=float(np.mean(np.abs(ze - zt) / zt)),
        delta_125=float(np.mean(ratio < 1.25)),
        valid=float(has.mean()),
        n_points=int(gt.sum()),
    )
