"""``mine bench range``: proposal survival and localisation error against distance.

For every ground-truth object (KITTI label_02 Car / Van / Pedestrian, or a synthetic
object with ≥ 100 visible pixels) in each frame the image pipeline runs on
(``FrameLoop``: geometry → proposals → localise → geometric filter), by distance bin of
the object's true centre depth Z:

* **proposal**: share with a proposal of box IoU ≥ 0.5 (the best-overlapping one);
* **localised**: share of those whose proposal got a finite 3D position;
* **kept**: share of those with a proposal that pass the geometric filter, and for the
  dropped ones the first clause that dropped them (``FILTER_CLAUSES``; "cap" = beyond
  the filter's per-frame maximum);
* **error**: |position − true centre| and the depth error Z − Z_true, against the
  standard deviation the observation's covariance predicts (σ_Z); "dZ/σ" is
  median(|dZ| / σ_Z) / 0.6745 — 1 when the errors are N(0, σ_Z²), above 1 when the
  covariance claims too much precision (bias and spread both count; dX/σ, dY/σ: the same
  across and down); "dZ std" is the depth error's robust spread (1.4826 · MAD), without
  its bias; "dh": measured height above the ground plane − the true centre's (half the
  object's height), against the height std the covariance predicts (σh = √(nᵀΣn)).

Synthetic truth also gives the exact depth, so two more tables separate the stereo noise
from the rest: the same proposal mask localised on the true depth ("perfect stereo"), whose
difference to the estimate is the stereo part of the error (compared with the triangulation
covariance without its prior), and the per-pixel disparity error of the geometry stage on
object pixels against distance (bias and robust spread, full-resolution pixels) and
against the true disparity's fraction of a pixel at the matching resolution (sub-pixel
"pixel locking": an error that a mask's median does not average away).

KITTI labels give the bottom centre in rectified camera 0; the centre is half a height
above it, moved to the left colour camera with the calibration (``rect0_to_cam2``). The
``kitti-raw`` source gives the same disparity tables on real images against LiDAR.
"""

from __future__ import annotations

import argparse
import copy
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mining.boxes import box_iou
from mining.checks import count
from mining.config import JobConfig
from mining.formats.kitti_tracking import read_kitti_tracking
from mining.localise.localise import (
    FILTER_CLAUSES,
    filter_clauses,
    geometric_filter,
    localise,
    triangulation_covariance,
)
from mining.pipeline.arguments import add_data_option, add_job_options, frame_range, job_config
from mining.pipeline.frames import FrameRecord, frame_records
from mining.sources import open_source

BINS_M = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 80.0)  # ours: 10 m bins to REFERENCE's 60 m filter, one beyond
MATCH_IOU = 0.5  # REFERENCE (evaluation protocols): a match needs box IoU ≥ 0.5
MIN_VISIBLE_PX = 100  # ours, as the synthetic protocol: objects under 100 px cannot pass the 100 px² box filter
KITTI_TYPES = ("Car", "Van", "Pedestrian")  # the labelled classes the pipeline is scored on (Van: Car's neighbour)
RAW_DRIVE = "2011_09_26_drive_0001_sync"  # the shared KITTI raw drive with LiDAR (SOURCES.md)
MAD_TO_STD = 1.4826  # a normal distribution's std per median absolute deviation
HALF_NORMAL_MEDIAN = 0.6745  # median of |x| for a standard normal x


@dataclass
class GtRow:
    """One ground-truth object in one frame and what the pipeline made of it."""

    frame: int
    category: str
    z_true: float
    centre: np.ndarray
    iou: float = 0.0
    localised: bool = False
    kept: bool = False
    dropped_by: str = ""
    position: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    covariance: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    covariance_stereo: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))  # without the prior
    perfect: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))  # same mask, true depth (synthetic)
    height: float = np.nan  # measured height of the position above the ground plane
    height_true: float = np.nan  # the true centre's height above the ground: half the object's height
    height_std: float = np.nan  # the height's std predicted by the covariance (nᵀΣn)
    plane_error: float = np.nan  # the true centre's height above the measured plane − the true one
    objectness: float = np.nan

    @property
    def matched(self) -> bool:
        return self.iou >= MATCH_IOU


@dataclass
class Truth:
    boxes: np.ndarray  # (N, 4)
    centres: np.ndarray  # (N, 3) left camera
    categories: list[str]
    half_heights: np.ndarray  # (N,) half the object's height: its centre's height above the ground


