"""``mine inspect geometry``: run the geometry stage over a frame range and write its results.

Outputs, in ``out_dir``:

* ``disparity/<frame>.png`` — KITTI 16-bit disparity (value = disparity × 256, 0 = invalid);
* ``poses.txt`` — KITTI odometry poses from the chained egomotion, one row-major 3×4
  camera-to-world line per frame, the first frame the identity. A failed egomotion or a
  recording gap breaks the chain: that frame's line and all later ones are NaN (never a
  guessed identity);
* ``quality.json`` — per frame: egomotion (ok, reason, inliers, matches, RMSE, the 3×4
  relative transform), ground plane, disparity density, flow count and timings.

Each file is written under a temporary name and renamed. If a frame cannot be read, the
frames before it stay written and ``quality.json`` records the error.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from mining.catalog import safe_files
from mining.checks import output_folder
from mining.errors import MiningError
from mining.formats.disparity import disparity_png
from mining.formats.poses import poses_text
from mining.geometry.config import GeometryConfig
from mining.geometry.poses import chain_egomotion
from mining.pipeline.arguments import add_job_options, frame_range, job_config
from mining.pipeline.frames import plan_geometry
from mining.sources.base import Source
from mining.types import FrameGeometry


def frame_quality(g: FrameGeometry) -> dict[str, Any]:
    """JSON-ready summary of one frame's geometry."""
    q: dict[str, Any] = {
        "frame": g.index,
        "t_ns": g.t_ns,
        "disparity_valid": float(np.isfinite(g.disparity).mean()),
        "flow_matches": None if g.flow is None else len(g.flow),
        "timings_ms": {k: round(v, 2) for k, v in g.timings_ms.items()},
        "ground": {
            "ok": g.ground.ok,
            "reason": g.ground.reason,
            "inliers": g.ground.inliers,
            "normal": None if g.ground.normal is None else [float(x) for x in g.ground.normal],
            "d": float(g.ground.d) if g.ground.ok else None,
        },
    }
    e = g.egomotion
    q["egomotion"] = None if e is None else {
        "ok": e.ok,
        "reason": e.reason,
        "inliers": e.inliers,
        "matches": e.matches,
        "rmse_px": None if not np.isfinite(e.rmse_px) else float(e.rmse_px),
        "T_cur_prev": None if e.T_cur_prev is None else [float(x) for x in e.T_cur_prev[:3].ravel()],
    }
    return q


def inspect_geometry(
    source: Source, sequence: str, start: int, stop: int | None, cfg: GeometryConfig, out_dir: str | Path
) -> dict[str, Any]:
    """Run geometry on plan positions [start, stop) of ``sequence``; returns the summary written."""
    out = Path(out_dir)  # its files are replaced, never written through a link (safe_files.write_atomic)
    safe_files.make_folder(out, "disparity")
    plan = source.plan(sequence)
    stop = len(plan) if stop is None else min(stop, len(plan))
    frames: list[dict[str, Any]] = []
    transforms: list[np.ndarray | None] = []
    error = None
    try:
        for _, _, g, _ in plan_geometry(source, plan, start, stop, cfg):  # a recording gap breaks the chain
            safe_files.write_atomic(out, f"disparity/{g.index:06d}.png", disparity_png(g.disparity))
            frames.append(frame_quality(g))
            transforms.append(None if g.egomotion is None or not g.egomotion.ok else g.egomotion.T_cur_prev)
    except MiningError as e:
        error = str(e)
        raise
    finally:
        summary = {
            "dataset": source.dataset,
            "sequence": sequence,
            "positions": [start, stop],
            "frames": frames,
            "egomotion_failures": sum(1 for f in frames[1:] if not f["egomotion"]["ok"]),
            "error": error,
        }
        if transforms:
            safe_files.write_atomic(out, "poses.txt", poses_text(chain_egomotion(transforms)).encode())
        safe_files.write_atomic(out, "quality.json", json.dumps(summary, indent=1).encode())
    return summary


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine inspect geometry``'s options."""
    add_job_options(p)
    p.add_argument("--sequence", required=True)
    p.add_argument("--frames", type=frame_range, default=(0, None), metavar="A:B", help="plan positions [A, B)")
    p.add_argument("--out", type=output_folder, required=True, help="output folder")


def run(args: argparse.Namespace) -> int:
    """``mine inspect geometry``: writes the outputs and prints one line about them."""
    cfg = job_config(args)
    source = cfg.source.open()
    start, stop = args.frames
    summary = inspect_geometry(source, args.sequence, start, stop, cfg.geometry, args.out)
    n = len(summary["frames"])
    fails = summary["egomotion_failures"]
    print(f"{n} frames of {summary['dataset']}/{summary['sequence']} → {args.out}: "
          f"disparity/*.png, poses.txt, quality.json; egomotion failures: {fails}")
    return 0
