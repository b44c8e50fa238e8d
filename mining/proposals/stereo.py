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
5. **Objectness** = sigmoid(bias + Σ wₖ·cueₖ), every cue in [0, 1] with higher meaning
   more object-like and every weight ≥ 0, so objectness is monotone non-decreasing in
   each cue (:func:`objectness_from_cues`). Cues, in ``CUES`` order: border contrast (the
   fraction of the mask's border ring that is background: ground, no depth, or a depth
   jump — the object stands free), fill (mask area / box area), plausible footprint,
   plausible top height, point support.

A frame whose ground plane failed gets no proposals: without the ground there is no
"above the ground" and inventing a plane would be a silent substitute. The reason is kept
in ``StereoProposer.last_reason`` (the caller also has ``geometry.ground.reason``).
"""

from __future__ import annotations

import math
import time

import cv2
import numpy as np

from mining.errors import InputError
from mining.masks import crop_rle
from mining.proposals.onnx_yolo import nms_keep
from mining.proposals.stereo_config import StereoProposerConfig
from mining.types import FrameGeometry, Proposals, StereoFrame

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


class StereoProposer:
    """Stateless per frame; ``last_timings_ms``, ``last_reason`` and ``last_cues`` describe the last call."""

    def __init__(self, cfg: StereoProposerConfig | None = None):
        self.cfg = cfg or StereoProposerConfig()
        if self.cfg.pixel_step < 1 or self.cfg.column_px < 1:
            raise ValueError("stereo proposer: pixel_step and column_px must be ≥ 1")
        self.last_timings_ms: dict[str, float] = {}
        self.last_reason = ""
        self.last_cues = np.zeros((0, len(CUES)), np.float32)

    def __call__(self, frame: StereoFrame, geometry: FrameGeometry) -> Proposals:
        calib, cfg = frame.calib, self.cfg
        H, W = calib.height, calib.width
        where = f"{frame.dataset}/{frame.sequence}"
        if geometry.depth is None or geometry.depth.shape != (H, W):
            raise InputError(f"depth map must be ({H}, {W}), got {getattr(geometry.depth, 'shape', None)}",
                             where, frame.index)
        if geometry.index != frame.index:
            raise InputError(f"geometry of frame {geometry.index} given with frame {frame.index}", where, frame.index)
        self.last_cues = np.zeros((0, len(CUES)), np.float32)
        if not geometry.ground.ok:
            self.last_reason = "no ground plane: " + geometry.ground.reason
            self.last_timings_ms = {}
            return empty_proposals(frame.index)
        self.last_reason = ""
        t0 = time.perf_counter()

        # 1. Points above the ground, on the sample grid (every s-th pixel).
        s, bf = cfg.pixel_step, calib.bf
        z = geometry.depth[::s, ::s].astype(np.float64)
        hs, ws = z.shape
        u = (np.arange(ws) * s)[None, :]
        v = (np.arange(hs) * s)[:, None]
        n, d0 = geometry.ground.normal, geometry.ground.d
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
        pv, pu = np.nonzero(keep)
        pz, ph, px = z[pv, pu], h[pv, pu], x[pv, pu]

        # 2. Polar bird's-eye grid of visible vertical surface per cell.
        n_cols = -(-W // cfg.column_px)
        n_rows = int(range_index(np.array([cfg.max_depth_m]), bf, cfg)[0]) + 1
        cell = np.minimum(range_index(pz, bf, cfg).astype(np.int64), n_rows - 1) * n_cols + (pu * s) // cfg.column_px
        surface = np.bincount(cell, weights=s * s * pz / (calib.fy * cfg.column_px), minlength=n_rows * n_cols)
        surface = surface.reshape(n_rows, n_cols)
        t1 = time.perf_counter()

        # 3. Multi-scale connected components; each distinct point set once.
        clusters: list[np.ndarray] = []
        seen: set[bytes] = set()
        for mult, dr, dc in cfg.scales:
            occupied = (surface >= cfg.min_density_m * mult).astype(np.uint8)
            links = cv2.dilate(occupied, np.ones((2 * dr + 1, 2 * dc + 1), np.uint8)) if dr or dc else occupied
            _, labels = cv2.connectedComponents(links, connectivity=8)
            labels[occupied == 0] = 0
            _collect(labels.ravel()[cell], labels.max(), cfg.min_points, seen, clusters)
        # Height bands: adjacent cells whose tops differ (a car before a taller bush) part.
        if cfg.height_band_m > 0:
            top = np.zeros(n_rows * n_cols)
            np.maximum.at(top, cell, ph)
            top = top.reshape(n_rows, n_cols)
            occupied = surface >= cfg.min_density_m
            for offset in (0.0, 0.5 * cfg.height_band_m):
                band = np.floor((top + offset) / cfg.height_band_m).astype(np.int32)
                labels = np.zeros((n_rows, n_cols), np.int32)
                n_labels = 0
                for b in np.unique(band[occupied]):
                    n_b, lab_b = cv2.connectedComponents((occupied & (band == b)).astype(np.uint8), connectivity=8)
                    labels[lab_b > 0] = lab_b[lab_b > 0] + n_labels
                    n_labels += n_b - 1
                _collect(labels.ravel()[cell], n_labels, cfg.min_points, seen, clusters)

        # The same in the image: regions of object-height points cut where the depth jumps.
        disparity = bf / z
        for jump_px in cfg.image_jumps_px:
            cut = np.zeros((hs, ws), bool)
            gap = np.maximum(jump_px, cfg.border_gap_m * disparity * disparity / bf)
            dx = np.abs(np.diff(disparity, axis=1)) > gap[:, 1:]
            dy = np.abs(np.diff(disparity, axis=0)) > gap[1:, :]
            cut[:, 1:] |= dx
            cut[1:, :] |= dy
            _, labels = cv2.connectedComponents((keep & ~cut).astype(np.uint8), connectivity=4)
            _collect(labels[pv, pu], labels.max(), cfg.min_points, seen, clusters)
        t2 = time.perf_counter()

        # 4.–5. Masks and cues per cluster.
        k_close = max(1, cfg.mask_close_px // s) | 1
        close_kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k_close, k_close))
        ring_kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
        pad = k_close // 2 + 3 + cfg.grow_steps
        grow_kernel = np.ones((1, 3), np.uint8)
        trim = cfg.left_trim_px // s
        # 4a. Cheap 3D statistics per cluster (order statistics of at most ~256 points each).
        stats = []  # (idx, subsample, quantile positions, z quantiles, x quantiles, top, width, length, point box)
        for idx in clusters:
            sub = idx[:: max(1, idx.size // cfg.stats_points)]
            zs, xs_, hs_ = np.sort(pz[sub]), np.sort(px[sub]), np.sort(ph[sub])
            q = (np.array([0.05, 0.5, 0.95]) * (sub.size - 1)).round().astype(int)
            zq, xq = zs[q], xs_[q]
            spread = 2.0 * zq[1] ** 2 * cfg.disparity_noise_px / bf  # range spread stereo noise alone makes
            length = max(0.0, zq[2] - zq[0] - spread)
            width = xq[2] - xq[0]
            if max(width, length) > cfg.max_extent_m:
                continue
            cv_, cu_ = pv[idx], pu[idx]
            box = (cu_.min(), cv_.min(), cu_.max() + 1, cv_.max() + 1)
            stats.append((idx, sub, q, zq, xq, float(hs_[q[2]]), width, length, box))
        if not stats:
            self.last_timings_ms = {"points": 1e3 * (t1 - t0), "cluster": 1e3 * (t2 - t1)}
            return empty_proposals(frame.index)
        # 4b. Near-duplicates across scales go before their masks are built: NMS on the point
        # boxes, ranked by the cues known so far (border contrast taken as 1/2 for all).
        pre = np.array([(0.5, st[0].size / ((st[8][2] - st[8][0]) * (st[8][3] - st[8][1])),
                         max(st[6], st[7]), st[5], st[0].size) for st in stats])
        pre_keep = nms_keep(np.array([st[8] for st in stats], np.float64), objectness_from_cues(self._cues(pre), cfg),
                            cfg.nms_iou, int(cfg.mask_budget * cfg.max_proposals))
        t3 = time.perf_counter()

        # 4c. Masks and the remaining cues of the survivors.
        crops, boxes, cues, positions, sizes = [], [], [], [], []
        for i in pre_keep:
            idx, sub, q, zq, xq, top, width, length, _ = stats[i]
            cv_, cu_, cz = pv[idx], pu[idx], pz[idx]
            r0, c0 = max(0, cv_.min() - pad), max(0, cu_.min() - pad)
            r1, c1 = min(hs, cv_.max() + pad + 1), min(ws, cu_.max() + pad + 1)
            points = np.zeros((r1 - r0, c1 - c0), np.uint8)
            points[cv_ - r0, cu_ - c0] = 1
            zobj = np.zeros(points.shape, np.float32)
            zobj[cv_ - r0, cu_ - c0] = cz
            # Growth downwards (and diagonally) over points within the cluster's depth range: its
            # feet, below the ground cut, as many rows as the ground cut removed at this depth.
            zc = z[r0:r1, c0:c1]
            noise_z = zq[1] ** 2 * cfg.disparity_noise_px / bf
            grow_gap, ring_gap = max(cfg.border_gap_m, noise_z), max(cfg.border_gap_m, 3.0 * noise_z)
            cut_gap = cfg.min_height_m - cfg.grow_min_height_m + cfg.height_noise_sigmas * d0 * zq[1] * cfg.disparity_noise_px / bf
            steps = min(cfg.grow_steps, math.ceil(cut_gap * calib.fy / (zq[1] * s)))
            if steps > 0:
                ok = (growable[r0:r1, c0:c1] & (zc >= zq[0] - grow_gap) & (zc <= zq[2] + grow_gap)).astype(np.uint8)
                for _ in range(steps):
                    below = np.zeros_like(points)
                    below[1:] = cv2.dilate(points, grow_kernel)[:-1]  # one row down, one column aside
                    new = below & ok & (points == 0)
                    if not new.any():
                        break
                    points |= new
                grown = (points > 0) & (zobj == 0)
                zobj[grown] = zc[grown]
            mask = cv2.morphologyEx(points, cv2.MORPH_CLOSE, close_kernel)
            if trim > 0:  # left-edge fattening: keep pixels whose left neighbours are in the mask too
                kept = mask.copy()
                for k in range(1, trim + 1):
                    kept[:, k:] &= mask[:, :-k]
                    kept[:, :k] = 0
                mask = kept if kept.any() else mask
            # Border ring: background where there is no object-height point at the object's depth.
            znear = cv2.dilate(zobj, ring_kernel)
            ring = (cv2.dilate(mask, ring_kernel) > 0) & (mask == 0) & (znear > 0)
            rz = zc[ring]
            rlow = low[r0:r1, c0:c1][ring]
            jump = ~(np.abs(rz - znear[ring]) <= ring_gap)  # NaN depth counts as a jump
            contrast = float((rlow | jump).mean()) if rz.size else 1.0
            rows = np.nonzero(mask.any(axis=1))[0]
            cols = np.nonzero(mask.any(axis=0))[0]
            mask = mask[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
            fill = float(np.count_nonzero(mask)) / mask.size
            # Full-resolution crop: each sample stands for an s × s block.
            y0, x0 = (r0 + int(rows[0])) * s, (c0 + int(cols[0])) * s
            crop = np.repeat(np.repeat(mask.astype(bool), s, axis=0), s, axis=1)[: H - y0, : W - x0]
            crops.append((crop, x0, y0))
            boxes.append((x0, y0, x0 + crop.shape[1], y0 + crop.shape[0]))
            cues.append((contrast, fill, max(width, length), top, idx.size))
            positions.append((xq[1], float(np.sort(y[pv[sub], pu[sub]])[q[1]]), zq[1]))
            sizes.append((width, top, length))
        t4 = time.perf_counter()

        cue = self._cues(np.asarray(cues, np.float64))
        score = objectness_from_cues(cue, cfg)
        boxes_a = np.asarray(boxes, np.float32)
        keep_i = nms_keep(boxes_a, score, cfg.nms_iou, cfg.max_proposals)
        rles = [crop_rle(crops[i][0], crops[i][1], crops[i][2], H, W) for i in keep_i]
        self.last_cues = cue[keep_i].astype(np.float32)
        self.last_timings_ms = {"points": 1e3 * (t1 - t0), "cluster": 1e3 * (t2 - t1), "stats": 1e3 * (t3 - t2),
                                "masks": 1e3 * (t4 - t3), "encode": 1e3 * (time.perf_counter() - t4)}
        return Proposals(
            frame=frame.index,
            rles=rles,
            boxes=boxes_a[keep_i].reshape(-1, 4),
            objectness=score[keep_i],
            posterior=None,
            proposer=[PROPOSER_NAME] * len(keep_i),
            position=np.asarray(positions, np.float32)[keep_i].reshape(-1, 3),
            size=np.asarray(sizes, np.float32)[keep_i].reshape(-1, 3),
        )

    def _cues(self, raw: np.ndarray) -> np.ndarray:
        """Raw (contrast, fill, extent m, top m, points) → the five cues in [0, 1], higher = more object-like."""
        cfg = self.cfg
        return np.column_stack([
            np.clip(raw[:, 0], 0.0, 1.0),
            np.clip(raw[:, 1], 0.0, 1.0),
            _plausible(raw[:, 2], 0.0, cfg.plausible_extent_m, cfg.max_extent_m),
            _plausible(raw[:, 3], cfg.plausible_top_m[0], cfg.plausible_top_m[1], cfg.max_height_m),
            np.clip(np.log(raw[:, 4]) / math.log(cfg.support_points), 0.0, 1.0),
        ])