def _kitti_truth(labels, calib, frame: int) -> Truth:
    sel = (labels.frame == frame) & np.isin(labels.type, KITTI_TYPES)
    loc = labels.location[sel].copy()
    loc[:, 1] -= labels.dimensions[sel, 0] / 2  # y points down: the centre is half a height (h) above the bottom
    return Truth(labels.box[sel], calib.rect0_to_cam2(loc), [str(t) for t in labels.type[sel]],
                 labels.dimensions[sel, 0] / 2)


def _synthetic_truth(truth) -> Truth:
    objs = [o for o in truth.objects if o.mask.sum() >= MIN_VISIBLE_PX]
    return Truth(np.array([o.box for o in objs], np.float64).reshape(-1, 4),
                 np.array([o.center_cam for o in objs], np.float64).reshape(-1, 3), [o.category for o in objs],
                 np.array([o.size[1] / 2 for o in objs], np.float64))


def _rows(rec: FrameRecord, truth: Truth, cfg: JobConfig, perfect_depth: np.ndarray | None) -> list[GtRow]:
    loc = rec.localised
    filt = cfg.localise.filters
    clauses = filter_clauses(loc, rec.ground, filt)
    kept = np.zeros(len(loc), bool)
    kept[geometric_filter(loc, rec.ground, filt)] = True
    no_prior = copy.deepcopy(cfg.localise)
    no_prior.prior_var_x = no_prior.prior_var_z = 0.0
    rows = []
    ious = box_iou(truth.boxes, loc.proposals.boxes) if len(loc) and len(truth.boxes) else np.zeros((len(truth.boxes), 0))
    best = ious.argmax(axis=1) if ious.shape[1] else np.zeros(len(truth.boxes), np.int64)
    for k in range(len(truth.boxes)):
        r = GtRow(rec.frame.index, truth.categories[k], float(truth.centres[k, 2]), truth.centres[k],
                  height_true=float(truth.half_heights[k]))
        if ious.shape[1]:
            r.iou = float(ious[k, best[k]])
        if rec.ground.ok:
            r.plane_error = float(rec.ground.height(truth.centres[k])) - r.height_true
        if r.matched:
            j = int(best[k])
            r.objectness = float(loc.proposals.objectness[j])
            r.localised = bool(np.isfinite(loc.position[j]).all())
            r.kept = bool(kept[j])
            if not r.kept:
                r.dropped_by = next((c for c in FILTER_CLAUSES if not clauses[c][j]), "cap")
            if r.localised:
                r.position, r.covariance = loc.position[j], loc.covariance[j]
                r.covariance_stereo = triangulation_covariance(loc.position[j:j + 1], rec.frame.calib, no_prior)[0]
                if rec.ground.ok:
                    r.height = float(rec.ground.height(loc.position[j]))
                    n = rec.ground.normal
                    r.height_std = float(np.sqrt(n @ loc.covariance[j] @ n))
                if perfect_depth is not None:
                    one = loc.proposals.take(np.array([j]))
                    p = localise(one, perfect_depth, rec.frame.calib, rec.ground, None, None, 0, cfg.localise)
                    r.perfect = p.position[0]
        rows.append(r)
    return rows


def _disparity_errors(rec: FrameRecord) -> tuple[np.ndarray, np.ndarray]:
    """(true depth, disparity error) of every object pixel with a valid estimate (synthetic)."""
    truth = rec.frame.truth
    objects = np.zeros(truth.depth.shape, bool)
    for o in truth.objects:
        if o.mask.sum() >= MIN_VISIBLE_PX:
            objects |= o.mask
    z = truth.depth[objects]
    est = rec.geometry.disparity[objects]
    ok = np.isfinite(z) & np.isfinite(est) & (z > 0)
    return z[ok], est[ok] - rec.frame.calib.bf / z[ok]


def lidar_disparity_errors(data: Path, cfg: JobConfig) -> list[tuple[np.ndarray, np.ndarray]]:
    """(LiDAR depth, disparity error) of every projected LiDAR point with a stereo estimate,
    KITTI raw 2011_09_26 drive 0001 frames 0–5 (real images; LiDAR as the truth)."""
    from mining.geometry.stage import GeometryStage

    source = open_source("kitti-raw", str(data / "kitti_raw"))
    plan = source.plan(RAW_DRIVE)
    stage, out = None, []
    for frame in source.read(plan, 0, len(plan)):
        stage = stage or GeometryStage(frame.calib, cfg.geometry)
        disparity = stage.run(frame).disparity
        z = source.lidar_depth(RAW_DRIVE, frame.index)
        ok = np.isfinite(z) & (z > 0) & np.isfinite(disparity)
        out.append((z[ok], disparity[ok] - frame.calib.bf / z[ok]))
    return out


