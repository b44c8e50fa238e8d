"""Geometry-stage settings. Defaults from REFERENCE.md (the original implementation) unless noted."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class StereoConfig:
    """Dense disparity (the original used ELAS; we use OpenCV SGBM)."""

    num_disparities: int = 128  # ours: search range in px, covers ~3 m at KITTI's bf ≈ 386 px·m
    block_size: int = 5  # ours: SGBM matching block
    p1_factor: int = 8  # ours: SGBM P1 = factor · channels · block²  (OpenCV's usual choice)
    p2_factor: int = 32  # ours: SGBM P2 = factor · channels · block²
    uniqueness_ratio: int = 10  # ours: reject ambiguous minima, %
    speckle_window: int = 100  # ours: speckle filter area, px
    speckle_range: int = 2  # ours: speckle filter disparity range, px
    disp12_max_diff: int = 1  # ours: left-right consistency, px
    pre_filter_cap: int = 63  # ours: SGBM pre-filter clip
    mode: str = "sgbm_3way"  # ours: "sgbm", "sgbm_3way", "hh" or "hh4"
    grayscale: bool = True  # ours: match on grey images (3× cheaper cost volume than RGB)
    downscale: int = 2  # ours: 2 = match at half resolution (≈5× faster than full, abs-rel +0.003 on KITTI raw); 1 = full
    pad_left: bool = True  # ours: pad the left border so its first num_disparities columns get matched
    max_depth_m: float = 90.0  # REFERENCE: points beyond 90 m depth are ignored


@dataclass
class FlowConfig:
    """Sparse scene flow on cycle-consistent quad matches (libviso2-style in the original)."""

    nms_window: int = 5  # REFERENCE: feature non-maximum suppression window, px
    match_radius_px: float = 200.0  # REFERENCE: matching search radius, px
    disparity_tolerance_px: float = 1.0  # REFERENCE: left/right row tolerance, px
    outlier_tolerance_px: float = 5.0  # REFERENCE: cycle-closure tolerance, px
    bucket_size_px: int = 50  # REFERENCE: bucketing cell, px
    bucket_max_features: int = 2  # REFERENCE: features kept per bucket (egomotion)
    max_depth_m: float = 90.0  # REFERENCE: points beyond 90 m depth are ignored
    max_lateral_m: float = 30.0  # REFERENCE: points beyond 30 m lateral are ignored
    max_features: int = 4000  # ours: corners detected per image before matching
    detect_bucket_max: int = 8  # ours: corners kept per bucket for scene flow (spreads them over the image)
    fast_threshold: int = 20  # ours: FAST corner threshold (grey levels)
    max_disparity_px: float = 128.0  # ours: left/right matches must lie within the stereo search range
    lk_window: int = 9  # ours: Lucas–Kanade window, px
    lk_levels: int = 3  # ours: temporal LK pyramid levels without a motion prior (reach ≈ window · 2^levels)
    lk_levels_predicted: int = 1  # ours: temporal LK levels when the last egomotion predicts the match
    lk_levels_stereo: int = 1  # ours: left/right LK levels (the dense disparity or prediction starts it)
    lk_iterations: int = 20  # ours: LK iterations per level


@dataclass
class EgomotionConfig:
    """Stereo visual odometry (libviso2 in the original)."""

    ransac_iterations: int = 200  # REFERENCE: RANSAC iterations
    inlier_threshold_px: float = 2.0  # REFERENCE: reprojection inlier threshold, px
    min_inliers: int = 20  # ours: fewer inliers → the estimate is flagged as failed
    max_rmse_px: float = 1.5  # ours: inlier RMSE above this → flagged as failed
    refine_iterations: int = 20  # ours: Gauss–Newton iterations at most (it converges in ~5)
    seed: int = 0  # ours: RANSAC seed, results are reproducible


@dataclass
class GroundConfig:
    """Ground plane by RANSAC on the stereo point cloud."""

    min_below_camera_m: float = 1.0  # REFERENCE: use points more than 1.0 m below the camera
    max_lateral_m: float = 15.0  # REFERENCE: use points within |x| < 15 m
    max_tilt_deg: float = 20.0  # REFERENCE: normal within ±20° of the camera y axis
    inlier_distance_m: float = 0.1  # REFERENCE: RANSAC inlier distance
    iterations: int = 3000  # REFERENCE: RANSAC iterations
    min_points: int = 1000  # REFERENCE: fewer candidate points → no plane
    max_points: int = 20000  # ours: subsample the candidates for speed
    pixel_step: int = 3  # ours: take every 3rd disparity pixel in each direction as a candidate
    max_depth_m: float = 40.0  # ours: farther stereo points are too noisy to pin the plane
    score_points: int = 2000  # ours: RANSAC counts support on this many random candidates
    batch: int = 100  # ours: hypotheses scored per vectorised batch
    confidence: float = 0.999  # ours: adaptive RANSAC stop; `iterations` is the cap
    seed: int = 0  # ours: RANSAC seed


@dataclass
class GeometryConfig:
    stereo: StereoConfig = field(default_factory=StereoConfig)
    flow: FlowConfig = field(default_factory=FlowConfig)
    egomotion: EgomotionConfig = field(default_factory=EgomotionConfig)
    ground: GroundConfig = field(default_factory=GroundConfig)
