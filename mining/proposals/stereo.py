"""The weight-free ``stereo`` proposer: object candidates from the stereo point cloud above
the ground plane, of any shape and kind (cars as well as bins, cones, crates, debris,
animals), with objectness from geometric cues and no classes (posterior None).

Per frame:

1. **Points above the ground.** Every ``pixel_step``-th pixel with valid depth is lifted to
   3D; points between the ground cut and ``max_height_m`` above the ground plane, nearer
   than ``max_depth_m``, are kept. The ground cut rises with the height noise of a stereo
   point, σ_h = |n·ray|·σ_z, so that far road surface does not pass as obstacles.
2. **Polar bird's-eye grid.** Points fall into cells (viewing direction = image column bin,
   range). Range cells are ``range_cell_m`` deep near the camera and ``disparity_cell_px``
   of disparity deep farther out, so stereo noise spreads an object over about the same
   number of cells at any distance. A cell holds the *visible vertical surface* of its
   points in metres (each sample stands for ``step·z/fy`` metres of one image column);
   normalising this way makes a far object as dense as a near one, although it has far
   fewer points.
3. **Multi-scale clusters.** Candidate point sets come from three groupings, each at
   several settings; fine ones split touching objects, coarse ones join objects broken by
   stereo holes, and all hypotheses are proposed (proposals live on recall; tubes and
   co-selection sort out the duplicates):
   * connected components of occupied grid cells per ``scales`` entry (density threshold,
     dilation; dilation only links cells, clusters keep their own cells);
   * the same within bands of cell top height (``height_band_m``, two offsets): a car
     parked before a taller hedge at the same range parts from it (on KITTI 0005 this
     alone lifts car recall from 0.33 to 0.77);
   * image regions of object-height pixels cut where neighbouring disparities jump
     (``image_jumps_px``): objects before a background at another depth.
   Identical point sets are proposed once; footprints longer than ``max_extent_m`` (walls,
   hedges, facades) are dropped — such structures are not objects. Near-duplicates go by
   NMS on the point boxes, and masks are built for at most ``mask_budget·max_proposals``
   clusters, best cheap cues first.
4. **Masks.** A cluster's mask is the pixels of its points, grown down over points within
   its depth range that lie between ``grow_min_height_m`` and the ground cut (its feet; as
   many rows as the cut removed at that depth), closed in the image to fill stereo holes,
   trimmed by ``left_trim_px`` at its left edges (left-reference stereo spreads a
   foreground disparity over the background it occludes, to its left), and run-length encoded from its crop (``mining.masks.crop_rle``). ``position`` is the
   median of the cluster's points (camera metres), ``size`` = (width across x, top height
   above the ground, length along z less the spread stereo noise alone makes).
   Small masks (≤ ``refine_max_area_px``) are then moved to the object's outline in the image
   (``refine``, issue 29): a colour model seeded by the mask (histograms of the mask vs a ring
   around it, :func:`refine_by_colour`) or OpenCV's GrabCut (:func:`refine_with_image`), in
   :func:`refine_candidates`. With ``low_min_height_m`` > 0, low points whose surface stands up
   from the ground (:func:`low_standing`) join the image-region grouping; with
   ``support_ref_depth_m`` > 0 the support cue counts visible surface instead of points.
5. **Objectness** = sigmoid(bias + Σ wₖ·cueₖ), every cue in [0, 1] with higher meaning
   more object-like and every weight ≥ 0, so objectness is monotone non-decreasing in
   each cue (:func:`objectness_from_cues`). Cues, in ``CUES`` order: border contrast (the
   fraction of the mask's border ring that is background: ground, no depth, or a depth
   jump — the object stands free), fill (mask area / box area), plausible footprint,
   plausible top height, point support.

Each step is a function below: :func:`points_above_ground` (1), :func:`polar_grid` (2),
:func:`cluster_points` (3), :func:`cluster_stats`, :func:`first_masks`, :func:`build_mask` and
:func:`refine_candidates` (4), :func:`score_and_encode` (5). ``StereoProposer.propose`` runs them and returns the
proposals with their cues and step timings (:class:`StereoResult`); calling the proposer
returns the proposals alone, the shape every proposer has.

A frame whose ground plane failed gets no proposals: without the ground there is no
"above the ground" and inventing a plane would be a silent substitute. The reason is
returned in ``StereoResult.reason`` (the caller also has ``geometry.ground.reason``).
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from mining.boxes import nms_keep
from mining.errors import InputError
from mining.masks import crop_rle
from mining.proposals.config import ProposalConfig
from mining.proposals.stereo_config import StereoProposerConfig
from mining.types import FrameGeometry, GroundPlane, Proposals, StereoCalib, StereoFrame

PROPOSER_NAME = "stereo"
CUES = ("contrast", "fill", "extent", "top", "support")


def empty_proposals(frame: int) -> Proposals:
    return Proposals(frame=frame, rles=[], boxes=np.zeros((0, 4), np.float32), objectness=np.zeros(0, np.float32),
                     posterior=None, proposer=[], position=np.zeros((0, 3), np.float32),
                     size=np.zeros((0, 3), np.float32))


def objectness_from_cues(cues: np.ndarray, cfg: StereoProposerConfig) -> np.ndarray:
    """(N, 5) cues in ``CUES`` order, each in [0, 1] → (N,) objectness in [0, 1], monotone in each cue."""
    w = np.array([cfg.w_contrast, cfg.w_fill, cfg.w_extent, cfg.w_top, cfg.w_support])
    if (w < 0).any():
        raise ValueError("stereo objectness weights must be ≥ 0 (objectness is monotone in its cues)")
    logit = cfg.bias + np.clip(cues, 0.0, 1.0) @ w
    return (1.0 / (1.0 + np.exp(-logit))).astype(np.float32)


def range_index(z: np.ndarray, bf: float, cfg: StereoProposerConfig) -> np.ndarray:
    """Continuous range coordinate: metric cells near, disparity cells where those are coarser."""
    c, k = cfg.range_cell_m, cfg.disparity_cell_px
    z0 = math.sqrt(c * bf / k)  # the depth where a disparity cell is c metres deep
    near = z / c
    far = z0 / c + (bf / z0 - bf / np.maximum(z, 1e-6)) / k
    return np.where(z <= z0, near, far)


def _plausible(value: np.ndarray, lo: float, hi: float, zero_at: float) -> np.ndarray:
    """1 inside [lo, hi], falling linearly to 0 at 0 (below lo) and at zero_at (above hi)."""
    below = np.clip(value / lo, 0.0, 1.0) if lo > 0 else np.ones_like(value)
    above = np.clip((zero_at - value) / (zero_at - hi), 0.0, 1.0)
    return np.minimum(below, above)


def _collect(point_label: np.ndarray, n_labels: int, min_points: int, seen: set[bytes],
             clusters: list[np.ndarray]) -> None:
    """Append the point sets of labels 1..n_labels (label 0 = none) not seen before."""
    order = np.argsort(point_label, kind="stable")  # stable: each set comes out in point order
    bounds = np.searchsorted(point_label[order], np.arange(1, n_labels + 2))
    for a, b in zip(bounds[:-1], bounds[1:]):
        if b - a < min_points:
            continue
        idx = order[a:b]
        key = idx.tobytes()
        if key not in seen:
            seen.add(key)
            clusters.append(idx)


@dataclass
class StereoResult:
    """One frame's stereo proposals and what explains them."""

    proposals: Proposals
    cues: np.ndarray  # (N, 5) float32, the proposals' cues in ``CUES`` order (objectness is their function)
    reason: str  # why the frame has no proposals (no ground plane); empty otherwise
    timings_ms: dict[str, float]  # per step: points, cluster, stats, masks, encode (those that ran)


