"""Gating and association score of predictions against observations (REFERENCE.md "Extend").

Gates: box IoU and 2D size similarity of the predicted and observed boxes
(``mining.boxes.jittered_box_gates``), mask IoU (box IoU for box-only predictions) and the
footpoint's Mahalanobis distance on the ground plane. Score (``TubeConfig.association``):

* "reference": mask IoU × Gaussian density of the footpoint, > ``association_floor.reference``.
  The density's peak falls with the stereo covariance (∝ depth² along the ray), so the same
  match, equally many σ off, scores ~7× lower at 50 m than at 10 m and a far object's
  tube breaks apart.
* "normalised": mask IoU × exp(−½·m²), the density relative to its peak (a likelihood
  ratio against the perfect match), > ``association_floor.normalised``: the same at every
  depth for the same distance in σ.

With ``gate_jitter_px`` = δ > 0 the IoU gates are relaxed to gate × the IoU a perfect
match of the predicted box keeps when shifted δ px in x and y (``mining.boxes.shifted_iou``):
a few pixels of jitter are a third of a 20 px object's IoU and nothing of a 200 px one's.

A prediction from a mask the image border cut (``MaskPoints.open_sides``) sees observations
only up to the predicted box's sides there (``view_edge_gates``): beyond them the object may
go on where the earlier view could not see it.

The density itself (the motion term of the tube's score) is the same in both modes.
Everything works on arrays of (prediction, observation) pairs, so many tubes are gated in
one pass; the forward association and the backward probe share ``best_pairs``.
"""

from __future__ import annotations

import numpy as np

from mining.boxes import cut_at_sides, jittered_box_gates, shifted_iou
from mining.tubes.config import TubeConfig

GROUND = [0, 2]  # x and z: the footpoint's coordinates on the ground plane (y is the plane's height)


