"""Co-selection of tubes: the pairwise overlap term and the QUBO over a batch of tubes.

The pairwise term of two tubes is Σ_t o_t(i, j) over the frames both span, with o one of

* ``overlap="iou"`` (REFERENCE.md, the default): o_t = IoU(A, B) of their masks A, B,
  counted only when their boxes' IoU exceeds ``box_iou_gate``;
* ``overlap="min"`` (ours): o_t = |A∩B| / min(|A|, |B|), intersection over the smaller mask,
  counted only when their boxes' intersection over the smaller box exceeds ``box_iou_gate``.

A part of an object (a wheel arch inside a car) has IoU ≈ its share of the car's area and a
box IoU often under the 0.1 gate, so "iou" hardly charges a tube that explains pixels
another tube already explains; "min" charges it as much as a duplicate (o ≈ 1). The
energy itself is stated in ``mining.select.qubo``.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix

from mining.boxes import box_ioa, box_iou
from mining.errors import ConfigError
from mining.masks import mask_iou, mask_overlap_min
from mining.select.config import SelectConfig
from mining.select.qubo import build_qubo, connected_groups, solve
from mining.types import Tube


DENSE_MAX = 400  # ours: up to this many tubes one dense N × N QUBO is cheaper than splitting it first


OVERLAPS = ("iou", "min")  # the pairwise measures SelectConfig.overlap names (REFERENCE, ours)


def _frame_overlaps(
    boxes: np.ndarray, rles: list[dict], gate_at: float, overlap: str, floor: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The gated pairs (a, b) of one frame's tube frames and their mask overlap, both orders.

    Masks are compared in one batched call for the frames that have any gated partner;
    pycocotools skips mask merges for pairs whose boxes do not meet, and only gated pairs
    are kept.
    """
    if overlap == "iou":
        gate = box_iou(boxes, boxes) > gate_at
    else:  # intersection over the smaller box = the larger of the two intersections over area
        ioa = box_ioa(boxes, boxes)
        gate = np.maximum(ioa, ioa.T) > gate_at
    np.fill_diagonal(gate, False)
    rows = np.flatnonzero(gate.any(axis=1))
    if rows.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    here = [rles[r] for r in rows]
    values = mask_iou(here, here) if overlap == "iou" else mask_overlap_min(here, here)
    a, b = np.nonzero(gate[np.ix_(rows, rows)])
    return rows[a], rows[b], above_floor(values[a, b], floor)


def above_floor(values: np.ndarray, floor: float) -> np.ndarray:
    """Per-frame overlaps with the share two distinct objects' masks have in common taken
    off: 0 up to ``floor``, rising linearly to 1 at full overlap; ``floor`` 0 leaves them."""
    if floor <= 0.0:
        return values
    if floor >= 1.0:
        raise ConfigError(f"select.overlap_floor must be below 1, got {floor}")
    return np.clip((values - floor) / (1.0 - floor), 0.0, None)


def overlap_pairs(tubes: list[Tube], box_iou_gate: float, overlap: str = "iou", floor: float = 0.0) -> csr_matrix:
    """Sparse symmetric (N, N) Σ_t o_t over common frames, zero diagonal; o per ``overlap``
    ("iou": mask IoU gated by box IoU; "min": intersection over the smaller mask gated by
    intersection over the smaller box; ``floor``: ``above_floor``; module docstring).

    Sparse because tubes overlap only near in time: a sequence of thousands of tubes has
    few overlapping pairs, and a dense N × N matrix would not fit.
    """
    return overlap_matrix(frame_pairs(tubes, box_iou_gate, overlap, floor), len(tubes))


FramePairs = tuple[int, np.ndarray, np.ndarray, np.ndarray]  # frame, tube a, tube b, o_t(a, b): both orders


def frame_pairs(tubes: list[Tube], box_iou_gate: float, overlap: str = "iou", floor: float = 0.0) -> list[FramePairs]:
    """The gated pairs of every frame that two or more of ``tubes`` span, frames in the order
    ``tubes`` (and each tube's frames) first meet them, pairs in row-major order of the tubes'
    indices: the terms ``overlap_matrix`` sums. A pair's term depends on its two tubes alone, so
    the stitch can take them group by group and put them in this order afterwards."""
    if overlap not in OVERLAPS:
        raise ConfigError(f"select.overlap: unknown overlap {overlap!r}; known: {', '.join(OVERLAPS)}")
    by_frame: dict[int, list[tuple[int, object]]] = defaultdict(list)
    for i, tube in enumerate(tubes):
        for f in tube.frames:
            by_frame[f.frame].append((i, f))
    out = []
    for frame, entries in by_frame.items():
        if len(entries) < 2:
            continue
        idx = np.array([i for i, _ in entries])
        a, b, v = _frame_overlaps(np.array([f.box for _, f in entries]), [f.rle for _, f in entries],
                                  box_iou_gate, overlap, floor)
        out.append((frame, idx[a], idx[b], v))
    return out


def overlap_matrix(pairs: list[FramePairs], n: int) -> csr_matrix:
    """``overlap_pairs``' matrix from ``frame_pairs``' terms. Summed in the order given: scipy sums
    a pair's terms in an order that depends on that order, and the sums must not move by a bit."""
    if not pairs:
        return csr_matrix((n, n))
    rows_, cols_, vals_ = [p[1] for p in pairs], [p[2] for p in pairs], [p[3] for p in pairs]
    m = coo_matrix((np.concatenate(vals_), (np.concatenate(rows_), np.concatenate(cols_))), shape=(n, n)).tocsr()
    m.sum_duplicates()
    m.setdiag(0.0)
    m.eliminate_zeros()
    return m


def pairwise_overlap(tubes: list[Tube], box_iou_gate: float, overlap: str = "iou", floor: float = 0.0) -> np.ndarray:
    """(N, N) dense symmetric Σ_t o_t over common frames, zero diagonal (``overlap_pairs``)."""
    return overlap_pairs(tubes, box_iou_gate, overlap, floor).toarray()


def co_select(tubes: list[Tube], scores: np.ndarray, cfg: SelectConfig, model: str = "reference") -> np.ndarray:
    """Boolean selection of the tubes that maximise mᵀQm (``model``: the unary the scores come
    from, "reference" or "calibrated": it picks the price and overlap weight, ``build_qubo``).

    Tubes that share no overlap do not interact, so each connected group of the overlap
    graph is its own QUBO: the same optimum, without an N × N matrix.
    """
    if not len(tubes):
        return np.zeros(0, bool)
    return select_over(overlap_pairs(tubes, cfg.box_iou_gate, cfg.overlap, cfg.overlap_floor), scores, cfg, model)


def select_over(overlap: csr_matrix, scores: np.ndarray, cfg: SelectConfig, model: str = "reference") -> np.ndarray:
    """``co_select`` from the tubes' summed overlaps (``overlap_pairs``), for one tube or more."""
    n = overlap.shape[0]
    scores = np.asarray(scores, np.float64)
    if n <= DENSE_MAX:  # small: one dense QUBO (the solver splits it into groups itself)
        dense = overlap.toarray()
        return np.asarray(solve(build_qubo(scores, 0.5 * (dense + dense.T), cfg, model), cfg)[0], bool)
    m = np.zeros(n, bool)
    for members in connected_groups(overlap):
        sub = overlap[members][:, members].toarray()
        sub = 0.5 * (sub + sub.T)  # exact symmetry despite summation order
        Q = build_qubo(scores[members], sub, cfg, model)
        m[members] = np.asarray(solve(Q, cfg)[0], bool)
    return m
