"""Cheap iteration on the recall funnel's ``proposed`` column (issue 29, scope item 1).

Two steps, so a setting can be tried in a minute instead of a full ``mine eval synthetic``:

* ``cache SEED N OUT_DIR``: render N synthetic frames once and keep, per frame, the stereo
  pair, the compact ground truth and the COCO ONNX model's raw outputs (anchors whose best
  class score is ≥ 0.001 and the prototypes) under OUT_DIR (not the repository).
* ``measure OUT_DIR SEED [SEED …] [--set KEY=VALUE …]``: per cached frame, the geometry
  stage's disparity and ground (not flow or egomotion: the proposers do not read them),
  the configured proposers (ONNX decoded from the cached outputs) and their union, then the
  funnel's rules (``evaluate_funnel`` with only a ``proposed`` stage): the share of
  evaluated ground-truth detections covered by a proposal with mask IoU ≥ 0.5, per split
  and distance bin, proposals per frame and disparity ms per frame.

Run from the repository root: ``python scripts/proposal_funnel.py measure /tmp/funnel_cache 0000 0001``
(the COCO model: ``TUBE_MINER_MODEL``, default ``../shared/models/yolov8n-seg_int8.onnx``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from mining.config import load_config
from mining.eval.funnel import StageFrame, evaluate_funnel, stage_frame
from mining.eval.synthetic import GtFrame, gt_frame
from mining.geometry.disparity import StereoMatcher
from mining.geometry.ground import estimate_ground
from mining.proposals.onnx_yolo import OnnxProposer
from mining.proposals.registry import proposer_names
from mining.proposals.union import union
from mining.proposals.yolo_seg import N_COCO, decode_predictions, plan_letterbox
from mining.sources import open_source
from mining.types import FrameGeometry, StereoCalib, StereoFrame

# the shared COCO model beside the checkout, as the tests find it
MODEL = os.environ.get("TUBE_MINER_MODEL",
                       str(Path(__file__).resolve().parents[1].parent / "shared" / "models" / "yolov8n-seg_int8.onnx"))
KEEP_SCORE = 0.001  # anchors kept in the cache: ten times below the decoder's 0.01


def _gt_json(g: GtFrame) -> dict:
    return {"track_ids": g.track_ids.tolist(), "known": g.known.tolist(), "categories": g.categories,
            "rles": [{"size": list(r["size"]), "counts": r["counts"].decode() if isinstance(r["counts"], bytes)
                      else r["counts"]} for r in g.rles],
            "areas": np.asarray(g.areas).tolist(), "boxes": g.boxes.tolist(), "depth": g.depth.tolist(),
            "size": list(g.size)}


def _gt_from_json(d: dict) -> GtFrame:
    return GtFrame(np.array(d["track_ids"], np.int64), np.array(d["known"], bool), d["categories"],
                   [{"size": r["size"], "counts": r["counts"].encode()} for r in d["rles"]],
                   np.array(d["areas"]), np.array(d["boxes"], np.float64).reshape(-1, 4),
                   np.array(d["depth"], np.float64), tuple(d["size"]))


def cache(seed: str, n: int, out: Path, stride: int) -> None:
    cfg = load_config(None, [f"proposals.onnx.model_path={MODEL}"])
    src = open_source("synthetic", None, n_frames=n)
    plan = src.plan(seed)
    d = out / seed
    d.mkdir(parents=True, exist_ok=True)
    onnx = None
    for frame in src.read(plan, 0, n):
        if frame.index % stride:
            continue
        onnx = onnx or OnnxProposer(cfg.proposals.onnx, frame_size=frame.left.shape[:2])
        pred, protos, _ = onnx.raw_outputs(frame.left)
        keep = pred[4:4 + N_COCO].max(axis=0) >= KEEP_SCORE
        np.savez(d / f"{frame.index:06d}.npz", left=frame.left, right=frame.right, pred=pred[:, keep],
                 protos=protos, t_ns=frame.t_ns, truth_depth=frame.truth.depth.astype(np.float16))
        (d / f"{frame.index:06d}.json").write_text(json.dumps(_gt_json(gt_frame(frame.truth))))
        c = frame.calib
        (d / "calib.json").write_text(json.dumps({k: getattr(c, k) for k in
                                                  ("fx", "fy", "cx", "cy", "baseline_m", "width", "height")}))
        print(f"{seed} {frame.index}", file=sys.stderr, flush=True)


def measure(root: Path, seeds: list[str], sets: list[str], max_frames: int | None) -> dict:
    cfg = load_config(None, [f"proposals.onnx.model_path={MODEL}"] + sets)
    names = proposer_names(cfg.proposals.proposer)
    truths, stages, nprop, disp_ms, per_name = {}, {}, [], [], {}
    key = 0
    for seed in seeds:
        d = root / seed
        calib = StereoCalib(**json.loads((d / "calib.json").read_text()))
        matcher = StereoMatcher(cfg.geometry.stereo)
        makers = {}
        for path in sorted(d.glob("*.npz"))[:max_frames]:
            z = np.load(path)
            idx = int(path.stem)
            frame = StereoFrame("synthetic", seed, idx, int(z["t_ns"]), z["left"], z["right"], calib)
            t0 = time.perf_counter()
            if cfg.geometry.stereo.exact_depth:
                td = z["truth_depth"].astype(np.float32)
                with np.errstate(divide="ignore", invalid="ignore"):
                    disparity = np.where(td > 0, np.float32(calib.bf) / td, np.nan).astype(np.float32)
            else:
                disparity = matcher.compute(frame.left, frame.right)
            disp_ms.append(1e3 * (time.perf_counter() - t0))
            depth = calib.depth_from_disparity(disparity)
            depth[depth > cfg.geometry.stereo.max_depth_m] = np.nan
            geom = FrameGeometry(idx, frame.t_ns, disparity, depth, None, None,
                                 estimate_ground(disparity, calib, cfg.geometry.ground))
            parts = []
            generic = cfg.proposals.onnx_generic.enabled and "onnx" in names
            for name in names + (["onnx_generic"] if generic else []):
                parts.append(_propose(name, cfg, frame, geom, z, makers))
                per_name.setdefault(name, []).append(len(parts[-1]))
            props = parts[0] if len(parts) == 1 else union(parts, cfg.proposals.union.mask_iou, cfg.proposals.union,
                                                           disparity, depth)
            nprop.append(len(props))
            truths[key] = _gt_from_json(json.loads(path.with_suffix(".json").read_text()))
            stages[key] = stage_frame(props)
            key += 1
    f = evaluate_funnel(truths, [], {"proposed": stages}, alpha=0.5, beta=0.5)
    out = {"frames": len(truths), "proposals_per_frame": float(np.mean(nprop)),
           "per_proposer": {k: float(np.mean(v)) for k, v in per_name.items()},
           "disparity_ms": float(np.median(disp_ms)), "recall": {}}
    for split in ("known", "unknown"):
        s = f["frames"][split]
        out["recall"][split] = {"all": (s["total"]["gt"], s["total"]["recall"]["proposed"])} | {
            b: (r["gt"], r["recall"]["proposed"]) for b, r in s["distance"].items()}
    return out


def _propose(name, cfg, frame, geom, z, makers):
    if name == "onnx":
        lb = plan_letterbox(cfg.proposals.onnx, frame.left.shape[:2])
        return decode_predictions(frame.index, z["pred"], z["protos"], lb, frame.left.shape[:2], cfg.proposals.onnx)
    if name == "onnx_generic":
        from mining.proposals.onnx_generic import generic_candidates

        lb = plan_letterbox(cfg.proposals.onnx, frame.left.shape[:2])
        return generic_candidates(frame.index, z["pred"], z["protos"], lb, frame.left.shape[:2], cfg.proposals.onnx,
                                  cfg.proposals.onnx_generic)
    if name not in makers:
        from mining.proposals.make import make_one

        makers[name] = make_one(name, cfg.proposals, frame.left.shape[:2])
    return makers[name](frame, geom)


def _table(res: dict) -> str:
    lines = [f"frames {res['frames']}, proposals/frame {res['proposals_per_frame']:.1f} "
             f"{ {k: round(v, 1) for k, v in res['per_proposer'].items()} }, disparity {res['disparity_ms']:.0f} ms"]
    for split, rows in res["recall"].items():
        lines.append(f"  {split:8s} " + "  ".join(f"{b}: {100 * r:.1f} % ({n})" for b, (n, r) in rows.items()))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("cache")
    c.add_argument("seed")
    c.add_argument("n", type=int)
    c.add_argument("out", type=Path)
    c.add_argument("--stride", type=int, default=2, help="keep every stride-th frame (spread over the sequence)")
    m = sub.add_parser("measure")
    m.add_argument("root", type=Path)
    m.add_argument("seeds", nargs="+")
    m.add_argument("--set", action="append", default=[])
    m.add_argument("--max-frames", type=int, default=None)
    m.add_argument("--json", type=Path, default=None)
    a = p.parse_args(argv)
    cv2.setNumThreads(1)
    if a.cmd == "cache":
        cache(a.seed, a.n, a.out, a.stride)
        return 0
    res = measure(a.root, a.seeds, a.set, a.max_frames)
    print(" ".join(a.set) or "(defaults)")
    print(_table(res))
    if a.json:
        a.json.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