def _inv_quad_2x2(d: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """dᵀ c⁻¹ d and det(c) for (N, 2) vectors and (N, 2, 2) matrices, in closed form."""
    a, b, cc, e = c[:, 0, 0], c[:, 0, 1], c[:, 1, 0], c[:, 1, 1]
    det = a * e - b * cc
    m2 = (e * d[:, 0] ** 2 - (b + cc) * d[:, 0] * d[:, 1] + a * d[:, 1] ** 2) / det
    return m2, det


def mahalanobis2(x: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distance on the ground plane."""
    return _inv_quad_2x2((x - mean)[:, GROUND], cov[:, GROUND][:, :, GROUND])[0]


def association_scores(iou: np.ndarray, foot: np.ndarray, mean: np.ndarray, cov: np.ndarray,
                       cfg: TubeConfig, pos_cov: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Each pair's association score (``cfg.association``'s rule) and its Gaussian density.

    The density is N(foot; mean, cov + density_extra_var·I) on the ground plane (the
    score's motion term in every mode); the "normalised" score replaces it by
    exp(−½·m²) = density / its peak, with m the Mahalanobis distance under the same
    covariance; "innovation" takes m under the Kalman innovation covariance
    S = P_pred + R_obs + density_extra_var·I (``pos_cov`` is P_pred), the covariance the
    Mahalanobis gate uses, so a young tube's own uncertainty counts too. One closed-form
    pass gives the density (the reference's arithmetic unchanged). It is per square metre
    of ground: the motion LLR's null hypothesis spreads clutter uniformly over the ground
    area (paper: 1/A_GP with A_GP ≈ 80 m × 50 m).
    """
    dcov = cov + cfg.density_extra_var * np.eye(3)
    m2, det = _inv_quad_2x2((foot - mean)[:, GROUND], dcov[:, GROUND][:, :, GROUND])
    relative = np.exp(-0.5 * m2)
    dens = relative / (2 * np.pi * np.sqrt(det))
    if cfg.association == "reference":
        return iou * dens, dens
    if cfg.association == "innovation":
        if pos_cov is None:
            raise ValueError("association='innovation' needs the prediction's covariance")
        relative = np.exp(-0.5 * mahalanobis2(foot, mean, pos_cov + dcov))
    return iou * relative, dens


def association_floor(cfg: TubeConfig) -> float:
    """The score a pair must exceed under ``cfg.association``'s rule (its entry of ``cfg.association_floor``)."""
    return getattr(cfg.association_floor, cfg.association)


def iou_gate(pred_box: np.ndarray, cfg: TubeConfig, gate: float) -> np.ndarray | float:
    """An IoU gate for each predicted box (K, 4): ``gate`` × ``shifted_iou`` of the box
    with ``cfg.gate_jitter_px``; ``gate`` itself without jitter tolerance."""
    if cfg.gate_jitter_px <= 0:
        return gate
    return gate * shifted_iou(pred_box[:, 2] - pred_box[:, 0], pred_box[:, 3] - pred_box[:, 1], cfg.gate_jitter_px)


def best_pairs(rows: np.ndarray, cols: np.ndarray, iou: np.ndarray, mean: np.ndarray, pos_cov: np.ndarray,
               foot: np.ndarray, cov: np.ndarray, cfg: TubeConfig, *,
               pred_box: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each prediction's best gated observation among (row, col) pairs.

    ``rows``/``cols`` index predictions and observations (rows ascending, cols ascending
    within a row); ``iou`` is the pair's mask (or box) IoU; ``mean`` and ``pos_cov`` are the
    pair's predicted footpoint (K, 3) and its covariance (K, 3, 3); ``foot`` and ``cov``
    the observed footpoint and covariance; ``pred_box`` the pair's predicted box (K, 4),
    whose size sets the jitter-tolerant IoU gate. ``cfg`` is a ``TubeConfig``. Returns the
    rows that take an observation, their observation, mask IoU and density. The highest
    score wins; ties go to the lower observation index, as ``np.argmax`` would.
    """
    ok = ((iou > iou_gate(pred_box, cfg, cfg.gate_mask_iou))
          & (mahalanobis2(foot, mean, pos_cov + cov) < cfg.gate_mahalanobis**2))
    rows, cols, iou, mean, foot, cov, pos_cov = (a[ok] for a in (rows, cols, iou, mean, foot, cov, pos_cov))
    score, dens = association_scores(iou, foot, mean, cov, cfg, pos_cov)
    order = np.lexsort((-score, rows))  # stable: equal scores keep the column order
    ro = rows[order]
    first = order[np.concatenate(([True], ro[1:] != ro[:-1]))] if order.size else order
    first = first[score[first] > association_floor(cfg)]
    nan = np.isnan(score)
    if nan.any():  # np.argmax would pick a NaN score, which then fails the threshold: such rows take nothing
        first = first[~np.isin(rows[first], rows[nan])]
    return rows[first], cols[first], iou[first], dens[first]


def view_edge_gates(pred_box: np.ndarray, obs_box: np.ndarray, open_sides: list[np.ndarray | None],
                    cfg: TubeConfig) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """The (T, N) box gates (``jittered_box_gates``) of predicted boxes (T, 4) against observed
    boxes (N, 4), where prediction i with ``open_sides[i]`` (4,) bool set compares the
    observations cut at those sides of its box. Also returns those rows' cut boxes, row → (N, 4)."""
    gate = jittered_box_gates(pred_box, obs_box, cfg.gate_box_iou, cfg.gate_size_similarity, cfg.gate_jitter_px)
    cut = {i: cut_at_sides(obs_box, pred_box[i], s) for i, s in enumerate(open_sides) if s is not None and s.any()}
    for i, boxes in cut.items():
        gate[i] = jittered_box_gates(pred_box[i:i + 1], boxes, cfg.gate_box_iou, cfg.gate_size_similarity,
                                     cfg.gate_jitter_px)[0]
    return gate, cut


def paired_obs_boxes(obs_box: np.ndarray, rows: np.ndarray, cols: np.ndarray, cut: dict[int, np.ndarray]) -> np.ndarray:
    """The observed box of each (row, col) pair (K, 4), cut where ``view_edge_gates`` cut row's."""
    out = obs_box[cols].copy()
    for i, boxes in cut.items():
        out[rows == i] = boxes[cols[rows == i]]
    return out