def kitti_rows(data: Path, cfg: JobConfig, sequence: str = "0005", start: int = 0, stop: int = 16) -> list[GtRow]:
    source = open_source("kitti", str(data / "kitti_tracking"))
    plan = source.plan(sequence)
    labels = read_kitti_tracking(data / "kitti_tracking" / "training" / "label_02" / f"{sequence}.txt")
    kc = source.kitti_calib(sequence)
    rows: list[GtRow] = []
    for rec in frame_records(source, plan, start, min(stop, len(plan)), cfg):
        rows += _rows(rec, _kitti_truth(labels, kc, rec.frame.index), cfg, None)
    return rows


def synthetic_rows(cfg: JobConfig, sequence: str = "0000", n_frames: int = 200, start: int = 0, stop: int = 100,
                   disparity: list | None = None) -> list[GtRow]:
    source = open_source("synthetic", None, n_frames=n_frames)
    plan = source.plan(sequence)
    rows: list[GtRow] = []
    for rec in frame_records(source, plan, start, min(stop, len(plan)), cfg):
        depth = rec.frame.truth.depth.astype(np.float32)
        rows += _rows(rec, _synthetic_truth(rec.frame.truth), cfg, depth)
        if disparity is not None:
            disparity.append(_disparity_errors(rec))
    return rows


def _bin_of(z: np.ndarray) -> np.ndarray:
    return np.digitize(z, BINS_M) - 1


def _bins() -> Iterator[tuple[int, str]]:
    for b in range(len(BINS_M) - 1):
        yield b, f"{BINS_M[b]:.0f}-{BINS_M[b + 1]:.0f}"


def _robust_std(x: np.ndarray) -> float:
    return float(MAD_TO_STD * np.median(np.abs(x - np.median(x)))) if len(x) else np.nan


def _honesty(e: np.ndarray, sigma: np.ndarray) -> float:
    """median(|e| / σ) / 0.6745: 1 when e ~ N(0, σ²); bias and spread both raise it."""
    return float(np.median(np.abs(e) / sigma) / HALF_NORMAL_MEDIAN) if len(e) else np.nan


def _pct(a: int, b: int) -> str:
    return f"{100 * a / b:5.0f}%" if b else "    - "


def survival_table(rows: list[GtRow]) -> str:
    z = np.array([r.z_true for r in rows])
    b = _bin_of(z)
    head = f"  {'Z bin m':>8} {'objects':>7} {'proposal':>8} {'localised':>9} {'kept':>6}   dropped by"
    out = [head]
    for i, name in _bins():
        sel = [r for r, bi in zip(rows, b) if bi == i]
        m = [r for r in sel if r.matched]
        loc = [r for r in m if r.localised]
        kept = [r for r in m if r.kept]
        drops: dict[str, int] = {}
        for r in m:
            if not r.kept:
                drops[r.dropped_by] = drops.get(r.dropped_by, 0) + 1
        why = ", ".join(f"{k} {v}" for k, v in sorted(drops.items(), key=lambda kv: -kv[1]))
        out.append(f"  {name:>8} {len(sel):>7} {_pct(len(m), len(sel)):>8} {_pct(len(loc), len(m)):>9} "
                   f"{_pct(len(kept), len(m)):>6}   {why}")
    return "\n".join(out)


