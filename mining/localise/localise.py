"""3D localisation of mask proposals (the paper's p, v, s per proposal; REFERENCE.md §6).

Position is the median of the mask's 3D points, with the covariance of stereo
triangulation at that point plus a prior. The footpoint is the position projected onto
the ground plane. Velocity is a robust mean of the scene-flow motions inside the mask
divided by the frame interval. Size is the robust 3D extent of the mask's points.

In detections-only mode (no images) the detector's 3D box gives position and size and
the footpoint is the box's bottom centre; the covariance follows the same stereo model.
"""

from __future__ import annotations

import math

import numpy as np

from mining.localise.config import LocaliseConfig, ProposalFilterConfig
from mining.masks import batch_mask_runs, grid_run_pixels
from mining.types import GroundPlane, Observations, Proposals, SceneFlow, StereoCalib


def triangulation_covariance(points: np.ndarray, calib: StereoCalib, cfg: LocaliseConfig) -> np.ndarray:
    """(N, 3, 3) covariance of stereo-triangulated points with pixel noise, plus the prior.

    X = (u − cx)·Z/f, Y = (v − cy)·Z/f, Z = f·b/d: first-order propagation of independent
    noise on u, v and the two image columns that make d.
    """
    p = np.asarray(points, np.float64).reshape(-1, 3)
    n = len(p)
    cov = np.full((n, 3, 3), np.nan)
    ok = np.isfinite(p).all(axis=1) & (p[:, 2] > 0)
    x, y, z = p[ok, 0], p[ok, 1], p[ok, 2]
    f = calib.fx
    d = f * calib.baseline_m / z
    J = np.zeros((ok.sum(), 3, 3))
    J[:, 0, 0] = z / f
    J[:, 1, 1] = z / f
    J[:, 0, 2] = -x / d
    J[:, 1, 2] = -y / d
    J[:, 2, 2] = -z / d
    s2 = cfg.pixel_noise_px**2
    S = np.diag([s2, s2, 2 * s2])  # d = u_left − u_right: two noisy columns
    c = J @ S @ J.transpose(0, 2, 1)
    c[:, 0, 0] += cfg.prior_var_x
    c[:, 2, 2] += cfg.prior_var_z
    cov[ok] = c
    return cov


def project_to_ground(points: np.ndarray, ground: GroundPlane) -> np.ndarray:
    """Orthogonal projection of camera points onto the ground plane."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    h = p @ ground.normal + ground.d
    return p - h[:, None] * ground.normal[None, :]


def _flow_keys(flow: SceneFlow | None, width: int, height: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Scene-flow samples by column-major pixel index (column · height + row, the order of
    COCO RLE runs), sorted, with the sample's row in ``flow``."""
    if flow is None or len(flow) == 0:
        return None
    good = np.flatnonzero(np.isfinite(flow.motion).all(axis=1))
    u = np.clip(np.round(flow.uv[good, 0]).astype(np.int64), 0, width - 1)
    v = np.clip(np.round(flow.uv[good, 1]).astype(np.int64), 0, height - 1)
    keys = u * height + v
    order = np.argsort(keys, kind="stable")
    return keys[order], good[order]


