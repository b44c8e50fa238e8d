"""Geometry-stage settings. Defaults from REFERENCE.md (the original implementation) unless noted."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from mining.checks import Count, MultipleOf, Odd, OneOf, Positive, Range


@dataclass
class StereoConfig:
    """Dense disparity (the original used ELAS; we use OpenCV SGBM)."""

    num_disparities: Annotated[int, Range(16), MultipleOf(16, "OpenCV SGBM searches disparities in blocks of 16")] = 128  # ours: search range in px, covers ~3 m at KITTI's bf ≈ 386 px·m
    block_size: Annotated[int, Range(1), Odd("SGBM matching blocks are centred on a pixel")] = 5  # ours: SGBM matching block
    p1_factor: int = 8  # ours: SGBM P1 = factor · channels · block²  (OpenCV's usual choice)
    p2_factor: int = 32  # ours: SGBM P2 = factor · channels · block²
    uniqueness_ratio: Annotated[int, Range(0, 100)] = 10  # ours: reject ambiguous minima, %
    speckle_window: int = 100  # ours: speckle filter area, px
    speckle_range: int = 2  # ours: speckle filter disparity range, px
    disp12_max_diff: int = 1  # ours: left-right consistency, px
    pre_filter_cap: int = 63  # ours: SGBM pre-filter clip
    mode: Annotated[str, OneOf(("sgbm", "sgbm_3way", "hh", "hh4"))] = "sgbm_3way"  # ours: "sgbm", "sgbm_3way", "hh" or "hh4"
    grayscale: bool = True  # ours: match on grey images (3× cheaper cost volume than RGB)
    downscale: Count = 2  # ours: 2 = match at half resolution (≈5× faster than full, abs-rel +0.003 on KITTI raw); 1 = full
    # ours: a matching image (after downscale) taller than this is also reduced vertically, by the smallest integer
    # factor that brings it within; depth precision is horizontal (bf), so it holds there. KITTI (188 rows at half
    # resolution) is untouched at 256; RobotCar 1280×960 would match at 640×240 (SGBM 38 → 18 ms). 0 = never, the default.
    # Off by default: measured, it fails the depth gate (abs-rel ≤ 40 m 0.037 → 0.050 on RobotCar-geometry synthetic
    # frames at 256 rows, 0.037 → 0.057 on KITTI raw LiDAR forced to half its rows; docs/RESULTS.md, issue 30)
    max_match_rows: Annotated[int, Range(0)] = 0
    # ours: when > 0, the search range is set by the nearest depth to match instead of num_disparities: bf / min_depth_m,
    # rounded up to SGBM's blocks (16 px at the matching scale). 0 = num_disparities as given (the default: KITTI's 128 px
    # is 3.0 m at bf 384 px·m). jobs/oxford.toml sets 2.5 m: RobotCar's wide pair (bf 236 px·m) then searches 96 px
    # instead of 128 (SGBM at 1280×960 −19 %, depth unchanged within 40 m; docs/RESULTS.md, issue 30)
    min_depth_m: Annotated[float, Range(0)] = 0.0
    # ours: a second SGBM pass at full resolution over disparities [0, far_full_disparities) (on KITTI, bf ≈ 386 px·m:
    # 32 px = depths beyond 12 m), over the rows that hold them, taken wherever the half-resolution disparity is below
    # that range less far_full_margin_px: far objects get full-resolution precision. 32 = ours, on by default since
    # issue 39: unknown frame recall 0.357 → 0.443 on training seeds 0000–0004 (known recall and HOTA up too; held
    # out: known recall and HOTA up, unknown recall flat), the geometry step 40.6 → 72.5 ms a frame on one core
    # (`mine bench geometry`; docs/RESULTS.md); 0 = off, REFERENCE's single half-resolution pass
    far_full_disparities: Annotated[int, Range(0), MultipleOf(16, "OpenCV SGBM searches disparities in blocks of 16")] = 32
    # ours: the far pass matches one row in far_row_step (rows averaged, INTER_AREA) and spreads the result back:
    # a far object's depth rests on its columns (bf / d) and the pass costs by rows. 1 = every row, the default:
    # 2 fails the depth gate on KITTI raw LiDAR (abs-rel within 40 m 0.0368 → 0.0406); jobs/oxford.toml sets 2
    # (RobotCar's 960 rows; docs/RESULTS.md, issue 42)
    far_row_step: Annotated[int, Range(1)] = 1
    far_full_margin_px: Annotated[float, Range(0)] = 8.0  # ours: the far pass's own range end is unreliable (a nearer surface clips to it)
    pad_left: bool = True  # ours: pad the left border so its first num_disparities columns get matched
    max_depth_m: Positive = 90.0  # REFERENCE: points beyond 90 m depth are ignored
    # ours, an instrument, never a mining setting: take the synthetic source's exact depth instead of
    # matching (`mine eval synthetic --set geometry.stereo.exact_depth=true`), so the recall funnel
    # separates what stereo depth loses from what proposals, tubes and selection lose. A frame
    # without exact depth (every real source) is an error, not a fallback to matching.
    exact_depth: bool = False


@dataclass
class FlowConfig:
    """Sparse scene flow on cycle-consistent quad matches (libviso2-style in the original)."""

    nms_window: Count = 5  # REFERENCE: feature non-maximum suppression window, px
    match_radius_px: Positive = 200.0  # REFERENCE: matching search radius, px
    disparity_tolerance_px: float = 1.0  # REFERENCE: left/right row tolerance, px
    outlier_tolerance_px: float = 5.0  # REFERENCE: cycle-closure tolerance, px
    bucket_size_px: Count = 50  # REFERENCE: bucketing cell, px
    bucket_max_features: Count = 2  # REFERENCE: features kept per bucket (egomotion)
    max_depth_m: Positive = 90.0  # REFERENCE: points beyond 90 m depth are ignored
    max_lateral_m: Positive = 30.0  # REFERENCE: points beyond 30 m lateral are ignored
    max_features: Count = 4000  # ours: corners detected per image before matching
    detect_bucket_max: Count = 8  # ours: corners kept per bucket for scene flow (spreads them over the image)
    fast_threshold: Annotated[int, Range(1, 255)] = 20  # ours: FAST corner threshold (grey levels)
    max_disparity_px: Positive = 128.0  # ours: left/right matches must lie within the stereo search range
    lk_window: Annotated[int, Range(3)] = 9  # ours: Lucas–Kanade window, px
    lk_levels: int = 3  # ours: temporal LK pyramid levels without a motion prior (reach ≈ window · 2^levels)
    lk_levels_predicted: int = 1  # ours: temporal LK levels when the last egomotion predicts the match
    lk_levels_stereo: int = 1  # ours: left/right LK levels (the dense disparity or prediction starts it)
    lk_iterations: Count = 20  # ours: LK iterations per level


@dataclass
class EgomotionConfig:
    """Stereo visual odometry (libviso2 in the original)."""

    ransac_iterations: Count = 200  # REFERENCE: RANSAC iterations
    inlier_threshold_px: Positive = 2.0  # REFERENCE: reprojection inlier threshold, px
    min_inliers: Annotated[int, Range(3, why="a rigid motion needs three points")] = 20  # ours: fewer inliers → the estimate is flagged as failed
    max_rmse_px: Positive = 1.5  # ours: inlier RMSE above this → flagged as failed
    refine_iterations: int = 20  # ours: Gauss–Newton iterations at most (it converges in ~5)
    seed: int = 0  # ours: RANSAC seed, results are reproducible


@dataclass
class GroundConfig:
    """Ground plane by RANSAC on the stereo point cloud."""

    min_below_camera_m: float = 1.0  # REFERENCE: use points more than 1.0 m below the camera
    max_lateral_m: float = 15.0  # REFERENCE: use points within |x| < 15 m
    max_tilt_deg: Annotated[float, Range(0, 90)] = 20.0  # REFERENCE: normal within ±20° of the camera y axis
    inlier_distance_m: Positive = 0.1  # REFERENCE: RANSAC inlier distance
    iterations: Count = 3000  # REFERENCE: RANSAC iterations
    min_points: Annotated[int, Range(3, why="a plane needs three points")] = 1000  # REFERENCE: fewer candidate points → no plane
    max_points: Annotated[int, Range(3)] = 20000  # ours: subsample the candidates for speed
    pixel_step: Count = 3  # ours: take every 3rd disparity pixel in each direction as a candidate
    max_depth_m: Positive = 40.0  # ours: farther stereo points are too noisy to pin the plane
    score_points: Count = 2000  # ours: RANSAC counts support on this many random candidates
    batch: Count = 100  # ours: hypotheses scored per vectorised batch
    confidence: Annotated[float, Range(0, 1, lo_open=True, hi_open=True)] = 0.999  # ours: adaptive RANSAC stop; `iterations` is the cap
    seed: int = 0  # ours: RANSAC seed


@dataclass
class GeometryConfig:
    stereo: StereoConfig = field(default_factory=StereoConfig)
    flow: FlowConfig = field(default_factory=FlowConfig)
    egomotion: EgomotionConfig = field(default_factory=EgomotionConfig)
    ground: GroundConfig = field(default_factory=GroundConfig)