def _no_cues() -> np.ndarray:
    return np.zeros((0, len(CUES)), np.float32)


@dataclass
class SamplePoints:
    """Step 1: the sample grid (every ``step``-th pixel) and its points above the ground."""

    step: int
    z: np.ndarray  # (hs, ws) float32 depth, NaN where invalid
    x: np.ndarray  # (hs, ws) camera x
    y: np.ndarray  # (hs, ws) camera y
    low: np.ndarray  # (hs, ws) bool: ground, or no depth
    growable: np.ndarray  # (hs, ws) bool: masks may grow over these (an object's feet)
    keep: np.ndarray  # (hs, ws) bool: object-height points
    keep_low: np.ndarray  # (hs, ws) bool: object-height points and low standing surfaces (``low_min_height_m``)
    pv: np.ndarray  # (P,) sample rows of the kept points
    pu: np.ndarray  # (P,) sample columns
    pz: np.ndarray  # (P,) depth
    ph: np.ndarray  # (P,) height above the ground
    px: np.ndarray  # (P,) camera x
    high: np.ndarray  # (P,) bool: object-height points (the rest are low standing surfaces, image regions only)


def points_above_ground(depth: np.ndarray, ground: GroundPlane, calib: StereoCalib,
                        cfg: StereoProposerConfig) -> SamplePoints:
    """Step 1: points above the ground, on the sample grid (every s-th pixel)."""
    s, bf = cfg.pixel_step, calib.bf
    z = depth[::s, ::s].astype(np.float64)
    hs, ws = z.shape
    u = (np.arange(ws) * s)[None, :]
    v = (np.arange(hs) * s)[:, None]
    n, d0 = ground.normal, ground.d
    valid = np.isfinite(z) & (z > 0)
    z = np.where(valid, z, np.nan).astype(np.float32)
    x = (u - calib.cx) * z / calib.fx
    y = (v - calib.cy) * z / calib.fy
    h = n[0] * x + n[1] * y + n[2] * z + d0
    # Height std from depth noise: along the viewing ray h changes by (h − d0)/z per metre.
    sigma_z = z * z * cfg.disparity_noise_px / bf
    ground_cut = cfg.min_height_m + cfg.height_noise_sigmas * np.abs(h - d0) / z * sigma_z
    low = ~(h >= ground_cut)  # ground, or no depth (NaN compares False)
    # Masks may grow over points down to a lower cut: the feet of an object lie below ground_cut.
    growable = (h >= cfg.grow_min_height_m + np.abs(h - d0) / z * sigma_z) & (h < cfg.max_height_m)
    keep = valid & ~low & (h < cfg.max_height_m) & (z < cfg.max_depth_m)
    keep_low = keep | low_standing(z, h, sigma_z, d0, bf, s, calib, cfg) if cfg.low_min_height_m > 0 else keep
    pv, pu = np.nonzero(keep_low)
    pz, ph, px = z[pv, pu], h[pv, pu], x[pv, pu]
    return SamplePoints(s, z, x, y, low, growable, keep, keep_low, pv, pu, pz, ph, px, keep[pv, pu])


