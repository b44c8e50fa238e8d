"""Gating and association score of predictions against observations (REFERENCE.md "Extend").

Gates: box IoU and 2D size similarity of the predicted and observed boxes
(``mining.boxes.box_gates``), mask IoU (box IoU for box-only predictions) and the
footpoint's Mahalanobis distance on the ground plane. Score: mask IoU × Gaussian density
of the footpoint. Everything works on arrays of (prediction, observation) pairs, so many
tubes are gated in one pass.
"""

from __future__ import annotations

import numpy as np

GROUND = [0, 2]  # x and z: the footpoint's coordinates on the ground plane (y is the plane's height)


def _inv_quad_2x2(d: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """dᵀ c⁻¹ d and det(c) for (N, 2) vectors and (N, 2, 2) matrices, in closed form."""
    a, b, cc, e = c[:, 0, 0], c[:, 0, 1], c[:, 1, 0], c[:, 1, 1]
    det = a * e - b * cc
    m2 = (e * d[:, 0] ** 2 - (b + cc) * d[:, 0] * d[:, 1] + a * d[:, 1] ** 2) / det
    return m2, det


def gaussian_density(x: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """N(x; mean, cov) on the ground plane, for (N, 3) points and (N, 3, 3) covariances.

    The motion LLR's null hypothesis spreads clutter uniformly over the ground area
    (paper: 1/A_GP with A_GP ≈ 80 m × 50 m), so the density is per square metre of ground.
    """
    m2, det = _inv_quad_2x2((x - mean)[:, GROUND], cov[:, GROUND][:, :, GROUND])
    return np.exp(-0.5 * m2) / (2 * np.pi * np.sqrt(det))


def mahalanobis2(x: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distance on the ground plane."""
    return _inv_quad_2x2((x - mean)[:, GROUND], cov[:, GROUND][:, :, GROUND])[0]


def best_pairs(rows: np.ndarray, cols: np.ndarray, iou: np.ndarray, mean: np.ndarray, pos_cov: np.ndarray,
               foot: np.ndarray, cov: np.ndarray, cfg) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each prediction's best gated observation among (row, col) pairs.

    ``rows``/``cols`` index predictions and observations (rows ascending, cols ascending
    within a row); ``iou`` is the pair's mask (or box) IoU; ``mean`` and ``pos_cov`` are the
    pair's predicted footpoint (K, 3) and its covariance (K, 3, 3); ``foot`` and ``cov``
    the observed footpoint and covariance. ``cfg`` is a ``TubeConfig``. Returns the rows
    that take an observation, their observation, mask IoU and density. Ties go to the
    lower observation index, as ``np.argmax`` would.
    """
    ok = (iou > cfg.gate_mask_iou) & (mahalanobis2(foot, mean, pos_cov + cov) < cfg.gate_mahalanobis**2)
    rows, cols, iou, mean, foot, cov = (a[ok] for a in (rows, cols, iou, mean, foot, cov))
    dens = gaussian_density(foot, mean, cov + cfg.density_extra_var * np.eye(3))
    score = iou * dens
    order = np.lexsort((-score, rows))  # stable: equal scores keep the column order
    ro = rows[order]
    first = order[np.concatenate(([True], ro[1:] != ro[:-1]))] if order.size else order
    first = first[score[first] > cfg.min_association]
    nan = np.isnan(score)
    if nan.any():  # np.argmax would pick a NaN score, which then fails the threshold: such rows take nothing
        first = first[~np.isin(rows[first], rows[nan])]
    return rows[first], cols[first], iou[first], dens[first]
