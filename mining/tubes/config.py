"""Tube generation settings (REFERENCE.md "Tube generation")."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from mining.checks import Count, Fraction, OneOf, Positive


@dataclass
class KalmanConfig:
    """Constant velocity on the ground plane; state x, y, z, vx, vz, w, h, l (world frame)."""

    process_std_position: tuple[float, float, float] = (0.5, 0.1, 0.5)  # REFERENCE: process noise std, position (m)
    process_std_velocity: tuple[float, float] = (1.0, 1.0)  # REFERENCE: process noise std, velocity (m/s)
    process_std_size: float = 0.05  # REFERENCE: process noise std, size (m)
    process_dt_s: Positive = 0.1  # REFERENCE: the original's fixed frame interval; noise above is per this interval
    measurement_std_size: tuple[float, float, float] = (0.2, 0.2, 0.5)  # REFERENCE: size measurement std (m)
    initial_var_velocity: tuple[float, float] = (1.0, 45.0)  # REFERENCE: initial vx, vz variance without flow
    max_size_m: Positive = 4.0  # REFERENCE: sizes ≤ 4 m


@dataclass
class AssociationFloor:
    """The association score a tube's best gated observation must exceed, by ``tubes.association``
    (the rules' scores live on different scales: a density per m², or a share of the density's peak)."""

    reference: float = 0.02  # REFERENCE: a tube takes its best gated observation if score > 0.02
    normalised: Fraction = 0.068  # ours: 0.02 / 0.296 = the reference's floor over the density's peak at 10 m on KITTI (f 721 px, b 0.54 m, 0.5 px: σx 0.71, σz 0.46 m, +0.2·I → 1/(2π·0.84·0.64)), so both rules accept the same pairs there (at 50 m, σz 4.6 m, the reference's floor is 0.48 in these units)
    innovation: Fraction = 0.068  # ours: as normalised (a share of the density's peak too; one value for both before issue 38)


@dataclass
class TubeConfig:
    kalman: KalmanConfig = field(default_factory=KalmanConfig)
    # Gating.
    gate_mahalanobis: float = 5.0  # REFERENCE: Mahalanobis distance of the footpoint < 5.0
    gate_box_iou: Fraction = 0.3  # REFERENCE: box IoU of predicted and observed > 0.3
    gate_size_similarity: Fraction = 0.6  # REFERENCE: 2D size similarity > 0.6
    gate_mask_iou: Fraction = 0.5  # REFERENCE: mask IoU > 0.5
    gate_jitter_px: float = 2.0  # ours: δ px of jitter the IoU gates tolerate (gate × shifted_iou(w, h, δ): 20 px box 0.68, 200 px 0.96; sizes compared +δ); 2 = ±1 px mask-boundary quantisation + ~1 px warp error; 0 = REFERENCE
    # Association.
    density_extra_var: float = 0.2  # REFERENCE: Gaussian density with observation covariance + 0.2·I
    # default "innovation" + 2 px jitter: HOTA up on synthetic training seeds and KITTI 0005 (docs/RESULTS.md,
    # "Association"); detections-only keeps "reference" (jobs/kitti-detections.toml: `mine bench crossval` chose it)
    association: Annotated[str, OneOf(("reference", "normalised", "innovation"))] = "innovation"  # "reference" = REFERENCE: IoU × Gaussian density > association_floor.reference; "normalised" = ours: the density is replaced by its value relative to its peak, exp(−½·m²), so the score means the same at every depth (the Mahalanobis gate already bounds the distance in σ), threshold association_floor.normalised; "innovation" = ours: the same with m under the Kalman innovation covariance (prediction + observation + 0.2·I, the gate's), the textbook normalised innovation, threshold association_floor.innovation
    association_floor: AssociationFloor = field(default_factory=AssociationFloor)  # was tubes.min_association and tubes.min_association_normalised (issue 38)
    # Mask prediction by 3D warping.
    warp_close_px: Count = 9  # REFERENCE: holes closed with a 9×9 box
    min_predicted_mask_px: int = 100  # REFERENCE: a predicted mask ≤ 100 px ends the tube
    # Start (forward-backward enumeration).
    backward_steps: Count = 5  # REFERENCE: run the filter backwards up to 5 frames
    backward_required: int = 3  # REFERENCE: require an inlier in each of the first 3 back-steps
    start_hypotheses: int = 3  # ours: velocity hypotheses (displacements to the frame before) per observation the own-motion start missed; 0 = none
    start_part_ioa: Fraction = 0.5  # ours: a mask at least half inside one a tube took is part of a tracked object: no displacement hypotheses
    start_max_speed_mps: Positive = 40.0  # ours: fastest object a displacement hypothesis may start (144 km/h on a motorway)
    view_edges: bool = True  # ours: an observed box side at the image border is where the view ends, not the object's edge: predictions from its mask's points compare later observations only up to that side (an object entering or leaving the view); False = REFERENCE (whole masks compared)
    view_edge_px: float = 2.0  # ours: a box side within this many px of the image border is a view edge (±1 px of mask-boundary quantisation, as gate_jitter_px)
    probe_with_boxes: bool = True  # ours: the backward probe gates on warped boxes (box IoU for mask IoU); the forward replay uses masks
    duplicate_box_iou: Fraction = 0.9  # REFERENCE: new tubes with the same inliers and box IoU ≥ 0.9 throughout are dropped
    # End.
    min_depth_m: float = 1.3  # REFERENCE: leaves the view behind 1.3 m
    max_depth_m: Positive = 80.0  # REFERENCE: leaves the view beyond 80 m
    lateral_margin: float = 0.3  # REFERENCE: lateral margin 0.3 (share of the image width outside the frame)
    max_gap_frames: int = 5  # REFERENCE: gap limit min(5, max(1, round(0.2 × inliers)))
    gap_inlier_factor: float = 0.2  # REFERENCE: gap limit min(5, max(1, round(0.2 × inliers)))
    # Joining fragments (issue 18): a tube ended by a gap waits this long for a new tube that continues it.
    join_gate_sigmas: float = 1.0  # ours: over a gap the IoU gates tolerate gate_jitter_px + this many σ of the predicted footpoint's lateral position in pixels (a 3-frame-old prediction drifts tens of px at 40 m); 1 measured best of 0 / 1 / 2 (docs/RESULTS.md, "Fragments")
    join_max_gap_s: float = 1.0  # ours: a confirmed new tube (3 back-step inliers) whose first observation is the ended tube's best gated one, predicted over ≤ 1 s (10 KITTI frames), continues it; 0 = REFERENCE (no joining)
    # Linking fragments of one object before selection (issue 18; mining/tubes/link.py).
    link_fragments: bool = True  # ours: add the joined tube of every chain of fragments as a candidate; False = REFERENCE (none)
    link_mask_iou: Fraction = 0.5  # REFERENCE's mask gate (> 0.5): two fragments' masks agree in a frame both observed when their IoU exceeds it
    link_agree_share: Fraction = 0.5  # ours: share of the frames both fragments observed whose masks agree; half measured better than all (docs/RESULTS.md, "Fragments")
    link_min_common: Count = 1  # ours: frames both fragments observed (and agree in) before they are one object
    # Tube NMS.
    nms_min_age: int = 4  # REFERENCE: tube NMS on tubes older than 4 frames
    nms_overlap: Fraction = 0.8  # REFERENCE: summed mask IoU / longer tube's inliers > 0.8 suppresses the weaker
    nms_length_ratio: Fraction = 0.7  # REFERENCE: ... when the length ratio ≥ 0.7