def low_standing(z: np.ndarray, h: np.ndarray, sigma_z: np.ndarray, d0: float, bf: float, s: int,
                 calib: StereoCalib, cfg: StereoProposerConfig) -> np.ndarray:
    """Low points (under the ground cut, above ``low_min_height_m`` + 1 height std) on a surface
    that stands up from the ground: down the image, the ground's disparity grows by
    bf·|n_y|/(−d0)·step/fy per sample row (a plane's disparity is linear in the pixel), a
    standing face's stays nearly constant. A point is standing where the disparity grows by
    less than ``low_standing_ratio`` of the ground's rate to the row above or below it
    (a tyre, a kerb-side box, a fallen load; a plate lying flat is ground to stereo)."""
    disparity = bf / z
    ground_rate = bf * s / (calib.fy * abs(d0)) if d0 else np.inf  # disparity per sample row on the ground (n ≈ −y)
    # the smaller one-sided step: a face two sample rows tall already has one neighbour on it
    step = np.abs(np.diff(disparity, axis=0))
    grad = np.full(z.shape, np.nan, np.float32)
    grad[1:-1] = np.fmin(step[1:], step[:-1])
    band = (h >= cfg.low_min_height_m + np.abs(h - d0) / z * sigma_z) & (h < cfg.max_height_m) & (z < cfg.max_depth_m)
    return band & (np.abs(grad) < cfg.low_standing_ratio * ground_rate)


@dataclass
class PolarGrid:
    """Step 2: the polar bird's-eye grid of visible vertical surface per cell."""

    cell: np.ndarray  # (P,) flat cell index of each kept point
    surface: np.ndarray  # (n_rows, n_cols) metres of visible vertical surface


