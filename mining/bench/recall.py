"""``mine eval recall``: proposal recall@N (box IoU > 0.5, ``mining/eval/recall.py``) for known
and unknown objects: of the configured proposer run over KITTI frames (with ``--funnel`` also
the recall funnel of the mined tubes, ``funnel.py``), or of proposal JSON files laid out like
the RobotCar labels of 4D-GVT."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mining.bench.funnel import run_kitti_funnel
from mining.catalog import safe_files
from mining.checks import input_file, input_folder, output_file
from mining.config import JobConfig
from mining.eval.funnel import format_funnel
from mining.eval.recall import format_recall, kitti_ground_truth, recall_at_n
from mining.formats.kitti_tracking import KittiTrackingRows, read_kitti_tracking
from mining.formats.oxford_labels import read_oxford_labels
from mining.pipeline.arguments import add_job_options, add_overwrite_option, frame_range, job_config
from mining.pipeline.frames import frame_records
from mining.pipeline.preflight import checked_plan
from mining.proposals.precomputed import read_proposal_json
from mining.sources.base import Source
from mining.types import SequencePlan


def oxford_recall(labels: str | Path, proposals: str | Path) -> tuple[int, dict]:
    """The number of labelled RobotCar frames under ``labels`` and recall@N of the proposal
    files under ``proposals``, each at its label file's path below the label folder
    (``<traversal>_sub_<NNNN>/postproc_<frame>.json``)."""
    frames = read_oxford_labels(labels)
    props, boxes, known = [], [], []
    for lf in frames:
        rel = lf.path.relative_to(lf.path.parents[1])
        props.append(read_proposal_json(Path(proposals) / rel, lf.frame))
        boxes.append(lf.boxes)
        known.append(lf.known)
    return len(frames), recall_at_n(props, boxes, known)


def kitti_recall(source: Source, plan: SequencePlan, start: int, stop: int, cfg: JobConfig,
                 rows: KittiTrackingRows, funnel: bool = False) -> tuple[dict, dict | None]:
    """Recall@N of the job's proposer over plan positions [start, stop) against the KITTI labels
    ``rows``, and with ``funnel`` the recall funnel of the tubes mined from them (else None)."""
    if funnel:
        props, frames, _, stages = run_kitti_funnel(source, plan, start, stop, cfg, rows)
    else:
        props, frames, stages = [], [], None
        for rec in frame_records(source, plan, start, stop, cfg):
            props.append(rec.proposals)
            frames.append(rec.frame.index)
    boxes, known = kitti_ground_truth(rows, frames)
    return recall_at_n(props, boxes, known), stages


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine eval recall``'s options."""
    add_job_options(p)
    p.add_argument("--sequence", help="KITTI: run the configured proposer on this sequence")
    p.add_argument("--frames", type=frame_range, default=(0, None), metavar="A:B")
    p.add_argument("--labels", type=input_file,
                   help="KITTI label_02 file (default: <root>/training/label_02/<sequence>.txt)")
    p.add_argument("--oxford-labels", type=input_folder, help="RobotCar: the 4D-GVT labels_4dgvt folder")
    p.add_argument("--proposals-json", type=input_folder,
                   help="RobotCar: proposal JSON files laid out like the label files")
    p.add_argument("--funnel", action="store_true", help="KITTI: also mine tubes and print the recall funnel "
                                                          "(proposed → observed → candidate → selected, box IoU "
                                                          "≥ 0.5, per distance and height bin)")
    p.add_argument("--json", type=output_file, default=None, metavar="PATH",
                   help="KITTI: also write recall@N (and the funnel) as JSON here")
    add_overwrite_option(p, "the --json file")


def run(args: argparse.Namespace) -> int:
    """``mine eval recall``: the recall table (and the funnel) on standard output."""
    if args.oxford_labels:
        n, recall = oxford_recall(args.oxford_labels, args.proposals_json)
        print(f"Proposal recall (box IoU > 0.5) on {n} labelled RobotCar frames")
        print(format_recall(recall))
        return 0
    cfg = job_config(args)
    source = cfg.source.open()
    plan = checked_plan(source, cfg, args.sequence, args.frames)
    start, stop = args.frames
    stop = len(plan) if stop is None else min(stop, len(plan))
    labels = Path(args.labels) if args.labels else Path(cfg.source.root) / "training" / "label_02" / f"{args.sequence}.txt"
    rows = read_kitti_tracking(labels)
    recall, funnel = kitti_recall(source, plan, start, stop, cfg, rows, funnel=args.funnel)
    print(f"Proposal recall (box IoU > 0.5), {cfg.proposals.proposer} proposer, {args.sequence} frames {start}:{stop}")
    print(format_recall(recall))
    if funnel is not None:
        print(format_funnel(funnel))
    if args.json:
        doc = {"sequence": args.sequence, "frames": [start, stop], "proposer": cfg.proposals.proposer,
               "recall_at_n": recall} | ({"funnel": funnel} if funnel is not None else {})
        safe_files.write_file(args.json, json.dumps(doc, indent=1).encode(), args.overwrite)
    return 0