def error_table(rows: list[GtRow], stereo_only: bool = False) -> str:
    """Median |error| and the depth error's bias and spread against the predicted σ_Z, per bin.

    ``stereo_only``: the estimate against the same mask on true depth, with the
    triangulation covariance without its prior (synthetic only).
    """
    loc = [r for r in rows if r.matched and r.localised and (not stereo_only or np.isfinite(r.perfect).all())]
    out = [(f"  {'Z bin m':>8} {'n':>5} {'|e| med':>7} {'dZ med':>6} {'dZ std':>6} {'σZ med':>6} {'dZ/σ':>5} "
            f"{'dX/σ':>5} {'dY/σ':>5} {'dh med':>6} {'dh std':>6} {'σh med':>6} {'dh/σ':>5}")]
    b = _bin_of(np.array([r.z_true for r in loc])) if loc else np.zeros(0, int)
    for i, name in _bins():
        sel = [r for r, bi in zip(loc, b) if bi == i]
        if not sel:
            out.append(f"  {name:>8} {0:>5}")
            continue
        ref = np.array([r.perfect if stereo_only else r.centre for r in sel])
        pos = np.array([r.position for r in sel])
        cov = np.array([r.covariance_stereo if stereo_only else r.covariance for r in sel])
        e = pos - ref
        s = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
        dh = np.array([r.height - r.height_true for r in sel])
        sh = np.array([r.height_std for r in sel])
        h_ok = np.isfinite(dh)
        hs = "" if stereo_only else (f"{np.median(dh[h_ok]):>6.2f} {_robust_std(dh[h_ok]):>6.2f} "
                                     f"{np.median(sh[h_ok]):>6.2f} {_honesty(dh[h_ok], sh[h_ok]):>5.2f}")
        out.append(f"  {name:>8} {len(sel):>5} {np.median(np.linalg.norm(e, axis=1)):>7.2f} "
                   f"{np.median(e[:, 2]):>6.2f} {_robust_std(e[:, 2]):>6.2f} {np.median(s[:, 2]):>6.2f} "
                   f"{_honesty(e[:, 2], s[:, 2]):>5.2f} {_honesty(e[:, 0], s[:, 0]):>5.2f} "
                   f"{_honesty(e[:, 1], s[:, 1]):>5.2f} {hs}")
    return "\n".join(out)


def plane_table(rows: list[GtRow]) -> str:
    """The measured ground plane at every true object: its true centre's height above the
    plane minus the true height (half the object's), by distance: the plane's own error there."""
    sel = [r for r in rows if np.isfinite(r.plane_error)]
    b = _bin_of(np.array([r.z_true for r in sel])) if sel else np.zeros(0, int)
    out = [f"  {'Z bin m':>8} {'objects':>7} {'median m':>8} {'std m':>6} {'|err| 90% m':>11}"]
    for i, name in _bins():
        e = np.array([r.plane_error for r, bi in zip(sel, b) if bi == i])
        if not len(e):
            out.append(f"  {name:>8} {0:>7}")
            continue
        out.append(f"  {name:>8} {len(e):>7} {np.median(e):>8.2f} {_robust_std(e):>6.2f} "
                   f"{np.quantile(np.abs(e), 0.9):>11.2f}")
    return "\n".join(out)


def disparity_table(samples: list[tuple[np.ndarray, np.ndarray]], bf: float) -> str:
    z = np.concatenate([s[0] for s in samples]) if samples else np.zeros(0)
    e = np.concatenate([s[1] for s in samples]) if samples else np.zeros(0)
    b = _bin_of(z)
    out = [f"  {'Z bin m':>8} {'pixels':>8} {'disp px':>7} {'bias px':>7} {'std px':>7} {'|e|>1px':>7}"]
    for i, name in _bins():
        sel = b == i
        if not sel.any():
            out.append(f"  {name:>8} {0:>8}")
            continue
        es = e[sel]
        out.append(f"  {name:>8} {sel.sum():>8} {np.median(bf / z[sel]):>7.1f} {np.median(es):>7.2f} "
                   f"{_robust_std(es):>7.2f} {100 * np.mean(np.abs(es) > 1):>6.0f}%")
    return "\n".join(out)


def locking_table(samples: list[tuple[np.ndarray, np.ndarray]], bf: float, downscale: int) -> str:
    """Disparity error by the fractional part of the true disparity at the matching resolution
    (objects at 15–80 m): sub-pixel interpolation pulls estimates towards whole pixels there."""
    z = np.concatenate([s[0] for s in samples]) if samples else np.zeros(0)
    e = np.concatenate([s[1] for s in samples]) if samples else np.zeros(0)
    far = (z >= 15.0) & (z < 80.0)
    frac = np.mod(bf / z[far] / downscale, 1.0)
    e = e[far]
    out = [f"  {'fraction':>11} {'pixels':>8} {'bias px':>7} {'std px':>7}"]
    for lo in np.arange(0.0, 1.0, 0.125):
        sel = (frac >= lo) & (frac < lo + 0.125)
        if sel.any():
            out.append(f"  {f'{lo:.3f}-{lo + 0.125:.3f}':>11} {sel.sum():>8} {np.median(e[sel]):>+7.2f} "
                       f"{_robust_std(e[sel]):>7.2f}")
    return "\n".join(out)