def polar_grid(pts: SamplePoints, calib: StereoCalib, cfg: StereoProposerConfig) -> PolarGrid:
    """Step 2: kept points → cells (image column bin, range), each holding its visible surface."""
    s, bf, W = pts.step, calib.bf, calib.width
    n_cols = -(-W // cfg.column_px)
    n_rows = int(range_index(np.array([cfg.max_depth_m]), bf, cfg)[0]) + 1
    rng = np.minimum(range_index(pts.pz, bf, cfg).astype(np.int64), n_rows - 1)
    cell = rng * n_cols + (pts.pu * s) // cfg.column_px
    surface = np.bincount(cell, weights=pts.high * s * s * pts.pz / (calib.fy * cfg.column_px),
                          minlength=n_rows * n_cols)
    return PolarGrid(cell, surface.reshape(n_rows, n_cols))


def cluster_points(pts: SamplePoints, grid: PolarGrid, bf: float, cfg: StereoProposerConfig) -> list[np.ndarray]:
    """Step 3: candidate point sets (indices into the kept points) of the three groupings,
    each distinct set once, in the order the groupings find them."""
    clusters: list[np.ndarray] = []
    seen: set[bytes] = set()
    _grid_components(pts, grid, cfg, seen, clusters)
    if cfg.height_band_m > 0:
        _height_band_components(pts, grid, cfg, seen, clusters)
    _image_regions(pts, bf, cfg, seen, clusters)
    return clusters


def _grid_components(pts: SamplePoints, grid: PolarGrid, cfg: StereoProposerConfig, seen: set[bytes], clusters: list[np.ndarray]) -> None:
    """Connected components of occupied cells per ``scales`` entry (dilation only links cells)."""
    for mult, dr, dc in cfg.scales:
        occupied = (grid.surface >= cfg.min_density_m * mult).astype(np.uint8)
        links = cv2.dilate(occupied, np.ones((2 * dr + 1, 2 * dc + 1), np.uint8)) if dr or dc else occupied
        _, labels = cv2.connectedComponents(links, connectivity=8)
        labels[occupied == 0] = 0
        _collect(labels.ravel()[grid.cell] * pts.high, labels.max(), cfg.min_points, seen, clusters)


def _height_band_components(pts: SamplePoints, grid: PolarGrid, cfg: StereoProposerConfig, seen: set[bytes],
                            clusters: list[np.ndarray]) -> None:
    """Components within bands of cell top height: adjacent cells whose tops differ (a car
    before a taller bush) part."""
    n_rows, n_cols = grid.surface.shape
    top = np.zeros(n_rows * n_cols)
    np.maximum.at(top, grid.cell, np.where(pts.high, pts.ph, 0.0))
    top = top.reshape(n_rows, n_cols)
    occupied = grid.surface >= cfg.min_density_m
    for offset in (0.0, 0.5 * cfg.height_band_m):
        band = np.floor((top + offset) / cfg.height_band_m).astype(np.int32)
        labels = np.zeros((n_rows, n_cols), np.int32)
        n_labels = 0
        for b in np.unique(band[occupied]):
            n_b, lab_b = cv2.connectedComponents((occupied & (band == b)).astype(np.uint8), connectivity=8)
            labels[lab_b > 0] = lab_b[lab_b > 0] + n_labels
            n_labels += n_b - 1
        _collect(labels.ravel()[grid.cell] * pts.high, n_labels, cfg.min_points, seen, clusters)


def _image_regions(pts: SamplePoints, bf: float, cfg: StereoProposerConfig, seen: set[bytes],
                   clusters: list[np.ndarray]) -> None:
    """The same in the image: regions of object-height points cut where the depth jumps."""
    hs, ws = pts.z.shape
    disparity = bf / pts.z
    for jump_px in cfg.image_jumps_px:
        for span in range(1, cfg.jump_span + 1):
            cut = np.zeros((hs, ws), bool)
            gap = np.maximum(jump_px, cfg.border_gap_m * disparity * disparity / bf)
            # a jump over ``span`` samples: SGBM smears a depth edge over a few pixels
            dx = np.abs(disparity[:, span:] - disparity[:, :-span]) > gap[:, span:]
            dy = np.abs(disparity[span:, :] - disparity[:-span, :]) > gap[span:, :]
            cut[:, span:] |= dx
            cut[span:, :] |= dy
            for keep in (pts.keep, pts.keep_low) if cfg.low_min_height_m > 0 else (pts.keep,):
                _, labels = cv2.connectedComponents((keep & ~cut).astype(np.uint8), connectivity=4)
                _collect(labels[pts.pv, pts.pu], labels.max(), cfg.min_points, seen, clusters)


class ClusterStats(NamedTuple):
    """Cheap 3D statistics of one cluster (order statistics of at most ~``stats_points`` points)."""

    idx: np.ndarray  # the cluster's kept points
    sub: np.ndarray  # the subsample the statistics come from
    q: np.ndarray  # positions of the 5 %, 50 %, 95 % quantiles in the sorted subsample
    zq: np.ndarray  # depth quantiles
    xq: np.ndarray  # camera-x quantiles
    top: float  # 95 % height above the ground
    width: float  # across x, metres
    length: float  # along z less the spread stereo noise alone makes, metres
    box: tuple  # sample-grid box of the points (x2, y2 exclusive)
    support: float  # the support cue's raw value: points, or their visible surface in points at ``support_ref_depth_m``


def cluster_stats(clusters: list[np.ndarray], pts: SamplePoints, bf: float,
                  cfg: StereoProposerConfig) -> list[ClusterStats]:
    """Step 4a: statistics per cluster; footprints longer than ``max_extent_m`` are dropped."""
    stats = []
    for idx in clusters:
        sub = idx[:: max(1, idx.size // cfg.stats_points)]
        zs, xs_, hs_ = np.sort(pts.pz[sub]), np.sort(pts.px[sub]), np.sort(pts.ph[sub])
        q = (np.array([0.05, 0.5, 0.95]) * (sub.size - 1)).round().astype(int)
        zq, xq = zs[q], xs_[q]
        spread = 2.0 * zq[1] ** 2 * cfg.disparity_noise_px / bf  # range spread stereo noise alone makes
        length = max(0.0, zq[2] - zq[0] - spread)
        width = xq[2] - xq[0]
        if max(width, length) > cfg.max_extent_m:
            continue
        cv_, cu_ = pts.pv[idx], pts.pu[idx]
        box = (cu_.min(), cv_.min(), cu_.max() + 1, cv_.max() + 1)
        # A far object has fewer points for the same surface: with a reference depth, support
        # counts its visible surface (each point stands for (step·z/f)² m²) in points at that depth.
        support = float(idx.size) if cfg.support_ref_depth_m <= 0 else \
            float(np.sum(np.maximum(pts.pz[idx], cfg.support_ref_depth_m) ** 2)) / cfg.support_ref_depth_m ** 2
        stats.append(ClusterStats(idx, sub, q, zq, xq, float(hs_[q[2]]), width, length, box, support))
    return stats


def first_masks(stats: list[ClusterStats], cfg: StereoProposerConfig) -> np.ndarray:
    """Step 4b: which clusters get a mask. Near-duplicates across scales go before their
    masks are built: NMS on the point boxes, ranked by the cues known so far (border
    contrast taken as 1/2 for all); at most ``mask_budget·max_proposals``."""
    pre = np.array([(0.5, st.idx.size / ((st.box[2] - st.box[0]) * (st.box[3] - st.box[1])),
                     max(st.width, st.length), st.top, st.support) for st in stats])
    return nms_keep(np.array([st.box for st in stats], np.float64), objectness_from_cues(cues_from_raw(pre, cfg), cfg),
                    cfg.nms_iou, int(cfg.mask_budget * cfg.max_proposals))


class MaskKernels(NamedTuple):
    """The image operations' kernels, the same for every cluster of a frame."""

    close: np.ndarray  # closing that fills stereo holes
    ring: np.ndarray  # the border ring's width
    grow: np.ndarray  # one growth step: from the row above, one column aside (the top row of a 3 × 3 window)
    pad: int  # crop margin around a cluster's points, samples
    trim: int  # left-edge trim, samples


def mask_kernels(cfg: StereoProposerConfig) -> MaskKernels:
    """The kernels for the configured sample step."""
    s = cfg.pixel_step
    k_close = max(1, cfg.mask_close_px // s) | 1
    close_kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k_close, k_close))
    ring_kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    pad = k_close // 2 + 3 + cfg.grow_steps
    grow = np.zeros((3, 3), np.uint8)
    grow[0] = 1  # anchored at the centre: a pixel takes the row above's three, so no shifted copy is made
    return MaskKernels(close_kernel, ring_kernel, grow, pad, cfg.left_trim_px // s)


class Candidate(NamedTuple):
    """One cluster's mask and the values its proposal row needs."""

    crop: np.ndarray  # (h, w) bool full-resolution mask crop
    x0: int  # the crop's top-left pixel
    y0: int
    box: tuple[int, int, int, int]  # x1, y1, x2, y2 pixels (x2, y2 exclusive)
    raw_cues: tuple  # (contrast, fill, extent m, top m, points), see :func:`cues_from_raw`
    position: tuple  # camera metres
    size: tuple  # width, top height, length metres


def build_mask(st: ClusterStats, pts: SamplePoints, kernels: MaskKernels, calib: StereoCalib, d0: float,
               cfg: StereoProposerConfig) -> Candidate:
    """Step 4c: a cluster's mask (grown over its feet, closed, left-trimmed) and its
    remaining cues (border contrast, fill)."""
    s, bf, H, W = pts.step, calib.bf, calib.height, calib.width
    hs, ws = pts.z.shape
    pad, trim = kernels.pad, kernels.trim
    idx, sub, q, zq, xq, top, width, length, _, support = st
    cv_, cu_, cz = pts.pv[idx], pts.pu[idx], pts.pz[idx]
    r0, c0 = max(0, cv_.min() - pad), max(0, cu_.min() - pad)
    r1, c1 = min(hs, cv_.max() + pad + 1), min(ws, cu_.max() + pad + 1)
    points = np.zeros((r1 - r0, c1 - c0), np.uint8)
    points[cv_ - r0, cu_ - c0] = 1
    zobj = np.zeros(points.shape, np.float32)
    zobj[cv_ - r0, cu_ - c0] = cz
    # Growth downwards (and diagonally) over points within the cluster's depth range: its
    # feet, below the ground cut, as many rows as the ground cut removed at this depth.
    zc = pts.z[r0:r1, c0:c1]
    noise_z = zq[1] ** 2 * cfg.disparity_noise_px / bf
    grow_gap, ring_gap = max(cfg.border_gap_m, noise_z), max(cfg.border_gap_m, 3.0 * noise_z)
    cut_gap = (cfg.min_height_m - cfg.grow_min_height_m
               + cfg.height_noise_sigmas * d0 * zq[1] * cfg.disparity_noise_px / bf)
    steps = min(cfg.grow_steps, math.ceil(cut_gap * calib.fy / (zq[1] * s)))
    if steps > 0:
        ok = (pts.growable[r0:r1, c0:c1] & (zc >= zq[0] - grow_gap) & (zc <= zq[2] + grow_gap)).astype(np.uint8)
        n = cv2.countNonZero(points)
        for _ in range(steps):
            # points ∪ (below ∩ ok): what the row above reaches, one column aside, where growth may go
            points = cv2.bitwise_or(points, cv2.bitwise_and(cv2.dilate(points, kernels.grow), ok))
            if (m := cv2.countNonZero(points)) == n:
                break
            n = m
        grown = (points > 0) & (zobj == 0)
        zobj[grown] = zc[grown]
    mask = cv2.morphologyEx(points, cv2.MORPH_CLOSE, kernels.close)
    if trim > 0:  # left-edge fattening: keep pixels whose left neighbours are in the mask too
        kept = mask.copy()
        for k in range(1, trim + 1):
            kept[:, k:] &= mask[:, :-k]
            kept[:, :k] = 0
        mask = kept if kept.any() else mask
    # Border ring: background where there is no object-height point at the object's depth.
    znear = cv2.dilate(zobj, kernels.ring)
    ring = (cv2.dilate(mask, kernels.ring) > 0) & (mask == 0) & (znear > 0)
    rz = zc[ring]
    rlow = pts.low[r0:r1, c0:c1][ring]
    jump = ~(np.abs(rz - znear[ring]) <= ring_gap)  # NaN depth counts as a jump
    contrast = float((rlow | jump).mean()) if rz.size else 1.0
    rows = np.nonzero(mask.any(axis=1))[0]
    cols = np.nonzero(mask.any(axis=0))[0]
    mask = mask[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
    fill = float(np.count_nonzero(mask)) / mask.size
    # Full-resolution crop: each sample stands for an s × s block.
    y0, x0 = (r0 + int(rows[0])) * s, (c0 + int(cols[0])) * s
    h, w = mask.shape  # mask holds 0 / 1 (morphology of 0 / 1), so its bytes are bools
    crop = cv2.resize(mask, (w * s, h * s), interpolation=cv2.INTER_NEAREST_EXACT).view(bool)[: H - y0, : W - x0]
    return Candidate(crop, x0, y0, (x0, y0, x0 + crop.shape[1], y0 + crop.shape[0]),
                     (contrast, fill, max(width, length), top, support),
                     (xq[1], float(np.sort(pts.y[pts.pv[sub], pts.pu[sub]])[q[1]]), zq[1]), (width, top, length))


def refine_with_image(crop: np.ndarray, x0: int, y0: int, image: np.ndarray,
                      cfg: StereoProposerConfig) -> tuple[np.ndarray, int, int]:
    """A stereo mask moved to the object's outline in the image: OpenCV's GrabCut (colour
    GMMs of object and background, a graph cut along image edges) initialised from the
    mask. The mask is *probable* object, a band of ``refine_band_px`` around it *probable*
    background (what stereo bleeding may have missed or added lies in mask and band), the
    rest of the crop certain background. Returns the refined (crop, x0, y0); the stereo
    mask itself where the cut keeps less than ``refine_min_keep`` of it or adds more than
    its own area (a colour model that failed, not an outline)."""
    H, W = image.shape[:2]
    b = cfg.refine_band_px
    h, w = crop.shape
    X0, Y0 = max(0, x0 - 2 * b), max(0, y0 - 2 * b)
    X1, Y1 = min(W, x0 + w + 2 * b), min(H, y0 + h + 2 * b)
    m = np.zeros((Y1 - Y0, X1 - X0), np.uint8)
    m[y0 - Y0: y0 - Y0 + h, x0 - X0: x0 - X0 + w] = crop
    band = cv2.dilate(m, _disc(b)) > 0
    gc = np.full(m.shape, cv2.GC_BGD, np.uint8)
    gc[band] = cv2.GC_PR_BGD
    gc[m > 0] = cv2.GC_PR_FGD
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    try:
        cv2.grabCut(np.ascontiguousarray(image[Y0:Y1, X0:X1]), gc, None, bgd, fgd, cfg.refine_iterations,
                    cv2.GC_INIT_WITH_MASK)
    except cv2.error:  # a colour model that cannot be fit (too few pixels of one side)
        return crop, x0, y0
    out = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
    n_in, n_out = int(m.sum()), int(out.sum())
    kept = int((out & (m > 0)).sum())
    if kept < cfg.refine_min_keep * n_in or n_out > 2 * n_in:
        return crop, x0, y0
    rows, cols = np.nonzero(out.any(axis=1))[0], np.nonzero(out.any(axis=0))[0]
    out = out[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
    return out, X0 + int(cols[0]), Y0 + int(rows[0])


def refine_candidates(candidates: list[Candidate], image: np.ndarray, cfg: StereoProposerConfig) -> list[Candidate]:
    """Step 4d: small masks (≤ ``refine_max_area_px``) moved to the object's outline in the
    image (``refine``: :func:`refine_by_colour` or :func:`refine_with_image`), in place of the
    stereo mask or, with ``refine_keep_stereo``, beside it (both hypotheses proposed). The
    cues and 3D rows stay the stereo cluster's."""
    if cfg.refine == "none":
        return candidates
    bins = colour_bins(image, cfg.refine_colour_bits) if cfg.refine == "colour" else image
    refine = refine_by_colour if cfg.refine == "colour" else refine_with_image
    out = []
    for c in candidates:
        area = int(c.crop.sum())
        if 0 < area <= cfg.refine_max_area_px:
            crop, x0, y0 = refine(c.crop, c.x0, c.y0, bins, cfg)
            if crop is not c.crop:
                if cfg.refine_keep_stereo:
                    out.append(c)
                c = c._replace(crop=crop, x0=x0, y0=y0, box=(x0, y0, x0 + crop.shape[1], y0 + crop.shape[0]))
        out.append(c)
    return out


@functools.lru_cache(maxsize=8)
def _disc(radius: int) -> np.ndarray:
    """An elliptic structuring element of this radius (made once: the refinement runs per mask)."""
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def colour_bins(image: np.ndarray, bits: int) -> np.ndarray:
    """(H, W) colour bin of each pixel (uint16, int32 past 5 bits): the top ``bits`` bits of each RGB channel."""
    q = image >> (8 - bits)  # uint8; the bins fit 16 bits for bits ≤ 5 (half the memory traffic of int32)
    dtype = np.uint16 if bits <= 5 else np.int32
    return (q[..., 0].astype(dtype) << (2 * bits)) | (q[..., 1].astype(dtype) << bits) | q[..., 2]


def refine_by_colour(crop: np.ndarray, x0: int, y0: int, bins: np.ndarray,
                     cfg: StereoProposerConfig) -> tuple[np.ndarray, int, int]:
    """A stereo mask moved to the object's outline by a colour model seeded by the mask:
    colour histograms of the mask and of a ring around it (``refine_band_px`` to twice that
    outside), and each pixel of the mask and its band goes to the side whose histogram
    holds its colour more often (Bayes with equal priors, add-one smoothing). ``bins`` is
    :func:`colour_bins` of the frame. The stereo mask stays where the colours do not tell
    object from background (less than ``refine_min_keep`` of it kept, or more than twice its
    area), cheap enough (a bincount per mask) to run on every small mask."""
    H, W = bins.shape
    b = cfg.refine_band_px
    h, w = crop.shape
    X0, Y0 = max(0, x0 - 2 * b), max(0, y0 - 2 * b)
    X1, Y1 = min(W, x0 + w + 2 * b), min(H, y0 + h + 2 * b)
    m = np.zeros((Y1 - Y0, X1 - X0), np.uint8)
    m[y0 - Y0: y0 - Y0 + h, x0 - X0: x0 - X0 + w] = crop
    near = cv2.dilate(m, _disc(b)) > 0
    far = cv2.dilate(m, _disc(2 * b)) > 0
    c = bins[Y0:Y1, X0:X1]
    n_bins = 1 << (3 * cfg.refine_colour_bits)
    inside = m > 0
    ring = far & ~near
    if not ring.any():
        return crop, x0, y0
    hf = np.bincount(c[inside], minlength=n_bins) + 1.0
    hb = np.bincount(c[ring], minlength=n_bins) + 1.0
    fg = (hf / hf.sum() > hb / hb.sum())[c] & near
    fg = cv2.medianBlur(fg.astype(np.uint8), 3) > 0  # single pixels of a shared colour are noise
    n_in, n_out = int(inside.sum()), int(fg.sum())
    if (fg & inside).sum() < cfg.refine_min_keep * n_in or n_out > 2 * n_in or n_out == 0:
        return crop, x0, y0
    rows, cols = np.nonzero(fg.any(axis=1))[0], np.nonzero(fg.any(axis=0))[0]
    fg = fg[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
    return fg, X0 + int(cols[0]), Y0 + int(rows[0])


def cues_from_raw(raw: np.ndarray, cfg: StereoProposerConfig) -> np.ndarray:
    """Raw (contrast, fill, extent m, top m, points) → the five cues in [0, 1], higher = more object-like."""
    return np.column_stack([
        np.clip(raw[:, 0], 0.0, 1.0),
        np.clip(raw[:, 1], 0.0, 1.0),
        _plausible(raw[:, 2], 0.0, cfg.plausible_extent_m, cfg.max_extent_m),
        _plausible(raw[:, 3], cfg.plausible_top_m[0], cfg.plausible_top_m[1], cfg.max_height_m),
        np.clip(np.log(raw[:, 4]) / math.log(cfg.support_points), 0.0, 1.0),
    ])


def score_and_encode(frame: int, candidates: list[Candidate], calib: StereoCalib,
                     cfg: StereoProposerConfig) -> tuple[Proposals, np.ndarray]:
    """Step 5: objectness from the cues, the final NMS, RLE of the survivors; (proposals, their cues)."""
    cue = cues_from_raw(np.asarray([c.raw_cues for c in candidates], np.float64), cfg)
    score = objectness_from_cues(cue, cfg)
    boxes_a = np.asarray([c.box for c in candidates], np.float32)
    keep_i = nms_keep(boxes_a, score, cfg.nms_iou, cfg.max_proposals)
    rles = [crop_rle(candidates[i].crop, candidates[i].x0, candidates[i].y0, calib.height, calib.width) for i in keep_i]
    proposals = Proposals(
        frame=frame,
        rles=rles,
        boxes=boxes_a[keep_i].reshape(-1, 4),
        objectness=score[keep_i],
        posterior=None,
        proposer=[PROPOSER_NAME] * len(keep_i),
        position=np.asarray([c.position for c in candidates], np.float32)[keep_i].reshape(-1, 3),
        size=np.asarray([c.size for c in candidates], np.float32)[keep_i].reshape(-1, 3),
    )
    return proposals, cue[keep_i].astype(np.float32)


class StereoProposer:
    """Stateless per frame. ``propose`` gives a :class:`StereoResult`; calling the proposer
    gives its proposals alone (the ``proposer(frame, geometry) -> Proposals`` shape)."""

    def __init__(self, cfg: StereoProposerConfig | None = None):
        self.cfg = cfg or StereoProposerConfig()
        if self.cfg.pixel_step < 1 or self.cfg.column_px < 1:
            raise ValueError("stereo proposer: pixel_step and column_px must be ≥ 1")

    def __call__(self, frame: StereoFrame, geometry: FrameGeometry) -> Proposals:
        return self.propose(frame, geometry).proposals

    def propose(self, frame: StereoFrame, geometry: FrameGeometry) -> StereoResult:
        """One frame's proposals, their cues, the reason when there are none, and step timings."""
        calib, cfg = frame.calib, self.cfg
        H, W = calib.height, calib.width
        where = f"{frame.dataset}/{frame.sequence}"
        if geometry.depth is None or geometry.depth.shape != (H, W):
            raise InputError(f"depth map must be ({H}, {W}), got {getattr(geometry.depth, 'shape', None)}",
                             where, frame.index)
        if geometry.index != frame.index:
            raise InputError(f"geometry of frame {geometry.index} given with frame {frame.index}", where, frame.index)
        if not geometry.ground.ok:
            reason = "no ground plane: " + geometry.ground.reason
            return StereoResult(empty_proposals(frame.index), _no_cues(), reason, {})
        t0 = time.perf_counter()
        pts = points_above_ground(geometry.depth, geometry.ground, calib, cfg)
        grid = polar_grid(pts, calib, cfg)
        t1 = time.perf_counter()
        clusters = cluster_points(pts, grid, calib.bf, cfg)
        t2 = time.perf_counter()
        stats = cluster_stats(clusters, pts, calib.bf, cfg)
        if not stats:
            return StereoResult(empty_proposals(frame.index), _no_cues(), "",
                                {"points": 1e3 * (t1 - t0), "cluster": 1e3 * (t2 - t1)})
        chosen = first_masks(stats, cfg)
        t3 = time.perf_counter()
        kernels = mask_kernels(cfg)
        candidates = [build_mask(stats[i], pts, kernels, calib, geometry.ground.d, cfg) for i in chosen]
        candidates = refine_candidates(candidates, frame.left, cfg)
        t4 = time.perf_counter()
        proposals, cues = score_and_encode(frame.index, candidates, calib, cfg)
        timings = {"points": 1e3 * (t1 - t0), "cluster": 1e3 * (t2 - t1), "stats": 1e3 * (t3 - t2),
                   "masks": 1e3 * (t4 - t3), "encode": 1e3 * (time.perf_counter() - t4)}
        return StereoResult(proposals, cues, "", timings)


def stereo_proposer(cfg: ProposalConfig, frame_size: tuple[int, int]) -> StereoProposer:
    """The registry's factory of ``stereo`` (``proposals.stereo``; each frame brings its own size)."""
    return StereoProposer(cfg.stereo)
