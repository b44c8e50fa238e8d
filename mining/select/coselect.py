"""Co-selection of tubes: the pairwise overlap term and the QUBO over a batch of tubes.

The pairwise term of two tubes is the sum, over the frames both span, of their masks'
IoU; a frame counts only when their boxes' IoU exceeds ``box_iou_gate`` (REFERENCE.md).
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix

from mining.boxes import box_iou
from mining.masks import mask_iou
from mining.select.config import SelectConfig
from mining.select.qubo import build_qubo, connected_groups, solve
from mining.types import Tube


DENSE_MAX = 400  # ours: up to this many tubes one dense N × N QUBO is cheaper than splitting it first


def overlap_pairs(tubes: list[Tube], box_iou_gate: float) -> csr_matrix:
    """Sparse symmetric (N, N) Σ_t mask IoU over common frames, zero diagonal.

    Sparse because tubes overlap only near in time: a sequence of thousands of tubes has
    few overlapping pairs, and a dense N × N matrix would not fit.
    """
    n = len(tubes)
    by_frame: dict[int, list[tuple[int, object]]] = defaultdict(list)
    for i, tube in enumerate(tubes):
        for f in tube.frames:
            by_frame[f.frame].append((i, f))
    rows_, cols_, vals_ = [], [], []
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
        rows_.append(idx[rows[a]])
        cols_.append(idx[rows[b]])
        vals_.append(ious[a, b])
    if not rows_:
        return csr_matrix((n, n))
    m = coo_matrix((np.concatenate(vals_), (np.concatenate(rows_), np.concatenate(cols_))), shape=(n, n)).tocsr()
    m.sum_duplicates()
    m.setdiag(0.0)
    m.eliminate_zeros()
    return m


def pairwise_overlap(tubes: list[Tube], box_iou_gate: float) -> np.ndarray:
    """(N, N) dense symmetric Σ_t mask IoU over common frames, zero diagonal."""
    return overlap_pairs(tubes, box_iou_gate).toarray()


def co_select(tubes: list[Tube], scores: np.ndarray, cfg: SelectConfig) -> np.ndarray:
    """Boolean selection of the tubes that maximise mᵀQm.

    Tubes that share no overlap do not interact, so each connected group of the overlap
    graph is its own QUBO: the same optimum, without an N × N matrix.
    """
    n = len(tubes)
    if not n:
        return np.zeros(0, bool)
    scores = np.asarray(scores, np.float64)
    overlap = overlap_pairs(tubes, cfg.box_iou_gate)
    if n <= DENSE_MAX:  # small: one dense QUBO (the solver splits it into groups itself)
        dense = overlap.toarray()
        return np.asarray(solve(build_qubo(scores, 0.5 * (dense + dense.T), cfg), cfg)[0], bool)
    m = np.zeros(n, bool)
    for members in connected_groups(overlap):
        sub = overlap[members][:, members].toarray()
        sub = 0.5 * (sub + sub.T)  # exact symmetry despite summation order
        Q = build_qubo(scores[members], sub, cfg)
        m[members] = np.asarray(solve(Q, cfg)[0], bool)
    return m
