"""Settings of 3D localisation and the geometric proposal filter (REFERENCE.md §5, §6)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from mining.checks import Count, Fraction, Positive, Range


@dataclass
class ProposalFilterConfig:
    """The geometric proposal filter, applied once proposals are localised in 3D (``[localise.filters]``,
    ``localise.geometric_filter``)."""

    min_box_area_px: float = 100.0  # REFERENCE: drop proposals whose box area < 100 px²
    max_abs_x_m: float = 50.0  # REFERENCE: drop ground-projected |X| > 50 m
    # The stereo range: the paper tracks to 40–50 m and REFERENCE's filter allows 60 m. At 60 m
    # KITTI's disparity is bf/Z ≈ 6.4 px and one point's depth std ≈ 6.6 m (0.5 px per image column).
    z_range_m: tuple[float, float] = (0.0, 60.0)  # REFERENCE: drop ground-projected Z outside (0, 60) m
    height_range_m: tuple[float, float] = (0.1, 5.0)  # REFERENCE: drop height above ground outside (0.1, 5.0) m
    # The limits above are on the object's true place; a stereo estimate is only dropped when it
    # lies beyond them by more than this many of its own standard deviations (the observation's
    # triangulation covariance: σ_Z grows as Z², σ_h = √(nᵀΣn)). For |X| and Z the test is on the
    # nearest point of the viewing ray within that many disparity stds (disparity noise is
    # Gaussian, depth noise is not): on KITTI, with 0.5 px pixel noise, an estimate is dropped beyond
    # Z ≈ 77 m, not 60 m. 0 = the hard limits on the estimate.
    noise_sigmas: float = 2.0  # ours: 2 std drops few objects at a limit (`mine bench range`, docs/RESULTS.md)
    max_proposals: Count = 300  # REFERENCE: sorted by score, at most 300 kept (authors advise ≤ 500)
    min_objectness: Fraction = 0.0  # ours: 0 keeps every proposal (REFERENCE's 0.8 cut defeats generic proposals); detectors may want one


@dataclass
class LocaliseConfig:
    # Checked at range (`mine bench range`; docs/RESULTS.md): the covariance is honest at 10–60 m, so it stays.
    pixel_noise_px: Positive = 0.5  # REFERENCE: stereo triangulation with 0.5 px pixel noise
    prior_var_x: float = 0.5  # REFERENCE: covariance prior, +0.5 on x (m²)
    prior_var_z: float = 0.18  # REFERENCE: covariance prior, +0.18 on z (m²)
    min_points: Count = 10  # REFERENCE: at least 10 points for a 3D box
    min_flow_samples: Count = 4  # REFERENCE: fewer than 4 flow samples → no velocity measurement
    velocity_noise_factor: Positive = 2.0  # REFERENCE: velocity measurement noise = 2 × the position covariance
    max_size_m: Positive = 4.0  # REFERENCE: sizes ≤ 4 m
    max_points: Count = 1000  # ours: mask pixels sampled per proposal on a regular grid (median and warping need no more)
    point_outlier_mahalanobis: float = 10.0  # REFERENCE: mask points beyond 10 Mahalanobis units from the median are dropped before warping
    # ours: of the points left, one whose depth lies this many robust units (1.4826 MAD, floored by the stereo depth
    # noise) from the mask's median depth takes the median depth on its own pixel (``at_median_depth``); 0 = REFERENCE
    # (warped at its own depth). Chosen on training seeds 0004–0006 (docs/RESULTS.md).
    point_depth_outlier_units: float = 5.0
    size_percentiles: Annotated[tuple[float, float], Range(0, 100)] = (5.0, 95.0)  # ours: robust extent of the mask's points
    filters: ProposalFilterConfig = field(default_factory=ProposalFilterConfig)
