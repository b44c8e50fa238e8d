"""Box algebra on x1, y1, x2, y2 pixel boxes: IoU, intersection over area, 2D size similarity,
class-agnostic NMS.

One plain implementation of each, used by every stage and metric. ``box_gates`` is the
tube gate's fused pass (IoU and size similarity of all prediction × observation pairs
without the IoU division); ``tests/test_boxes.py`` holds it equal to the plain functions
on real boxes.
"""

from __future__ import annotations

import cv2
import numpy as np


def _overlap(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intersection area and the two box areas of ``a[..., :4]`` and ``b[..., :4]``, broadcast."""
    # np.maximum(x, 0) is np.clip(x, 0, None) without clip's Python-level dispatch.
    iw = np.maximum(np.minimum(a[..., 2], b[..., 2]) - np.maximum(a[..., 0], b[..., 0]), 0)
    ih = np.maximum(np.minimum(a[..., 3], b[..., 3]) - np.maximum(a[..., 1], b[..., 1]), 0)
    inter = iw * ih
    area_a = (a[..., 2] - a[..., 0]) * (a[..., 3] - a[..., 1])
    area_b = (b[..., 2] - b[..., 0]) * (b[..., 3] - b[..., 1])
    return inter, area_a, area_b


def paired_box_iou(a: np.ndarray, b: np.ndarray, min_area: float | None = None) -> np.ndarray:
    """IoU of the boxes ``a[..., :4]`` and ``b[..., :4]`` element by element (broadcast):
    the pairs of a gate's mask without the full matrix.

    0 where the union is empty. With ``min_area`` (TrackEval's rule, its float epsilon), a
    box of area ≤ ``min_area`` overlaps nothing, and neither does a union that small.
    """
    inter, area_a, area_b = _overlap(a, b)
    union = area_a + area_b - inter
    if min_area is None:
        valid = union > 0
    else:
        valid = (area_a > min_area) & (area_b > min_area) & (union > min_area)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(valid, inter / union, 0.0)


def box_iou(a: np.ndarray, b: np.ndarray, min_area: float | None = None) -> np.ndarray:
    """(len(a), len(b)) IoU of x1, y1, x2, y2 boxes (``min_area`` as in :func:`paired_box_iou`)."""
    a = np.asarray(a, np.float64).reshape(-1, 4)
    b = np.asarray(b, np.float64).reshape(-1, 4)
    return paired_box_iou(a[:, None], b[None, :], min_area)


def box_ioa(a: np.ndarray, b: np.ndarray, min_area: float = 0.0) -> np.ndarray:
    """(len(a), len(b)) intersection over the area of each box of ``a`` (rows); 0 for rows
    of area ≤ ``min_area``."""
    a = np.asarray(a, np.float64).reshape(-1, 4)
    b = np.asarray(b, np.float64).reshape(-1, 4)
    inter, area_a, _ = _overlap(a[:, None], b[None, :])
    return np.divide(inter, area_a, out=np.zeros_like(inter), where=area_a > min_area)


def size_similarity(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(len(a), len(b)) 2D size similarity of boxes: product of width and height ratios (≤ 1)."""
    a = np.asarray(a, np.float64).reshape(-1, 4)
    b = np.asarray(b, np.float64).reshape(-1, 4)
    wa, ha = a[:, 2] - a[:, 0], a[:, 3] - a[:, 1]
    wb, hb = b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        rw = np.minimum(wa[:, None], wb[None]) / np.maximum(wa[:, None], wb[None])
        rh = np.minimum(ha[:, None], hb[None]) / np.maximum(ha[:, None], hb[None])
    return np.nan_to_num(rw * rh)


def _gate_terms(pred: np.ndarray, obs: np.ndarray) -> tuple[np.ndarray, ...]:
    """Widths and heights of ``pred`` and ``obs``, and their (T, N) intersection and union
    areas: what both box gates compare (one copy, so the two gates cannot drift apart)."""
    pw, ph = pred[:, 2] - pred[:, 0], pred[:, 3] - pred[:, 1]
    ow, oh = obs[:, 2] - obs[:, 0], obs[:, 3] - obs[:, 1]
    iw = np.minimum(pred[:, None, 2], obs[None, :, 2]) - np.maximum(pred[:, None, 0], obs[None, :, 0])
    ih = np.minimum(pred[:, None, 3], obs[None, :, 3]) - np.maximum(pred[:, None, 1], obs[None, :, 1])
    inter = np.maximum(iw, 0) * np.maximum(ih, 0)
    union = (pw * ph)[:, None] + (ow * oh)[None, :] - inter
    return pw, ph, ow, oh, inter, union


def _size_ratios(pw: np.ndarray, ph: np.ndarray, ow: np.ndarray, oh: np.ndarray) -> np.ndarray:
    """(T, N) width ratio × height ratio of the gates' size similarity (NaN for two empty
    sizes, which no threshold passes)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return (np.minimum(pw[:, None], ow[None]) / np.maximum(pw[:, None], ow[None])
                * np.minimum(ph[:, None], oh[None]) / np.maximum(ph[:, None], oh[None]))


def box_gates(pred: np.ndarray, obs: np.ndarray, min_iou: float, min_similarity: float) -> np.ndarray:
    """(T, N) bool: box IoU > min_iou and 2D size similarity > min_similarity, in one pass.

    The same test as ``(box_iou(pred, obs) > min_iou) & (size_similarity(pred, obs) >
    min_similarity)`` but faster: IoU is compared as ``inter > min_iou · union`` without
    the division, and the ratios multiply in another order, so a pair within rounding of
    a threshold may fall on the other side.
    """
    pw, ph, ow, oh, inter, union = _gate_terms(pred, obs)
    with np.errstate(divide="ignore", invalid="ignore"):
        ok = inter > min_iou * union
    return ok & (_size_ratios(pw, ph, ow, oh) > min_similarity)


def cut_at_sides(obs: np.ndarray, pred: np.ndarray, sides: np.ndarray) -> np.ndarray:
    """Boxes ``obs`` (N, 4) cut at the sides of one box ``pred`` (4,) marked in ``sides``
    (4,) bool, x1, y1, x2, y2: the part of each that lies on ``pred``'s side of them. A
    box that lies beyond such a side becomes empty (x2 ≤ x1 or y2 ≤ y1)."""
    out = np.array(obs, np.float64).reshape(-1, 4)
    lo, hi = sides[:2], sides[2:]
    out[:, :2][:, lo] = np.maximum(out[:, :2][:, lo], pred[:2][lo])
    out[:, 2:][:, hi] = np.minimum(out[:, 2:][:, hi], pred[2:][hi])
    return out


def shifted_iou(w: np.ndarray, h: np.ndarray, delta: float) -> np.ndarray:
    """IoU of a ``w`` × ``h`` box with itself shifted by ``delta`` pixels in x and in y:
    (w−δ)(h−δ) / (2wh − (w−δ)(h−δ)), in [0, 1].

    How much of an IoU gate ``delta`` pixels of jitter use up: a 20 px box loses a third
    of its IoU to a 2 px shift (0.68), a 200 px box 4 % (0.96). 1 at δ = 0, also for an
    empty box (no jitter, no relaxation).
    """
    w, h = np.asarray(w, np.float64), np.asarray(h, np.float64)
    inter = np.maximum(w - delta, 0) * np.maximum(h - delta, 0)
    union = 2 * w * h - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        j = np.where(union > 0, inter / union, 1.0 if delta <= 0 else 0.0)
    return np.clip(j, 0.0, 1.0)


def jittered_box_gates(pred: np.ndarray, obs: np.ndarray, min_iou: float, min_similarity: float,
                       jitter_px: float) -> np.ndarray:
    """(T, N) bool: ``box_gates`` tolerant of ``jitter_px`` pixels of box jitter.

    Prediction i's IoU gate is ``min_iou × shifted_iou(w_i, h_i, jitter_px)`` (its own box's
    IoU with itself shifted by the jitter: the IoU a perfect match jittered that much
    keeps), and the 2D size similarity compares the sizes with ``jitter_px`` added to both
    widths and both heights (a few pixels of a small box's size are boundary noise). With
    ``jitter_px`` = 0 this is ``box_gates`` itself.
    """
    if jitter_px <= 0:
        return box_gates(pred, obs, min_iou, min_similarity)
    pw, ph, ow, oh, inter, union = _gate_terms(pred, obs)
    gate = min_iou * shifted_iou(pw, ph, jitter_px)
    # A box of width or height ≤ 0 never gates, as in box_gates (the added jitter would make its size look fine).
    real = ((pw > 0) & (ph > 0))[:, None] & ((ow > 0) & (oh > 0))[None, :]
    sim = _size_ratios(pw + jitter_px, ph + jitter_px, ow + jitter_px, oh + jitter_px)
    return real & (inter > gate[:, None] * union) & (sim > min_similarity)


def nms_keep(boxes: np.ndarray, scores: np.ndarray, iou: float, top_k: int) -> np.ndarray:
    """Class-agnostic NMS (OpenCV); indices of kept boxes, best score first."""
    if len(boxes) == 0:
        return np.zeros(0, np.int64)
    xywh = np.column_stack([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]]).astype(np.float64)
    keep = cv2.dnn.NMSBoxes(xywh, scores.astype(np.float32), 0.0, iou, top_k=top_k)
    return np.asarray(keep, np.int64).reshape(-1)