def localise(
    proposals: Proposals,
    depth: np.ndarray,
    calib: StereoCalib,
    ground: GroundPlane,
    flow: SceneFlow | None,
    dt_s: float | None,
    t_ns: int,
    cfg: LocaliseConfig,
) -> Observations:
    """Localise every proposal of one frame; rows without enough depth stay NaN.

    All masks' pixels are handled as one array (``seg`` says whose pixel it is); only the
    per-mask sort and the point covariance run mask by mask.
    """
    n = len(proposals)
    h, w = depth.shape
    position = np.full((n, 3), np.nan)
    size = np.full((n, 3), np.nan)
    heights = np.array([int(r["size"][0]) for r in proposals.rles], np.int64)
    if (heights != h).any():
        raise ValueError(f"masks {sorted(set(heights.tolist()) - {h})} rows high on a depth map of {h} rows")
    runs = batch_mask_runs(proposals.rles)  # (mask, first pixel, length) of each run of the masks' pixels
    velocity = _velocities(*runs, n, flow, dt_s, w, h, cfg) if dt_s else np.full((n, 3), np.nan)
    # A regular grid keeps at most ~max_points samples spread over each mask.
    count = np.bincount(runs[0], weights=runs[2], minlength=n).astype(np.int64)
    grid = np.where(count > cfg.max_points, np.ceil(np.sqrt(count / cfg.max_points)), 1).astype(np.int64)
    seg, rows, cols = grid_run_pixels(*runs, heights, grid)
    z = depth.ravel()[rows * w + cols]
    ok = np.isfinite(z)
    n_points = np.bincount(seg[ok], minlength=n).astype(np.int64)
    good = n_points >= cfg.min_points
    velocity[~good] = np.nan
    ok &= good[seg]
    seg = seg[ok]
    pts = calib.backproject(cols[ok], rows[ok], z[ok])
    bounds = np.searchsorted(seg, np.arange(n + 1))
    masks = np.flatnonzero(good)
    # One sort per mask gives the median and the robust extent (nearest-rank percentiles).
    srt = np.empty_like(pts)
    for i in masks:
        srt[bounds[i]:bounds[i + 1]] = np.sort(pts[bounds[i]:bounds[i + 1]], axis=0)
    first, m = bounds[masks], n_points[masks] - 1
    lo, hi = cfg.size_percentiles
    position[masks] = 0.5 * (srt[first + m // 2] + srt[first + (m + 1) // 2])
    size[masks] = np.minimum(srt[first + np.round(hi / 100 * m).astype(np.int64)]
                             - srt[first + np.round(lo / 100 * m).astype(np.int64)], cfg.max_size_m)
    keep = _inliers(pts, position[seg], bounds, masks, cfg.point_outlier_mahalanobis)
    points: list[np.ndarray] = [np.zeros((0, 3), np.float32)] * n
    kept = np.concatenate([[0], np.cumsum(keep)])[bounds]
    pts32 = pts[keep].astype(np.float32)
    for i in masks:
        points[i] = pts32[kept[i]:kept[i + 1]]
    obs = _observations(proposals, t_ns, position, size, velocity, n_points, calib, ground, cfg)
    if cfg.point_depth_outlier_units > 0:  # the depth noise floor: the triangulation covariance just computed
        units = cfg.point_depth_outlier_units
        for i in _may_move_to_median_depth(pts32[:, 2], kept, masks, obs.covariance[:, 2, 2], units):
            points[i] = at_median_depth(points[i], math.sqrt(obs.covariance[i, 2, 2]), units)
    obs.points, obs.grid = points, grid
    return obs


def _velocities(run_seg: np.ndarray, run_start: np.ndarray, run_len: np.ndarray, n: int, flow: SceneFlow | None,
                dt_s: float, width: int, height: int, cfg: LocaliseConfig) -> np.ndarray:
    """(n, 3) median scene-flow motion of the samples inside each mask / dt (NaN with too few); the
    masks are given as runs of pixels (``batch_mask_runs``)."""
    velocity = np.full((n, 3), np.nan)
    keys = _flow_keys(flow, width, height)
    if keys is None or run_seg.size == 0:
        return velocity
    flow_at, rows_of = keys
    # The flow samples inside each run (a pixel may hold several), in ``flow_at`` order: found
    # from the run's ends, not pixel by pixel.
    start = np.searchsorted(flow_at, run_start)
    k = np.searchsorted(flow_at, run_start + run_len) - start
    at = np.repeat(start - np.concatenate([[0], np.cumsum(k)[:-1]]), k) + np.arange(k.sum())
    samples, owner = rows_of[at], np.repeat(run_seg, k)  # owner ascends: masks come in order
    n_samples = np.bincount(owner, minlength=n)
    enough = np.flatnonzero(n_samples >= cfg.min_flow_samples)
    if enough.size == 0:
        return velocity
    keep = (n_samples >= cfg.min_flow_samples)[owner]
    motion, owner = flow.motion[samples[keep]], owner[keep]
    # Median per mask and axis: sort each mask's values, average the middle one or two
    # (as np.median does, in the motion's dtype).
    first, m = np.searchsorted(owner, enough), n_samples[enough]
    for c in range(3):
        v = motion[np.lexsort((motion[:, c], owner)), c]
        velocity[enough, c] = (v[first + (m - 1) // 2] + v[first + m // 2]) / 2 / dt_s
    return velocity


def at_median_depth(points: np.ndarray, noise_z: float, units: float) -> np.ndarray:
    """A mask's warp points with each depth outlier moved along its viewing ray to the mask's median depth.

    A depth outlier lies more than ``units`` robust units from the points' median depth:
    1.4826 × the median absolute deviation, floored by ``noise_z`` (the stereo depth noise
    std at the mask's position). Such a pixel belongs to the mask but its depth is not the
    object's (an occluder in front of it, stereo bleeding across the object's border):
    dropping it shrinks the predicted mask below the masks it is compared with, while
    warping it at its own depth sends it tens of pixels away when the camera moves (a
    person at 29 m with 5 % of its pixels at 8 m: a 16 px box predicted 45 px wide one
    frame back). Keeping the pixel at the object's depth moves it with the object.
    """
    if len(points) < 4:
        return points
    z = points[:, 2]
    med = float(np.median(z))
    dev = np.abs(z - med)
    if dev.max() <= units * noise_z:
        return points  # within the noise floor: no point can be an outlier
    out = dev > units * max(1.4826 * float(np.median(dev)), noise_z)
    if not out.any() or out.sum() > len(points) - 3:
        return points
    moved = points.copy()
    moved[out] *= (med / z[out])[:, None]  # the same pixel (x/z, y/z kept), at the median depth
    return moved


def _may_move_to_median_depth(z: np.ndarray, bounds: np.ndarray, masks: np.ndarray, var_z: np.ndarray,
                              units: float) -> np.ndarray:
    """The masks whose points ``at_median_depth`` may move: mask ``i`` of ``masks`` owns depths
    ``z[bounds[i]:bounds[i + 1]]`` and has depth variance ``var_z[i]``. Left out: masks of fewer
    than 4 points, and masks whose depths span at most ``units`` noise stds (the median lies
    between the nearest and the farthest point, so no point can be further from it): at 500
    proposals a frame that is ~70 % of them, whose medians need not be taken one mask at a time."""
    n = bounds[masks + 1] - bounds[masks]
    big = masks[n >= 4]
    if big.size == 0:
        return big
    # Each big mask's [start, end) as consecutive reduceat indices; the odd results are discarded.
    idx = np.stack([bounds[big], bounds[big + 1]], axis=1).ravel()
    zz = np.append(z, z.dtype.type(0))  # an end index may be len(z)
    span = np.maximum.reduceat(zz, idx)[::2] - np.minimum.reduceat(zz, idx)[::2]
    return big[~(span <= units * np.sqrt(var_z[big]))]


def _inliers(points: np.ndarray, median: np.ndarray, bounds: np.ndarray, masks: np.ndarray,
             max_mahalanobis: float) -> np.ndarray:
    """Which points lie within ``max_mahalanobis`` of their mask's median under the mask's
    own point covariance; each mask ``i`` of ``masks`` owns ``points[bounds[i]:bounds[i + 1]]``
    and ``median`` is given per point. Masks with fewer than 4 points keep them all."""
    diff = points - median
    big = masks[bounds[masks + 1] - bounds[masks] >= 4]
    if big.size == 0:
        return np.ones(len(points), bool)
    cov = np.stack([diff[bounds[i]:bounds[i + 1]].T @ diff[bounds[i]:bounds[i + 1]] for i in big])
    cov = cov / (bounds[big + 1] - bounds[big])[:, None, None] + 1e-6 * np.eye(3)
    y = np.zeros_like(diff)  # stays 0 (kept) for points of small masks
    for i, c in zip(big, np.linalg.inv(cov)):
        y[bounds[i]:bounds[i + 1]] = diff[bounds[i]:bounds[i + 1]] @ c
    p = y * diff
    m2 = p[:, 0] + p[:, 1] + p[:, 2]  # the row sum, added in the order ``sum(axis=1)`` adds
    return m2 <= max_mahalanobis**2


def _observations(proposals, t_ns, position, size, velocity, n_points, calib, ground, cfg) -> Observations:
    cov = triangulation_covariance(position, calib, cfg)
    if ground.ok:
        foot = project_to_ground(position, ground)
    else:
        foot = np.full_like(position, np.nan)
    vel_cov = cfg.velocity_noise_factor * cov
    return Observations(proposals, t_ns, position, cov, foot, velocity, vel_cov, size, n_points)


def localise_detections(proposals: Proposals, calib: StereoCalib, t_ns: int, cfg: LocaliseConfig) -> Observations:
    """Observations from proposals that carry a 3D box (centre ``position``, ``size`` w, h, l)."""
    if proposals.position is None or proposals.size is None:
        raise ValueError("detections-only localisation needs proposals with 3D position and size")
    position = np.asarray(proposals.position, np.float64)
    size = np.minimum(np.asarray(proposals.size, np.float64), cfg.max_size_m)
    n = len(proposals)
    cov = triangulation_covariance(position, calib, cfg)
    foot = position.copy()
    foot[:, 1] += size[:, 1] / 2.0  # y points down: the bottom centre lies half a height below
    velocity = np.full((n, 3), np.nan)
    return Observations(proposals, t_ns, position, cov, foot, velocity, cfg.velocity_noise_factor * cov, size,
                        np.where(np.isfinite(position).all(axis=1), cfg.min_points, 0))


FILTER_CLAUSES = ("box_area", "objectness", "no_3d", "abs_x", "z_range", "height")  # the filter's tests, in order


def filter_clauses(obs: Observations, ground: GroundPlane | None, cfg: ProposalFilterConfig,
                   stereo_noise: bool = True) -> dict[str, np.ndarray]:
    """Per clause of the geometric filter (``FILTER_CLAUSES``), which observations pass it.

    The limits are on the object's true place. With ``stereo_noise`` an observation is
    dropped only when it lies beyond a limit by more than ``cfg.noise_sigmas`` of its own
    standard deviations (its covariance is stereo triangulation's): |X| and Z are tested at
    the nearest point of the footpoint's viewing ray within that many disparity stds —
    depth Z / (1 + k·σ_Z / Z), i.e. disparity d + k·σ_d — and the height above the plane as
    h ± k·√(nᵀΣn). Without it (positions that do not come from stereo, e.g. LiDAR 3D
    boxes in detections-only mode) the limits apply to the estimate as it is.

    A clause that cannot be evaluated for a row (no footpoint) passes there: ``no_3d``
    speaks for it. The height clause passes everywhere when no plane is known.
    """
    b = obs.proposals.boxes
    area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    foot = obs.footpoint
    finite = np.isfinite(foot).all(axis=1)
    ok = {"box_area": area >= cfg.min_box_area_px, "objectness": obs.proposals.objectness >= cfg.min_objectness,
          "no_3d": finite}
    k = cfg.noise_sigmas if stereo_noise else 0.0
    with np.errstate(invalid="ignore", divide="ignore"):
        sigma_z = np.sqrt(obs.covariance[:, 2, 2]) if k > 0 else np.zeros(len(obs))
        near = foot / (1.0 + k * sigma_z / obs.position[:, 2])[:, None] if k > 0 else foot
        ok["abs_x"] = ~finite | (np.abs(near[:, 0]) <= cfg.max_abs_x_m)
        ok["z_range"] = ~finite | ((foot[:, 2] > cfg.z_range_m[0]) & (near[:, 2] < cfg.z_range_m[1]))
        if ground is not None and ground.ok:
            height = ground.height(obs.position)
            n = ground.normal
            tol = k * np.sqrt(np.einsum("i,nij,j->n", n, obs.covariance, n)) if k > 0 else 0.0
            ok["height"] = ~finite | ((height + tol > cfg.height_range_m[0]) & (height - tol < cfg.height_range_m[1]))
        else:
            ok["height"] = np.ones(len(obs), bool)
    return ok


def geometric_filter(obs: Observations, ground: GroundPlane | None, cfg: ProposalFilterConfig,
                     stereo_noise: bool = True) -> np.ndarray:
    """Indices of observations that pass REFERENCE.md's proposal filter, best objectness first.

    Dropped: box area < 100 px²; no 3D position; footpoint |X| > 50 m or Z outside
    (0, 60) m; height above the ground outside (0.1, 5.0) m (when a plane is known) —
    with ``stereo_noise``, only where the estimate lies beyond a limit by more than its
    stereo noise allows (``filter_clauses``). At most 300 are kept.
    """
    keep = np.logical_and.reduce(list(filter_clauses(obs, ground, cfg, stereo_noise).values()))
    idx = np.flatnonzero(keep)
    order = np.argsort(-obs.proposals.objectness[idx], kind="stable")
    return idx[order][: cfg.max_proposals]
