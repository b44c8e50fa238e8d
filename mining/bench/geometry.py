"""``mine bench geometry``: accuracy of the geometry stage on real ground truth, and its speed.

Everything runs pinned to one CPU core (the per-frame budget is stated for one core).
The rows and their targets are those of the foundation issue:

* depth vs projected LiDAR on KITTI raw 2011_09_26 drive 0001 frames 0–5 (abs-rel ≤ 0.04
  with ≥ 90 % of LiDAR points within 40 m covered);
* D1-all on KITTI 2015 000046 (≤ 10 %) and bad-2.0 on Middlebury 2014 Motorcycle (Q);
* egomotion drift (≤ 2 % over 5+ frames) on KITTI raw vs OXTS, KITTI tracking 0005 vs
  ORB-SLAM3 and synthetic sequences vs their exact poses;
* ms per frame for each geometry step at 1242×375 (≤ 150 ms for the whole step).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mining.catalog import safe_files
from mining.checks import count, output_file
from mining.eval.depth import depth_errors
from mining.eval.odometry import odometry_errors
from mining.eval.stereo import bad_n, d1_all, density
from mining.formats.disparity import read_pfm
from mining.formats.poses import read_poses
from mining.geometry.config import GeometryConfig
from mining.geometry.disparity import compute_disparity
from mining.geometry.poses import chain_egomotion
from mining.geometry.stage import GeometryStage
from mining.pipeline.arguments import add_data_option, add_job_options, add_overwrite_option, job_config
from mining.sources import open_source

RAW_DRIVE = "2011_09_26_drive_0001_sync"


def pin_one_core() -> None:
    """Run on one core: OpenCV single-threaded and the process bound to one CPU."""
    cv2.setNumThreads(1)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})


def _run_sequence(source, sequence: str, cfg: GeometryConfig, start: int = 0, stop: int | None = None):
    plan = source.plan(sequence)
    stage = None
    out = []
    for frame in source.read(plan, start, stop):
        stage = stage or GeometryStage(frame.calib, cfg)
        out.append((frame, stage.run(frame)))
    return out


def _egomotion_row(name: str, geoms, truth: np.ndarray) -> dict[str, Any]:
    transforms = [None if g.egomotion is None or not g.egomotion.ok else g.egomotion.T_cur_prev for _, g in geoms]
    est = chain_egomotion(transforms)
    err = odometry_errors(est, truth, min_frames=min(5, len(truth) - 1))
    fails = sum(1 for _, g in geoms[1:] if not g.egomotion.ok)
    return {"name": name, "frames": len(geoms), "translation_pct": err.translation_pct,
            "rotation_deg_per_m": err.rotation_deg_per_m, "segments": err.segments, "failures": fails}


def bench_depth(data: Path, cfg: GeometryConfig) -> list[dict[str, Any]]:
    source = open_source("kitti-raw", str(data / "kitti_raw"))
    rows = []
    for frame, g in _run_sequence(source, RAW_DRIVE, cfg):
        lidar = source.lidar_depth(RAW_DRIVE, frame.index)
        for limit in (40.0, None):
            e = depth_errors(g.depth, lidar, max_depth_m=limit)
            rows.append({"frame": frame.index, "max_depth_m": limit, **asdict(e)})
    return rows


def bench_stereo(data: Path, cfg: GeometryConfig) -> dict[str, Any]:
    from mining.formats.disparity import read_disparity_png

    k = data / "stereo_gt" / "kitti2015_000046"
    left = cv2.cvtColor(cv2.imread(str(k / "image_2" / "000046_10.png")), cv2.COLOR_BGR2RGB)
    right = cv2.cvtColor(cv2.imread(str(k / "image_3" / "000046_10.png")), cv2.COLOR_BGR2RGB)
    truth = read_disparity_png(k / "disp_occ_0" / "000046_10.png")
    est = compute_disparity(left, right, cfg.stereo)
    m = data / "stereo_gt" / "middlebury2014_motorcycleQ"
    mleft = cv2.cvtColor(cv2.imread(str(m / "im0.png")), cv2.COLOR_BGR2RGB)
    mright = cv2.cvtColor(cv2.imread(str(m / "im1.png")), cv2.COLOR_BGR2RGB)
    mtruth = read_pfm(m / "disp0GT.pfm")
    nocc = cv2.imread(str(m / "mask0nocc.png"), cv2.IMREAD_GRAYSCALE) == 255
    mest = compute_disparity(mleft, mright, cfg.stereo)
    return {
        "kitti2015_d1_all": d1_all(est, truth),
        "kitti2015_density": density(est, truth),
        "middlebury_bad2_nonocc": bad_n(mest, mtruth, nocc, 2.0),
        "middlebury_density_nonocc": float(np.isfinite(mest[nocc]).mean()),
    }


def bench_egomotion(data: Path, cfg: GeometryConfig, synthetic_frames: int) -> tuple[list[dict[str, Any]], list[dict[str, float]]]:
    rows = []
    raw = open_source("kitti-raw", str(data / "kitti_raw"))
    oxts_frames, oxts = raw.oxts_poses(RAW_DRIVE)
    assert list(oxts_frames) == list(range(len(oxts))), "OXTS must cover the first frames"
    geoms = _run_sequence(raw, RAW_DRIVE, cfg, 0, len(oxts))
    rows.append(_egomotion_row("kitti-raw 0001 frames 0-4 vs OXTS", geoms, oxts))

    kitti = open_source("kitti", str(data / "kitti_tracking"))
    geoms = _run_sequence(kitti, "0005", cfg, 0, 16)
    slam = read_poses(data / "kitti_tracking" / "training" / "egoposes_orbslam3" / "0005.txt")[:16]
    rows.append(_egomotion_row("kitti 0005 frames 0-15 vs ORB-SLAM3", geoms, slam))
    timings = [g.timings_ms for _, g in geoms[1:]]

    synth = open_source("synthetic", None, n_frames=synthetic_frames)
    for seq in ("0000", "0001"):
        geoms = _run_sequence(synth, seq, cfg)
        truth = np.array([f.truth.pose for f, _ in geoms])
        rows.append(_egomotion_row(f"synthetic {seq} frames 0-{synthetic_frames - 1} vs exact", geoms, truth))
    return rows, timings


def _fmt(x: float, pct: bool = False) -> str:
    if x is None or not np.isfinite(x):
        return "n/a"
    return f"{100 * x:.2f} %" if pct else f"{x:.4f}"


def run_geometry_bench(data: Path, cfg: GeometryConfig, synthetic_frames: int = 200, json_out: str | None = None,
                       overwrite: bool = False) -> int:
    """Print the geometry table; returns 0 when every target holds, 1 otherwise."""
    if not data.is_dir():
        print(f"mine bench geometry: real data folder {data} not found (pass --data)")
        return 2
    pin_one_core()
    t0 = time.perf_counter()
    results: dict[str, Any] = {}
    checks: list[tuple[str, bool]] = []

    depth_rows = bench_depth(data, cfg)
    results["depth"] = depth_rows
    print("Depth vs projected LiDAR, KITTI raw 2011_09_26 drive 0001 frames 0-5")
    print(f"  {'frame':>5} {'range':>7} {'abs-rel':>8} {'d<1.25':>8} {'valid':>8} {'points':>7}")
    for r in depth_rows:
        rng = f"≤{r['max_depth_m']:.0f} m" if r["max_depth_m"] else "all"
        print(f"  {r['frame']:>5} {rng:>7} {_fmt(r['abs_rel']):>8} {_fmt(r['delta_125']):>8} {_fmt(r['valid'], True):>8} {r['n_points']:>7}")
    for limit in (40.0, None):
        sel = [r for r in depth_rows if r["max_depth_m"] == limit]
        w = np.array([r["n_points"] * r["valid"] for r in sel])
        abs_rel = float(np.average([r["abs_rel"] for r in sel], weights=w))
        valid = float(sum(r["n_points"] * r["valid"] for r in sel) / sum(r["n_points"] for r in sel))
        d125 = float(np.average([r["delta_125"] for r in sel], weights=w))
        rng = "≤40 m" if limit else "all"
        print(f"  {'all':>5} {rng:>7} {_fmt(abs_rel):>8} {_fmt(d125):>8} {_fmt(valid, True):>8}")
        results[f"depth_{'40m' if limit else 'all'}"] = {"abs_rel": abs_rel, "delta_125": d125, "valid": valid}
        if limit:
            checks.append(("depth abs-rel ≤ 0.04 within 40 m", abs_rel <= 0.04))
            checks.append(("LiDAR points within 40 m with depth ≥ 90 %", valid >= 0.90))

    st = bench_stereo(data, cfg)
    results["stereo"] = st
    print("\nStereo disparity")
    print(f"  KITTI 2015 000046 D1-all: {_fmt(st['kitti2015_d1_all'], True)} (density {_fmt(st['kitti2015_density'], True)})")
    print(f"  Middlebury 2014 Motorcycle (Q) bad-2.0 non-occluded: {_fmt(st['middlebury_bad2_nonocc'], True)}"
          f" (density {_fmt(st['middlebury_density_nonocc'], True)})")
    checks.append(("KITTI 2015 D1-all ≤ 10 %", st["kitti2015_d1_all"] <= 0.10))

    ego_rows, timings = bench_egomotion(data, cfg, synthetic_frames)
    results["egomotion"] = ego_rows
    print("\nEgomotion drift (segments of 5+ frames)")
    print(f"  {'run':<44} {'t err':>8} {'r err':>12} {'fails':>5}")
    for r in ego_rows:
        print(f"  {r['name']:<44} {_fmt(r['translation_pct']):>6} % {_fmt(r['rotation_deg_per_m']):>7} °/m {r['failures']:>5}")
        checks.append((f"egomotion {r['name']}: t err ≤ 2 %", bool(r["translation_pct"] <= 2.0)))

    steps = sorted({k for t in timings for k in t})
    mean_ms = {k: float(np.mean([t.get(k, 0.0) for t in timings])) for k in steps}
    total = float(np.mean([sum(t.values()) for t in timings]))
    results["timings_ms"] = {**mean_ms, "total": total}
    print("\nGeometry step, ms per 1242×375 frame on one core (KITTI 0005 frames 1-15, mean)")
    for k in steps:
        print(f"  {k:<12} {mean_ms[k]:8.1f}")
    print(f"  {'total':<12} {total:8.1f}")
    checks.append(("geometry step ≤ 150 ms per frame", total <= 150.0))

    from mining.sources.synthetic import bench_render

    render_ms = {seq: bench_render(20, seq) for seq in ("0000", "0002")}
    results["synthetic_render_ms"] = render_ms
    print("\nSynthetic source, ms per frame (left + right + truth, 1242×375, one core, best of 20)")
    for seq, ms in render_ms.items():
        print(f"  sequence {seq}: {ms:6.1f}  ({1000 / ms:.1f} frames/s)")
    checks.append(("synthetic rendering ≥ 5 frames/s", max(render_ms.values()) <= 200.0))

    print("\nTargets")
    for name, ok in checks:
        print(f"  [{'ok' if ok else 'MISS'}] {name}")
    results["checks"] = {name: ok for name, ok in checks}
    print(f"\n(bench took {time.perf_counter() - t0:.0f} s)")
    if json_out:
        safe_files.write_file(json_out, json.dumps(results, indent=1, default=float).encode(), overwrite)
    return 0 if all(ok for _, ok in checks) else 1


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine bench geometry``'s options."""
    add_job_options(p)
    add_data_option(p)
    p.add_argument("--synthetic-frames", type=count(2), default=200, help="length of the synthetic egomotion runs")
    p.add_argument("--json", type=output_file, help="also write the results as JSON here")
    add_overwrite_option(p, "the --json file")


def run(args: argparse.Namespace) -> int:
    """``mine bench geometry``: 0 when every check passes."""
    cfg = job_config(args)
    return run_geometry_bench(Path(args.data), cfg.geometry, synthetic_frames=args.synthetic_frames,
                              json_out=args.json, overwrite=args.overwrite)
