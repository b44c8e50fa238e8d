"""``mine track images``: the full pipeline (geometry, proposals, tubes → score → select) over
plan positions of one sequence, in this process, written as KITTI tracking txt; the image
counterpart of the detections-only mode (``detections.py``)."""

from __future__ import annotations

import argparse
from pathlib import Path

from mining.catalog import safe_files
from mining.checks import output_folder
from mining.pipeline.arguments import add_job_options, add_overwrite_option, frame_range, job_config
from mining.pipeline.frames import frame_records
from mining.pipeline.kitti_export import write_tubes_kitti
from mining.pipeline.mine import mine_tubes
from mining.pipeline.preflight import checked_plan
from mining.proposals.make import classifiers_line
from mining.score.unary import unary_line
from mining.types import CALLS


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine track images``' options."""
    add_job_options(p)
    p.add_argument("--sequence", required=True)
    p.add_argument("--frames", type=frame_range, default=(0, None), metavar="A:B")
    p.add_argument("--out", type=output_folder, required=True, help="folder of the <sequence>.txt result")
    add_overwrite_option(p, "OUT/<sequence>.txt")


def run(args: argparse.Namespace) -> int:
    """``mine track images``: writes OUT/<sequence>.txt and prints what it mined."""
    cfg = job_config(args)
    out = Path(args.out) / f"{args.sequence}.txt"
    safe_files.check_output_file(out, args.overwrite, "--out")
    source = cfg.source.open()
    plan = checked_plan(source, cfg, args.sequence, args.frames)
    start, stop = args.frames
    stop = len(plan) if stop is None else min(stop, len(plan))
    mined = mine_tubes((r.tracking for r in frame_records(source, plan, start, stop, cfg)), cfg)
    # KITTI's 3D fields are in rectified camera 0; elsewhere they are placeholders.
    to_rect0 = source.kitti_calib(args.sequence).cam2_to_rect0 if cfg.source.dataset == "kitti" else None
    n = write_tubes_kitti(out, mined, to_rect0, observed_only=cfg.export.observed_only,
                          unclassified_as=cfg.export.unclassified_as, overwrite=args.overwrite)
    sel = [m for m in mined if m.selected]
    calls = [m.category.call for m in sel]
    print(f"{args.sequence} frames {start}:{stop}: {len(mined)} tubes, {len(sel)} selected "
          f"({', '.join(f'{calls.count(c)} {c}' for c in CALLS)}), {n} rows → {out}")
    print(classifiers_line(cfg.proposals.proposer))
    print(unary_line(cfg.score, cfg.proposals.proposer))
    return 0