def drop_list(rows: list[GtRow]) -> str:
    out = []
    for r in rows:
        if r.matched and not r.kept:
            out.append(f"    frame {r.frame:>4} {r.category:<10} Z {r.z_true:5.1f} m  iou {r.iou:.2f}  "
                       f"dropped by {r.dropped_by:<9} position {np.round(r.position, 2)}  height {r.height:5.2f} m  "
                       f"(true {r.height_true:4.2f}, σh {r.height_std:4.2f})  σZ {np.sqrt(r.covariance[2, 2]):.2f}")
    return "\n".join(out)


def run_range_bench(data: Path, cfg: JobConfig, sources: list[str], kitti_frames: tuple[int, int] = (0, 16),
                    synthetic_sequence: str = "0000", synthetic_n_frames: int = 200,
                    synthetic_frames: tuple[int, int] = (0, 100), verbose: bool = False) -> int:
    for name in sources:
        t0 = time.perf_counter()
        disparity: list = []
        if name in ("kitti", "kitti-raw") and not data.is_dir():
            print(f"mine bench range: real data folder {data} not found (pass --data)")
            return 2
        down = cfg.geometry.stereo.downscale
        if name == "kitti-raw":
            samples = lidar_disparity_errors(data, cfg)
            print(f"KITTI raw {RAW_DRIVE} frames 0-5: disparity error at projected LiDAR points "
                  f"(estimate − bf / Z_LiDAR, full-resolution px) ({time.perf_counter() - t0:.0f} s)")
            bf = open_source("kitti-raw", str(data / "kitti_raw")).plan(RAW_DRIVE).calib.bf
            print(disparity_table(samples, bf))
            print(f"By the true disparity's fraction of a pixel at the matching resolution (1/{down}), 15-80 m:")
            print(locking_table(samples, bf, down))
            print()
            continue
        if name == "kitti":
            rows = kitti_rows(data, cfg, "0005", *kitti_frames)
            title = f"KITTI 0005 frames {kitti_frames[0]}-{kitti_frames[1] - 1}, labels {'/'.join(KITTI_TYPES)}"
        else:
            rows = synthetic_rows(cfg, synthetic_sequence, synthetic_n_frames, *synthetic_frames, disparity=disparity)
            title = (f"synthetic {synthetic_sequence} frames {synthetic_frames[0]}-{synthetic_frames[1] - 1} "
                     f"(of {synthetic_n_frames}), objects ≥ {MIN_VISIBLE_PX} px")
        print(f"{title}, proposer {cfg.proposals.proposer} ({time.perf_counter() - t0:.0f} s)")
        print(f"Survival (box IoU ≥ {MATCH_IOU}; kept = passes the geometric filter; shares of the column before):")
        print(survival_table(rows))
        print("Localisation error against the true centre (covariance as used, with its prior):")
        print(error_table(rows))
        print("Ground plane error at the true objects (true centre's height above the plane − half its height):")
        print(plane_table(rows))
        if name == "synthetic":
            print("Stereo part: estimate − same mask on true depth (triangulation covariance without the prior):")
            print(error_table(rows, stereo_only=True))
            bf = open_source("synthetic", None).calib.bf
            print("Disparity error on object pixels (estimate − true, full-resolution px):")
            print(disparity_table(disparity, bf))
            print(f"By the true disparity's fraction of a pixel at the matching resolution (1/{down}), 15-80 m:")
            print(locking_table(disparity, bf, down))
        if verbose:
            print("Dropped objects:")
            print(drop_list(rows))
        print()
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine bench range``'s options."""
    add_job_options(p)
    add_data_option(p)
    p.add_argument("--sources", nargs="+", choices=["kitti", "synthetic", "kitti-raw"],
                   default=["kitti", "synthetic", "kitti-raw"])
    p.add_argument("--kitti-frames", type=frame_range, default=(0, 16), metavar="A:B", help="KITTI 0005 frames [A, B)")
    p.add_argument("--synthetic-sequence", default="0000")
    p.add_argument("--synthetic-n-frames", type=count(), default=200, help="length of the synthetic world")
    p.add_argument("--synthetic-frames", type=frame_range, default=(0, 100), metavar="A:B",
                   help="synthetic frames [A, B)")
    p.add_argument("--verbose", action="store_true", help="also list every dropped object")


def run(args: argparse.Namespace) -> int:
    """``mine bench range``."""
    return run_range_bench(Path(args.data), job_config(args), args.sources, kitti_frames=args.kitti_frames,
                           synthetic_sequence=args.synthetic_sequence, synthetic_n_frames=args.synthetic_n_frames,
                           synthetic_frames=args.synthetic_frames, verbose=args.verbose)
