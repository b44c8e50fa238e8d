"""Settings of the weight-free stereo proposer (``mining.proposals.stereo``). All ours: the
paper and the original implementation take their proposals from a trained network."""

from __future__ import annotations

from dataclasses import dataclass

from typing import Annotated

from mining.checks import Count, Fraction, OneOf, Positive, Signed


@dataclass
class StereoProposerConfig:
    """Object candidates from the stereo point cloud above the ground plane.

    The bird's-eye grid is polar: one column per ``column_px`` image columns (a viewing
    direction), and range cells ``range_cell_m`` deep near the camera that widen to
    ``disparity_cell_px`` of disparity farther out, where stereo depth noise outgrows them.
    """

    # Point cloud
    pixel_step: Count = 2  # ours: take every 2nd pixel in each direction (1/4 of the points)
    max_depth_m: Positive = 60.0  # ours: farther stereo points are too noisy to outline objects (REFERENCE's Z filter is 60 m)
    min_height_m: float = 0.2  # ours: points lower than this above the ground are ground (REFERENCE drops < 0.1 m proposals)
    # Low standing objects (issue 29: tyres, kerb-side boxes, fallen loads, a cone's base lie under the
    # ground cut): points down to this height (+1 height std) whose surface stands up from the ground
    # join the image-region grouping. 0 = off (only points above the ground cut, before issue 29).
    low_min_height_m: float = 0.0
    low_standing_ratio: Fraction = 0.5  # ours: a surface stands where its disparity grows down the image by less than this share of the ground's rate
    max_height_m: float = 4.0  # ours: points higher are canopy, facades, signs (REFERENCE drops > 5.0 m proposals)
    disparity_noise_px: Positive = 0.5  # ours: stereo disparity std at full resolution (SGBM at half resolution, measured on KITTI 2015)
    height_noise_sigmas: float = 2.0  # ours: the ground cut rises by this many height stds (far ground is noisy)
    # Polar bird's-eye grid
    column_px: Count = 6  # ours: image columns per grid column (0.17 m at 20 m on KITTI)
    range_cell_m: Positive = 0.25  # ours: range cell depth near the camera
    disparity_cell_px: Positive = 0.5  # ours: range cell depth in disparity where that is coarser (≈ 1 noise std; 1.0 px: R@all 0.75 vs 0.79 on KITTI 0005)
    min_density_m: float = 0.15  # ours: a cell is occupied by ≥ this many metres of visible vertical surface
    # Multi-scale clustering: each scale = (density multiplier, grid dilation rows, columns).
    # Finer scales split touching objects, coarser ones join objects broken by holes.
    scales: tuple[tuple[float, int, int], ...] = (
        (1.0, 0, 0), (1.0, 1, 1), (1.0, 2, 6), (3.0, 0, 0),
    )  # ours: chosen on KITTI 0005 and synthetic (adding (1, 1, 3) and (3, 1, 1) changed no recall)
    height_band_m: float = 1.0  # ours: extra clusters within bands of cell top height (two offsets); 0 = off (KITTI 0005 car R@all 0.77 → 0.33)
    image_jumps_px: tuple[float, ...] = (1.0,)  # ours: image regions are cut where neighbouring disparities differ by more (≈ 2 noise stds, or border_gap_m); () = off
    jump_span: Count = 1  # ours: image regions are also cut at jumps over 2 … jump_span samples (SGBM smears a depth edge over a few pixels); 1 = neighbours only (before issue 29)
    min_points: Count = 8  # ours: clusters with fewer sample points are noise (12 before issue 29; 8: far objects, with support_ref_depth_m and mask_budget 1.5 unknown proposed +0.7 points on seeds 0000–0006)
    stats_points: Count = 256  # ours: a cluster's percentiles (extent, top) come from about this many of its points
    max_extent_m: Positive = 10.0  # ours: footprints longer than this are structures (walls, hedges), not objects
    # Image masks
    grow_min_height_m: float = 0.05  # ours: masks grow over points this high (+1 height std) at the object's depth
    grow_steps: int = 12  # ours: at most this many growth steps of one sample; fewer where the cut band is thinner in the image
    left_trim_px: int = 4  # ours: masks lose this many pixels at their left edges (left-reference stereo fattens them there; 8 px: better on KITTI, worse on synthetic)
    mask_close_px: Count = 7  # ours: closing kernel (full-resolution px) that fills stereo holes in a mask
    # Image refinement (issue 29): stereo masks bleed at their borders (a 20 px crate loses IoU 0.5 to
    # two pixels), so small masks are moved to the object's outline in the image by GrabCut.
    refine: Annotated[str, OneOf(("none", "colour", "grabcut"))] = "colour"  # ours: "colour" (histograms of mask vs ring; unknown proposed 0.28 → 0.46 stereo, 0.50 → 0.60 onnx+stereo on seeds 0000–0006, every seed up), "grabcut" (OpenCV's, ~4 ms a mask, +0.01) or "none" (the stereo mask as is, before issue 29)
    refine_colour_bits: Count = 3  # ours: colour histograms of 2^(3·bits) bins (3: 512, from 8×8×8 RGB levels)
    refine_max_area_px: Count = 2000  # ours: only masks up to this area are refined (larger ones lose little IoU to a border pixel); 2000 / 4000 / 8000 px: the same unknown proposed (0.644 onnx+stereo, seeds 0000–0006), 2000 the cheapest
    refine_band_px: Count = 4  # ours: the band around the mask the refinement may give to the object (the colour ring lies outside it, to twice this) (≈ the bleeding of left-reference stereo at half resolution)
    refine_iterations: Count = 2  # ours: GrabCut iterations
    refine_keep_stereo: bool = False  # ours: also keep the stereo mask beside its refined one (both proposed)
    refine_min_keep: Fraction = 0.3  # ours: a cut keeping less of the stereo mask is a failed colour model: the stereo mask stays
    # Objectness = sigmoid(bias + Σ weight·cue); every cue lies in [0, 1], higher = more object-like,
    # and every weight is ≥ 0, so objectness never decreases when a cue increases.
    plausible_extent_m: Positive = 5.0  # ours: footprints up to this long are fully plausible (cars, people, bins)
    plausible_top_m: tuple[float, float] = (0.4, 2.5)  # ours: object tops in this height range are fully plausible
    support_points: Count = 400  # ours: clusters with this many sample points are fully supported
    support_ref_depth_m: float = 10.0  # ours: > 0: support counts a cluster's visible surface, in sample points at this depth (nearer points count as at it), so a far object is not ranked out for having fewer points (10 m: unknown 40–60 m proposed 0.46 → 0.53 with the other far settings, seeds 0000–0006; 20 m: 0.52); 0 = points (before issue 29)
    border_gap_m: float = 0.5  # ours: a border pixel this much farther than the object (or more than the noise) is background
    # Weights chosen on KITTI 0005 frames 0–15 (cars only: support, fill and top separate them from
    # clutter best; the border contrast less, as parked cars touch bushes) and checked on synthetic
    # frames with unknown objects. Tuned and measured on the same frames — optimistic figures.
    bias: Signed = -4.0  # ours: objectness with all cues at 0
    w_contrast: float = 1.0  # ours: the mask's border stands out in depth (free space around)
    w_fill: float = 3.0  # ours: the mask fills its box (compact in the image)
    w_extent: float = 1.5  # ours: plausible footprint
    w_top: float = 2.0  # ours: plausible height
    w_support: float = 2.0  # ours: enough stereo points (4.0 ranks KITTI cars a bit higher, small unknown objects lower)
    nms_iou: Fraction = 0.9  # ours: box IoU at which a lower-scoring near-duplicate from another scale goes
    max_proposals: Count = 100  # ours: at most this many per frame, best objectness first
    mask_budget: float = 1.5  # ours: masks are built for at most this × max_proposals clusters, best cheap cues first (1.0 before issue 29; 1.5: unknown proposed 0.617 → 0.644 onnx+stereo with the other issue-29 settings, seeds 0000–0006)
