"""Co-selection of tubes: the pairwise overlap term and the QUBO over a batch of tubes.

The pairwise term of two tubes is the sum, over the frames both span, of their masks'
IoU; a frame counts only when their boxes' IoU exceeds ``box_iou_gate`` (REFERENCE.md).
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from mining.masks import box_iou, mask_iou
from mining.select.config import SelectConfig
from mining.select.qubo import build_qubo, solve
from mining.tubes.tube import Tube


def pairwise_overlap(tubes: list[Tube], box_iou_gate: float) -> np.ndarray:
    """(N, N) symmetric Σ_t mask IoU over common frames, zero diagonal."""
    n = len(tubes)
    overlap = np.zeros((n, n))
    by_frame: dict[int, list[tuple[int, object]]] = defaultdict(list)
    for i, tube in enumerate(tubes):
        for f in tube.frames:
            by_frame[f.frame].append((i, f))
    for entries in by_frame.values():
        if len(entries) < 2:
            continue
        idx = np.array([i for i, _ in entries])
        boxes = np.array([f.box for _, f in entries])
        gate = box_iou(boxes, boxes) > box_iou_gate
        np.fill_diagonal(gate, False)
        rows = np.flatnonzero(gate.any(axis=1))
        if rows.size == 0:
            continue
        ious = mask_iou([entries[r][1].rle for r in rows], [entries[r][1].rle for r in rows])
        sub = gate[np.ix_(rows, rows)]
        a, b = np.nonzero(sub)
        np.add.at(overlap, (idx[rows[a]], idx[rows[b]]), ious[a, b])
    np.fill_diagonal(overlap, 0.0)
    return overlap


def co_select(tubes: list[Tube], scores: np.ndarray, cfg: SelectConfig) -> np.ndarray:
    """Boolean selection of the tubes that maximise mᵀQm."""
    if not tubes:
        return np.zeros(0, bool)
    overlap = pairwise_overlap(tubes, cfg.box_iou_gate)
    Q = build_qubo(np.asarray(scores, np.float64), overlap, cfg)
    m, _ = solve(Q, cfg)
    return np.asarray(m, bool)
