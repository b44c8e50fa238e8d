"""``mine bench looks``: does a COCO detector recognise the synthetic objects as it does real ones?

Recall@20 with the right class: the shared YOLO-seg ONNX model (``OnnxProposer``, config
``proposals.onnx``) runs on each frame; its 20 best proposals by objectness are kept; a
ground-truth object counts as recalled when one of them overlaps it with box IoU ≥ 0.5 and
has one of the object's COCO classes as its argmax over the 80 class scores. Box IoU on
both sides, because KITTI's labels are boxes only.

Which objects count is the same on both sides, after KITTI's "moderate" difficulty: box
height ≥ 25 px, at most partly occluded, at most 30 % truncated. KITTI gives occlusion and
truncation levels per label (occluded ≤ 1, truncated 0); the synthetic source gives the
exact visible mask and, through ``SyntheticSource.unoccluded``, the pixels each object would
cover if nothing hid it and its untruncated box, so "partly occluded" is at least half of
those pixels visible, truncation the share of the untruncated box outside the image, and
the synthetic protocol's 100 visible pixels apply as well.

Real reference: KITTI tracking 0005 frames 0–15 (labels: Car only). The right classes:
car → ``car``, and for a van (KITTI's Van, the synthetic van body) ``car`` or ``truck``: COCO
has no van class and its annotators put vans under either; the "car, strict" row takes
``car`` only, and the "car:<body>" rows too. A person walking or riding → ``person``; a
bicycle → ``bicycle`` or ``person`` (a cyclist's box covers the bicycle); truck → ``truck``;
bus → ``bus``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from mining.boxes import box_iou
from mining.catalog import safe_files
from mining.checks import count, input_file, output_file, output_folder
from mining.config import JobConfig
from mining.errors import MiningError
from mining.formats.coco import COCO_CLASSES
from mining.formats.kitti_tracking import read_kitti_tracking
from mining.pipeline.arguments import add_data_option, add_job_options, add_overwrite_option, default_data, job_config
from mining.proposals.onnx_yolo import OnnxProposer
from mining.proposals.yolo_seg import N_COCO
from mining.sources import open_source

TOP_K = 20  # the issue: recall among the 20 best proposals by objectness
MATCH_IOU = 0.5  # REFERENCE (evaluation protocols): a match needs box IoU ≥ 0.5
MIN_BOX_H_PX = 25.0  # KITTI object benchmark, "moderate": box height ≥ 25 px
MIN_VISIBLE_SHARE = 0.5  # ours: KITTI "partly occluded" (level ≤ 1) read as at least half visible
MAX_TRUNCATION = 0.3  # KITTI object benchmark, "moderate": truncation ≤ 30 %
MIN_VISIBLE_PX = 100  # the synthetic protocol (mining/eval/synthetic.py): smaller objects are ignored
KITTI_SEQUENCE, KITTI_FRAMES = "0005", (0, 16)  # the shared real frames with labels (SOURCES.md §1.2)
ROWS = ("car", "car, strict", "car, 25–50 px", "car, ≥ 50 px", "car:hatchback", "car:sedan", "car:estate", "car:suv", "car:van", "person", "rider",
        "bicycle", "truck", "bus")


def tally_rows(kind: str, body: str = "", height_px: float = 0.0) -> list[tuple[str, tuple[str, ...]]]:
    """The rows an object counts in, each with the COCO classes that are right there."""
    if kind == "car":
        right = ("car", "truck") if body == "van" else ("car",)
        rows = [("car", right), ("car, strict", ("car",)),
                ("car, 25–50 px" if height_px < 50 else "car, ≥ 50 px", right)]
        return rows + ([(f"car:{body}", ("car",))] if body else [])
    return [(kind, {"person": ("person",), "rider": ("person",), "bicycle": ("bicycle", "person"),
                    "truck": ("truck",), "bus": ("bus",)}[kind])]


@dataclass
class ClassTally:
    objects: int = 0
    recalled: int = 0  # right class among the top 20 at IoU ≥ 0.5
    located: int = 0  # any class
    argmax: Counter = field(default_factory=Counter)  # class of the best-overlapping top-20 proposal, when ≥ 0.5

    def row(self) -> dict:
        n = max(self.objects, 1)
        return {"objects": self.objects, "recall": self.recalled / n if self.objects else float("nan"),
                "any_class": self.located / n if self.objects else float("nan"),
                "argmax": dict(self.argmax.most_common(4))}


def _score_frame(props, boxes: np.ndarray, rows: list[list[tuple[str, tuple[str, ...]]]],
                 tallies: dict[str, ClassTally]) -> list[tuple]:
    """Count one frame's eligible objects (``boxes``; per object its ``tally_rows``); returns the
    top-20 detections (box, argmax class, objectness)."""
    order = np.argsort(-props.objectness, kind="stable")[:TOP_K]
    det_boxes = props.boxes[order].astype(np.float64)
    det_cls = [COCO_CLASSES[int(np.argmax(props.posterior[i, :N_COCO]))] for i in order]
    iou = box_iou(boxes, det_boxes) if len(boxes) and len(order) else np.zeros((len(boxes), len(order)))
    for g, obj_rows in enumerate(rows):
        hit = np.flatnonzero(iou[g] >= MATCH_IOU - 1e-9)
        for name, right in obj_rows:
            t = tallies.setdefault(name, ClassTally())
            t.objects += 1
            if len(hit):
                t.located += 1
                t.argmax[det_cls[hit[np.argmax(iou[g, hit])]]] += 1
                t.recalled += any(det_cls[j] in right for j in hit)
    return [(det_boxes[k], det_cls[k], float(props.objectness[order[k]])) for k in range(len(order))]


def _draw(image: np.ndarray, gts: list[tuple], dets: list[tuple], path: Path, overwrite: bool = False) -> None:
    """Ground truth (thin white, eligible: thick yellow) and the top-20 detections with class and score, as a
    PNG at ``path`` (``safe_files.write_file``: never through a link; an existing one replaced only with
    ``overwrite``)."""
    img = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    for box, eligible in gts:
        x0, y0, x1, y1 = (round(v) for v in box)
        cv2.rectangle(img, (x0, y0), (x1, y1), (0, 230, 255) if eligible else (255, 255, 255), 2 if eligible else 1)
    for box, cls, score in dets:
        x0, y0, x1, y1 = (round(v) for v in box)
        colour = {"car": (60, 220, 60), "person": (60, 60, 255), "bicycle": (255, 120, 0),
                  "truck": (200, 0, 200)}.get(cls, (180, 180, 180))
        cv2.rectangle(img, (x0, y0), (x1, y1), colour, 1)
        cv2.putText(img, f"{cls} {score:.2f}", (x0, max(9, y0 - 2)), cv2.FONT_HERSHEY_PLAIN, 0.8, colour, 1)
    ok, png = cv2.imencode(".png", img)
    if not ok:
        raise MiningError(f"could not encode the picture {path}")
    safe_files.write_file(path, png.tobytes(), overwrite)


def kitti_recall(data: Path, proposer: OnnxProposer, png_dir: Path | None = None,
                 overwrite: bool = False) -> dict[str, ClassTally]:
    """The figure on the real KITTI 0005 frames (labels: label_02, Car/Van/Pedestrian/Cyclist)."""
    root = data / "kitti_tracking"
    labels = read_kitti_tracking(root / "training" / "label_02" / f"{KITTI_SEQUENCE}.txt")
    src = open_source("kitti", str(root))
    plan = src.plan(KITTI_SEQUENCE)
    kind = {"Car": ("car", ""), "Van": ("car", "van"), "Pedestrian": ("person", ""), "Person_sitting": ("person", ""),
            "Cyclist": ("rider", "")}
    tallies: dict[str, ClassTally] = {}
    for pos in range(*KITTI_FRAMES):
        fr = src.read_frame(plan, pos)
        sel = (labels.frame == fr.index) & np.isin(labels.type, list(kind))
        box = labels.box[sel]
        ok = ((box[:, 3] - box[:, 1]) >= MIN_BOX_H_PX) & (labels.occluded[sel] <= 1) & (labels.truncated[sel] <= 0)
        props = proposer(fr.index, fr.left)
        rows = [tally_rows(*kind[str(t)], b[3] - b[1]) for t, b in zip(labels.type[sel][ok], box[ok])]
        rows = [[r for r in rr if not r[0].startswith("car:")] for rr in rows]  # KITTI gives no body types
        dets = _score_frame(props, box[ok], rows, tallies)
        if png_dir is not None and pos in (0, 15):
            _draw(fr.left, [(b, e) for b, e in zip(box, ok)], dets, png_dir / f"looks_kitti_{fr.index:06d}.png",
                  overwrite)
    return tallies


def synthetic_eligible(truth, unoccluded: dict, width: int, height: int) -> list[tuple]:
    """(object, eligible) for every truth object of one synthetic frame (the module docstring's rule)."""
    out = []
    for o in truth.objects:
        px = int(o.mask.sum())
        full, ubox = unoccluded.get(o.track_id, (px, None))
        h = o.box[3] - o.box[1]
        trunc = 1.0
        if ubox is not None:
            area = max((ubox[2] - ubox[0]) * (ubox[3] - ubox[1]), 1e-9)
            inside = max(0.0, min(ubox[2], width) - max(ubox[0], 0)) * max(0.0, min(ubox[3], height) - max(ubox[1], 0))
            trunc = 1.0 - inside / area
        ok = (px >= MIN_VISIBLE_PX and h >= MIN_BOX_H_PX and px >= MIN_VISIBLE_SHARE * max(full, 1)
              and trunc <= MAX_TRUNCATION)
        out.append((o, ok))
    return out


def synthetic_recall(proposer: OnnxProposer, seeds: list[str], frames: int, step: int, n_frames: int,
                     png_dir: Path | None = None, overwrite: bool = False,
                     **options) -> tuple[dict[str, ClassTally], list[float]]:
    """The figure on synthetic frames: ``frames`` positions ``step`` apart (from ``step``) of each seed;
    also the read_frame milliseconds of every frame."""
    src = open_source("synthetic", None, n_frames=n_frames, **options)
    tallies: dict[str, ClassTally] = {}
    ms = []
    for seq in seeds:
        plan = src.plan(seq)
        for k in range(frames):
            pos = step * (k + 1)
            if pos >= len(plan):
                break
            t0 = time.perf_counter()
            fr = src.read_frame(plan, pos)
            ms.append(1e3 * (time.perf_counter() - t0))
            objs = synthetic_eligible(fr.truth, src.unoccluded(plan, pos), fr.calib.width, fr.calib.height)
            rows, boxes = [], []
            for o, ok in objs:
                obj = src.scene(seq).objects[o.track_id - 1]
                kind = "rider" if o.category == "person" and obj.riding else o.category
                if ok and kind in ("car", "person", "rider", "bicycle", "truck", "bus"):
                    rows.append(tally_rows(kind, obj.shape if kind == "car" else "", o.box[3] - o.box[1]))
                    boxes.append(o.box)
            props = proposer(fr.index, fr.left)
            dets = _score_frame(props, np.array(boxes, np.float64).reshape(-1, 4), rows, tallies)
            if png_dir is not None and k in (1, frames // 2):
                _draw(fr.left, [(o.box, ok) for o, ok in objs if o.known], dets,
                      png_dir / f"looks_synthetic_{seq}_{fr.index:06d}.png", overwrite)
    return tallies, ms


def format_tallies(title: str, tallies: dict[str, ClassTally]) -> str:
    lines = [f"  {title}"]
    for name in ROWS:
        if name in tallies:
            r = tallies[name].row()
            am = ", ".join(f"{c} {n}" for c, n in r["argmax"].items())
            lines.append(f"    {name:<14} {r['objects']:6d}   {r['recall']:6.3f}   {r['any_class']:6.3f}   {am}")
    return "\n".join(lines)


def run_looks_bench(data: Path, cfg: JobConfig, model: str | None, seeds: list[str], frames: int = 34, step: int = 5,
                    n_frames: int = 200, png_dir: str | None = None, json_out: str | None = None,
                    overwrite: bool = False,
                    kitti: bool = True) -> int:
    cv2.setNumThreads(1)
    onnx = cfg.proposals.onnx
    if model:
        onnx.model_path = model
    proposer = OnnxProposer(onnx, (375, 1242))
    out = Path(png_dir) if png_dir else None
    results = {}
    print(f"recall@{TOP_K} with the right class ({Path(onnx.model_path).name}, box IoU ≥ {MATCH_IOU}; objects with "
          f"box height ≥ {MIN_BOX_H_PX:.0f} px, ≥ {MIN_VISIBLE_SHARE:.0%} visible, ≤ {MAX_TRUNCATION:.0%} truncated)")
    print(f"    {'class':<14} {'objects':>6}   {'recall':>6}   {'any cls':>6}   argmax of the best match")
    if kitti:
        tk = kitti_recall(data, proposer, out, overwrite)
        results["kitti"] = {k: v.row() for k, v in tk.items()}
        print(format_tallies(f"KITTI {KITTI_SEQUENCE} frames {KITTI_FRAMES[0]}–{KITTI_FRAMES[1] - 1}", tk))
    options = {k: v for k, v in cfg.source.options.items() if k != "n_frames"} if cfg.source.dataset == "synthetic" else {}
    ts, ms = synthetic_recall(proposer, seeds, frames, step, n_frames, out, overwrite, **options)
    results["synthetic"] = {k: v.row() for k, v in ts.items()}
    results["render_ms"] = {"min": min(ms), "median": statistics.median(ms), "frames": len(ms)}
    print(format_tallies(f"synthetic {' '.join(seeds)}: {len(ms)} frames (positions {step}, {2 * step}, …)", ts))
    print(f"  render: {min(ms):.0f} ms min, {statistics.median(ms):.0f} ms median per frame (left + right + truth); "
          f"run under `taskset -c 0` with OMP_NUM_THREADS=1 for the one-core figure")
    if json_out:
        safe_files.write_file(json_out, json.dumps(results, indent=2, default=float).encode(), overwrite)
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine bench looks``'s options."""
    add_job_options(p)
    add_data_option(p)
    p.add_argument("--model", type=input_file, default=Path(default_data()).parent / "models" / "yolov8n-seg_int8.onnx",
                   help="YOLO-seg ONNX model (default: ../shared/models/yolov8n-seg_int8.onnx)")
    p.add_argument("--seeds", nargs="+", default=["0000", "0001", "0002"], help="synthetic sequences")
    p.add_argument("--frames", type=count(), default=34, help="frames per seed")
    p.add_argument("--step", type=count(), default=5, help="plan positions between frames (the first is STEP)")
    p.add_argument("--n-frames", type=count(), default=200, help="length of the synthetic world")
    p.add_argument("--png", type=output_folder, help="write a few frames with the detections drawn to this folder "
                                                    "(made when absent)")
    p.add_argument("--no-kitti", action="store_true", help="skip the KITTI reference")
    p.add_argument("--json", type=output_file, help="also write the results as JSON here")
    add_overwrite_option(p, "the --json file and the --png pictures")


def run(args: argparse.Namespace) -> int:
    """``mine bench looks``."""
    return run_looks_bench(Path(args.data), job_config(args), args.model, args.seeds, frames=args.frames,
                           step=args.step, n_frames=args.n_frames, png_dir=args.png, json_out=args.json,
                           overwrite=args.overwrite,
                           kitti=not args.no_kitti)
