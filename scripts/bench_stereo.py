"""The stereo proposer's share of ground-truth objects proposed, on cached synthetic frames.

The full ``mine eval synthetic`` takes minutes; the stereo proposer alone takes tens of
milliseconds a frame. This script renders frames of a synthetic sequence once, runs the
geometry stage once (disparity, depth, ground) and the COCO ONNX model once, caches them as
npz (``cache``), and then runs only the stereo proposer with config overrides over the
cache (``measure``): per split and distance bin, the share of evaluated ground-truth
detections covered by a proposal with mask IoU ≥ 0.5 (``mining.eval.funnel``'s rules, a
``proposed`` stage alone), also for the union with the cached ONNX proposals (their
masks pooled: the union's de-duplication removes only near-duplicates), plus proposals per
frame and the stereo proposer's milliseconds per frame.

    python scripts/bench_stereo.py cache --seed 0000 --n-frames 100 --stride 2 [--exact]
    python scripts/bench_stereo.py measure --seeds 0000 0001 [--exact] [--set proposals.stereo.X=V ...]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from mining.config import load_config
from mining.eval.funnel import StageFrame, bin_names, evaluate_funnel
from mining.eval.synthetic import GtFrame, gt_frame
from mining.geometry.stage import GeometryStage
from mining.proposals.make import make_proposer
from mining.proposals.stereo import StereoProposer
from mining.sources import open_source
from mining.types import FrameGeometry, GroundPlane, StereoFrame

CACHE = Path("/work/cache_stereo")
MODEL = "/work/shared/models/yolov8n-seg_int8.onnx"


def cache_dir(seed: str, n_frames: int, stride: int, exact: bool) -> Path:
    return CACHE / f"{seed}_n{n_frames}_s{stride}{'_exact' if exact else ''}"


def cache(seed: str, n_frames: int, stride: int, exact: bool) -> None:
    out = cache_dir(seed, n_frames, stride, exact)
    out.mkdir(parents=True, exist_ok=True)
    sets = ["geometry.stereo.exact_depth=true"] if exact else []
    cfg = load_config(None, sets + ['proposals.proposer="onnx"', f'proposals.onnx.model_path="{MODEL}"'])
    src = open_source("synthetic", None, n_frames=n_frames)
    plan = src.plan(seed)
    onnx = None
    for pos in range(stride // 2, len(plan), stride):
        path = out / f"{pos:04d}.npz"
        if path.exists():
            continue
        frame = src.read_frame(plan, pos)
        geom = GeometryStage(frame.calib, cfg.geometry).run(frame)  # a fresh stage: depth and ground are per frame
        if onnx is None:
            onnx = make_proposer(cfg.proposals, (frame.calib.height, frame.calib.width))
        op = onnx(frame, geom)
        gt = gt_frame(frame.truth)
        g = geom.ground
        meta = {"index": frame.index, "t_ns": frame.t_ns, "calib": vars(frame.calib),
                "ground": {"normal": None if g.normal is None else list(map(float, g.normal)), "d": float(g.d),
                           "inliers": int(g.inliers), "ok": bool(g.ok), "reason": g.reason},
                "gt": {"categories": gt.categories, "rles": [_rle_json(r) for r in gt.rles], "size": list(gt.size)},
                "onnx": [_rle_json(r) for r in op.rles]}
        np.savez_compressed(path, left=frame.left, disparity=geom.disparity, depth=geom.depth,
                            track_ids=gt.track_ids, known=gt.known, areas=gt.areas, boxes=gt.boxes, gt_depth=gt.depth,
                            onnx_boxes=np.asarray(op.boxes, np.float64), meta=np.frombuffer(json.dumps(meta).encode(), np.uint8))
        print(f"cached {path}", flush=True)


def _rle_json(r: dict) -> dict:
    c = r["counts"]
    return {"size": list(r["size"]), "counts": c.decode() if isinstance(c, bytes) else c}


def _rle(r: dict) -> dict:
    return {"size": r["size"], "counts": r["counts"].encode()}


def load(seed: str, n_frames: int, stride: int, exact: bool) -> list[tuple]:
    items = []
    for path in sorted(cache_dir(seed, n_frames, stride, exact).glob("*.npz")):
        z = np.load(path)
        meta = json.loads(z["meta"].tobytes())
        from mining.types import StereoCalib
        calib = StereoCalib(**meta["calib"])
        g = meta["ground"]
        ground = GroundPlane(None if g["normal"] is None else np.array(g["normal"]), g["d"], g["inliers"], g["ok"],
                             g["reason"])
        frame = StereoFrame("synthetic", seed, meta["index"], meta["t_ns"], z["left"], z["left"], calib)
        geom = FrameGeometry(meta["index"], meta["t_ns"], z["disparity"], z["depth"], None, None, ground)
        gt = GtFrame(z["track_ids"], z["known"], meta["gt"]["categories"], [_rle(r) for r in meta["gt"]["rles"]],
                     z["areas"], z["boxes"], z["gt_depth"], tuple(meta["gt"]["size"]))
        onnx = StageFrame([_rle(r) for r in meta["onnx"]], z["onnx_boxes"])
        items.append((frame, geom, gt, onnx))
    return items


def measure(seeds: list[str], n_frames: int, stride: int, exact: bool, sets: list[str], verbose: bool) -> dict:
    cfg = load_config(None, sets)
    proposer = StereoProposer(cfg.proposals.stereo)
    report: dict = {"sets": sets, "seeds": {}}
    for seed in seeds:
        items = load(seed, n_frames, stride, exact)
        if not items:
            raise SystemExit(f"no cache for seed {seed}: run `cache` first")
        proposer.propose(items[0][0], items[0][1])  # warm-up
        truths, stereo, union = {}, {}, {}
        ms, n_props, steps = [], [], {}
        for frame, geom, gt, onnx in items:
            t0 = time.perf_counter()
            res = proposer.propose(frame, geom)
            ms.append(1e3 * (time.perf_counter() - t0))
            for k, v in res.timings_ms.items():
                steps[k] = steps.get(k, 0.0) + v
            p = res.proposals
            n_props.append(len(p))
            truths[frame.index] = gt
            s = StageFrame(list(p.rles), np.asarray(p.boxes, np.float64).reshape(-1, 4))
            stereo[frame.index] = s
            union[frame.index] = StageFrame(s.rles + onnx.rles, np.concatenate([s.boxes, onnx.boxes.reshape(-1, 4)]))
        f = evaluate_funnel(truths, [], {"stereo": stereo, "onnx+stereo": union}, alpha=0.5, beta=0.5)
        report["seeds"][seed] = {"frames": len(items), "ms": float(np.mean(ms)), "props": float(np.mean(n_props)),
                                 "steps_ms": {k: v / len(items) for k, v in steps.items()}, "funnel": f["frames"]}
    return report


def summarise(report: dict) -> str:
    lines = [f"sets: {' '.join(report['sets']) or '(defaults)'}"]
    dist = None
    agg: dict = {}
    for seed, r in report["seeds"].items():
        fr = r["funnel"]
        dist = list(fr["all"]["distance"])
        cells = []
        for split in ("unknown", "known"):
            for stage in ("stereo", "onnx+stereo"):
                t = fr[split]["total"]
                cells.append(f"{split[0]}:{stage[:4]} {t[stage] / max(1, t['gt']):.2f}")
                for key, block in [("total", t)] + [(d, fr[split]["distance"][d]) for d in dist]:
                    a = agg.setdefault((split, stage, key), [0, 0])
                    a[0] += block[stage]
                    a[1] += block["gt"]
        lines.append(f"  {seed}: {r['frames']} fr, {r['props']:.1f} props/fr, {r['ms']:.0f} ms/fr  " + "  ".join(cells))
    tot_ms = np.mean([r["ms"] for r in report["seeds"].values()])
    tot_p = np.mean([r["props"] for r in report["seeds"].values()])
    lines.append(f"  ALL: {tot_p:.1f} props/fr, {tot_ms:.0f} ms/fr")
    head = "    " + "split/stage".ljust(22) + "total".rjust(12) + "".join(d.rjust(14) for d in dist or [])
    lines.append(head)
    for split in ("unknown", "known"):
        for stage in ("stereo", "onnx+stereo"):
            row = f"    {split + '/' + stage:22s}"
            for key in ["total"] + (dist or []):
                c, n = agg[(split, stage, key)]
                row += (f"{c / n:.3f} ({n})" if n else "-").rjust(14 if key != "total" else 12)
            lines.append(row)
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("cache")
    c.add_argument("--seed", required=True)
    m = sub.add_parser("measure")
    m.add_argument("--seeds", nargs="+", required=True)
    m.add_argument("--set", action="append", default=[])
    m.add_argument("--json", default=None)
    m.add_argument("-v", action="store_true")
    for p in (c, m):
        p.add_argument("--n-frames", type=int, default=100)
        p.add_argument("--stride", type=int, default=2)
        p.add_argument("--exact", action="store_true")
    a = ap.parse_args()
    if any(s in a.__dict__.get("seed", "") for s in ("0007", "0008", "0009", "0010", "0011")):
        raise SystemExit("held-out seed")
    if a.cmd == "cache":
        cache(a.seed, a.n_frames, a.stride, a.exact)
    else:
        for s in a.seeds:
            if int(s) >= 7:
                raise SystemExit("held-out seed")
        r = measure(a.seeds, a.n_frames, a.stride, a.exact, a.set, a.v)
        print(summarise(r))
        if a.json:
            Path(a.json).write_text(json.dumps(r, indent=1, default=float))


if __name__ == "__main__":
    main()
