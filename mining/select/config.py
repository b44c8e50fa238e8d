"""Co-selection settings: the QUBO energy's weights and the solver's search limits.

Defaults from REFERENCE.md ("Co-selection") and the original implementation unless noted.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Annotated

from mining.checks import Count, Fraction, OneOf, Range, Signed


@dataclass
class Price:
    """ε1, the price of selecting a tube (the unary's offset), by the unary the scores come from
    (``score.model``: REFERENCE's weighted sum or the calibrated log-odds, on scales of their own)."""

    reference: Signed = 20.0  # REFERENCE: ε1, price of selecting a tube (unary offset)
    calibrated: Signed = 0.0  # ours: ε1 with the calibrated unary (score.model), a log-odds: 0 selects a tube alone when it is more likely an object than not


@dataclass
class OverlapWeight:
    """ε2, the weight of the pairwise overlap penalty, by the unary the scores come from (as ``Price``)."""

    # ε2 stays 30 for overlap="min" too. o_min ≥ IoU, but it grows only where one mask lies
    # (mostly) inside the other: a duplicate of equal size changes little (IoU 0.8 → o 0.89),
    # a part jumps from IoU ≈ its area share (~0.1) to ≈ 1, i.e. 30 a frame, far above any
    # tube's score per frame (~2–8). Two real neighbours that touch or occlude each other
    # (parked cars in a row) keep o small, since visible masks share only boundary pixels
    # (a few columns: o ≈ 0.05 → 1.5 a frame), so they stay selected (tests/test_select_parts.py).
    reference: float = 30.0  # REFERENCE: ε2, weight of the pairwise overlap penalty
    # ours: ε2 with the calibrated unary, chosen by `mine bench calibrate` (docs/RESULTS.md, "The calibrated unary");
    # 3, not 1: a duplicate (mask IoU ≥ 0.4 a frame) must still cost more than a strong object's log-odds a frame (≈ 1)
    calibrated: float = 3.0


UNARY_MODELS = tuple(f.name for f in dataclasses.fields(Price))  # the keys of the tables by unary: "reference", "calibrated"


@dataclass
class SelectConfig:
    # --- the energy: maximise mᵀQm, Q_ii = score_i − ε1, Q_ij = −½·ε2·Σ_t o_t(i, j), o per ``overlap``;
    # ε1 and ε2 by the unary the scores come from (the two live on different scales)
    price: Price = field(default_factory=Price)  # was select.epsilon1 and select.epsilon1_calibrated (issue 38)
    # ours (issue 39): added to ε1 for a tube called unknown (mining/score/call.py), in the unary's units; < 0 makes
    # unknown candidates cheaper than the whole set's operating point. 0 measured best: −1 raised unknown frame recall
    # 0.368 → 0.412 but cut the unknown set's precision 0.44 → 0.32 on seeds 0000–0006 (docs/RESULTS.md, issue 39)
    unknown_price: Signed = 0.0
    overlap_weight: OverlapWeight = field(default_factory=OverlapWeight)  # was select.epsilon2 and select.epsilon2_calibrated (issue 38)
    window_frames: Count = 100  # REFERENCE/paper: batches of 100 frames (original: ±50 frames around each frame)
    box_iou_gate: Fraction = 0.1  # REFERENCE: a frame's overlap counts only when the boxes' overlap (IoU; for "min": intersection over the smaller box) exceeds this
    overlap: Annotated[str, OneOf(("iou", "min"))] = "iou"  # "iou" = REFERENCE Σ_t mask IoU; "min" = ours: Σ_t |A∩B| / min(|A|, |B|) (intersection over the smaller mask, the overlap coefficient), so a part inside another tube costs as much as a duplicate
    overlap_floor: Annotated[float, Range(0, 0.99)] = 0.0  # ours: a frame's overlap up to this costs nothing (what two distinct objects' masks share at occlusion boundaries), then rises linearly to 1 at full overlap; 0 = REFERENCE

    # --- the original's greedy multi-branch search (Schindler et al. ECCV 2006)
    # The first two branch widths narrow as the problem grows: problems with fewer than
    # branch_size_limits[k] candidates use branch_head_widths[k]; larger ones the last entry.
    branch_size_limits: list[int] = field(default_factory=lambda: [50, 70, 100, 250])  # REFERENCE ("narrowing"; tiers from the original implementation)
    branch_head_widths: list[list[int]] = field(
        default_factory=lambda: [[50, 50], [70, 25], [50, 20], [50, 10], [50, 5]]
    )  # REFERENCE: widths of search levels 1–2 per size class
    branch_tail_widths: list[int] = field(default_factory=lambda: [5, 2, 1, 1])  # REFERENCE: levels 3–6; deeper levels are greedy (width 1)

    # --- our production solver (mining.select.qubo.solve)
    solver: Annotated[str, OneOf(("auto", "multibranch", "exhaustive"))] = "auto"  # ours: "auto" (reduce, split, exact or multi-branch + local search), "multibranch" (the original's), "exhaustive"
    exact_max_candidates: Annotated[int, Range(0, 26, why="2^26 selections is about the most enumeration stays practical for")] = 20  # ours: components this small are solved exactly by enumeration (2^20 in a few ms)
    tabu_iterations: int = 2000  # ours: at most this many 1-flip tabu moves per start on a large component
    tabu_stall_iterations: int = 300  # ours: a tabu run stops after this many moves without a new best (100 missed 1 of 30 hard groups, 300 none)
    tabu_restarts: int = 1  # ours: extra tabu runs from a seeded random perturbation of the best solution
    seed: int = 0  # ours: seeds tabu tenure jitter and perturbations, so results are reproducible
    time_limit_s: float = 0.0  # ours: wall-clock cap on the local search per component; 0 = none (keeps results deterministic)

    def energy_weights(self, model: str) -> tuple[float, float]:
        """(ε1, ε2): the price and overlap weight for scores of the unary ``model`` ("reference"
        or "calibrated", ``UNARY_MODELS``)."""
        if model not in UNARY_MODELS:
            raise ValueError(f"unary model must be one of {UNARY_MODELS}, got {model!r}")
        return getattr(self.price, model), getattr(self.overlap_weight, model)
