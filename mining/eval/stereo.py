"""Stereo disparity error metrics: KITTI D1 and Middlebury bad-N."""

from __future__ import annotations

import numpy as np


def d1_all(estimate: np.ndarray, truth: np.ndarray) -> float:
    """KITTI 2015 D1: share of ground-truth pixels whose error exceeds 3 px and 5 %.

    Pixels without an estimate (NaN) count as errors, as in the KITTI benchmark, which
    fills them by background interpolation; we do not interpolate, so this is stricter.
    """
    gt = np.isfinite(truth) & (truth > 0)
    err = np.abs(np.nan_to_num(estimate, nan=-1e9)[gt] - truth[gt])
    bad = (err > 3.0) & (err > 0.05 * truth[gt])
    return float(bad.mean()) if gt.any() else float("nan")


def bad_n(estimate: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None, threshold: float = 2.0) -> float:
    """Middlebury bad-N: share of evaluated pixels with |error| > N px; missing estimates count as bad."""
    sel = np.isfinite(truth)
    if mask is not None:
        sel &= mask
    err = np.abs(np.nan_to_num(estimate, nan=-1e9)[sel] - truth[sel])
    return float((err > threshold).mean()) if sel.any() else float("nan")


def density(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Share of ground-truth pixels that have an estimate."""
    gt = np.isfinite(truth) & (truth > 0)
    return float(np.isfinite(estimate[gt]).mean()) if gt.any() else float("nan")
