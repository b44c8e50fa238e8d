"""``mine bench classify``: calibrate and measure known / unknown / unclassified (issue 10).

Three steps, each on data named for it, so nothing is tuned on what it is scored on:

1. **Detectability** (``proposals.union.detect_h50_px``, ``detect_log_scale``): for every
   labelled COCO-class object of the *training* data — KITTI 0005 frames 0–15 (label_02:
   Car, Van, Truck, Pedestrian, Person_sitting, Cyclist, Tram) and the synthetic training
   seeds' known objects — whether a learned proposal covers it (box IoU ≥ 0.5, the learned
   proposer alone, at its own low score threshold), against the object's box height. A
   maximum-likelihood logistic in ln(height) is the weight a class-agnostic proposal that no
   learned proposal covers gives to "unknown" (``mining.proposals.union``).
2. **Known margin** (``score.known_margin.reference``): the training seeds mined with the job's
   proposer (``onnx+stereo``); every selected tube on a known or unknown object (the
   renderer's truth, ``evaluate_synthetic``'s tube split) is decided again for each margin
   of a grid; the margin with the best balanced accuracy (mean of the known-called-known and
   unknown-called-unknown shares) is reported beside the paper's 0. A margin other than 0 is
   worth taking only when it wins by more than one tube's share on the training seeds.
3. **Targets** on held-out data: a synthetic seed not among the training seeds (the
   issue's shares, clutter, unknown frame and tube recall) and KITTI 0005 (the share of tubes
   on labelled cars called ``car``).
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

from mining.bench.synthetic import run_synthetic
from mining.boxes import box_iou
from mining.catalog import safe_files
from mining.checks import count, output_file
from mining.config import JobConfig
from mining.eval.synthetic import SyntheticEvalProtocol, gt_frame
from mining.formats.kitti_tracking import read_kitti_tracking
from mining.pipeline.arguments import add_data_option, add_job_options, add_overwrite_option, job_config
from mining.pipeline.frames import frame_records
from mining.pipeline.mine import mine_tubes
from mining.proposals.onnx_yolo import OnnxProposer
from mining.sources import open_source
from mining.sources.kitti import KittiTrackingSource
from mining.score.category import decide
from mining.types import MinedTube

KITTI_COCO_TYPES = ("Car", "Van", "Truck", "Pedestrian", "Person_sitting", "Cyclist", "Tram")  # COCO: car, truck, person, bicycle, train
COVER_IOU = 0.5  # ours: box IoU at which a learned proposal covers an object (KITTI has boxes only)
MARGIN_GRID = tuple(np.round(np.arange(0.0, 3.01, 0.25), 2))  # ln-ratio margins tried (0 = the paper's argmax; never negative: mining/score/call.py)


# --- 1. detectability -----------------------------------------------------------------------

def _covered(gt_boxes: np.ndarray, prop_boxes: np.ndarray) -> np.ndarray:
    if len(gt_boxes) == 0:
        return np.zeros(0, bool)
    if len(prop_boxes) == 0:
        return np.zeros(len(gt_boxes), bool)
    return box_iou(gt_boxes, prop_boxes).max(axis=1) >= COVER_IOU


def kitti_samples(root: Path, sequence: str, frames: range, cfg: JobConfig) -> tuple[np.ndarray, np.ndarray]:
    """(box heights, covered) of KITTI's labelled COCO-class objects under the learned proposer."""
    src = KittiTrackingSource(str(root))
    plan = src.plan(sequence)
    labels = read_kitti_tracking(root / "training" / "label_02" / f"{sequence}.txt")
    proposer = OnnxProposer(cfg.proposals.onnx, frame_size=(plan.calib.height, plan.calib.width))
    heights, covered = [], []
    for pos in frames:
        frame = src.read_frame(plan, pos)
        keep = (labels.frame == frame.index) & np.isin(labels.type, KITTI_COCO_TYPES)
        gt = labels.box[keep]
        props = proposer(frame.index, frame.left)
        heights.append(gt[:, 3] - gt[:, 1])
        covered.append(_covered(gt, props.boxes.astype(np.float64)))
    return np.concatenate(heights), np.concatenate(covered)


def synthetic_samples(seeds: Sequence[str], n_frames: int, cfg: JobConfig, step: int = 5,
                      min_visible_px: int = SyntheticEvalProtocol.min_visible_px) -> tuple[np.ndarray, np.ndarray]:
    """(box heights, covered) of the synthetic known objects (every ``step``-th frame)."""
    heights, covered = [], []
    for seed in seeds:
        src = open_source("synthetic", None, n_frames=n_frames)
        plan = src.plan(seed)
        proposer = OnnxProposer(cfg.proposals.onnx, frame_size=(plan.calib.height, plan.calib.width))
        for pos in range(0, len(plan), step):
            frame = src.read_frame(plan, pos)
            gt = gt_frame(frame.truth)
            keep = gt.known & (gt.areas >= min_visible_px)
            boxes = gt.boxes[keep]
            props = proposer(frame.index, frame.left)
            heights.append(boxes[:, 3] - boxes[:, 1])
            covered.append(_covered(boxes, props.boxes.astype(np.float64)))
    return np.concatenate(heights), np.concatenate(covered)


def fit_detectability(heights: np.ndarray, covered: np.ndarray) -> tuple[float, float]:
    """Maximum-likelihood (h50, log scale) of P(covered) = 1 / (1 + exp(−(ln h − ln h50) / s))."""
    x = np.log(np.maximum(heights, 1.0))
    y = covered.astype(np.float64)

    def nll(theta):
        mu, log_s = theta
        z = (x - mu) / np.exp(log_s)
        return float(np.sum(np.logaddexp(0, -z) * y + np.logaddexp(0, z) * (1 - y)))

    res = minimize(nll, x0=[np.log(20.0), np.log(0.3)], method="Nelder-Mead")
    return float(np.exp(res.x[0])), float(np.exp(res.x[1]))


def _by_height(heights: np.ndarray, covered: np.ndarray) -> list[str]:
    edges = [0, 10, 15, 20, 30, 50, 100, 1000]
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (heights >= lo) & (heights < hi)
        if m.any():
            out.append(f"{lo}–{hi} px: {covered[m].mean():.2f} of {int(m.sum())}")
    return out


# --- 2. margin ------------------------------------------------------------------------------

def tube_calls(mined: Sequence[MinedTube], split: dict) -> list[tuple[str, np.ndarray | None]]:
    """(truth split, accumulated posterior or None) per selected tube on a known or unknown object."""
    return [(split[m.tube.tube_id], m.category.posterior) for m in mined
            if m.selected and split.get(m.tube.tube_id) in ("known", "unknown")]


def balanced_accuracy(calls: Sequence[tuple[str, np.ndarray | None]], margin: float) -> tuple[float, float, float]:
    """(balanced accuracy, known-called-known share, unknown-called-unknown share) at ``margin``."""
    hit = {"known": [], "unknown": []}
    for truth, post in calls:
        called = None if post is None else decide(post, margin)[0]
        hit[truth].append(called is (truth == "known"))
    k = float(np.mean(hit["known"])) if hit["known"] else float("nan")
    u = float(np.mean(hit["unknown"])) if hit["unknown"] else float("nan")
    return float(np.nanmean([k, u])), k, u


# --- 3. KITTI cars called car ---------------------------------------------------------------

def kitti_car_calls(root: Path, sequence: str, frames: range, cfg: JobConfig) -> dict:
    """Selected tubes on labelled cars (box IoU ≥ 0.5 in at least half their observed frames) and their calls."""
    src = KittiTrackingSource(str(root))
    plan = src.plan(sequence)
    mined = mine_tubes((r.tracking for r in frame_records(src, plan, frames.start, frames.stop, cfg)), cfg)
    labels = read_kitti_tracking(root / "training" / "label_02" / f"{sequence}.txt")
    cars = {int(f): labels.box[(labels.frame == f) & (labels.type == "Car")] for f in np.unique(labels.frame)}
    on_car, called = 0, {"car": 0, "other known": 0, "unknown": 0, "clutter": 0, "unclassified": 0}
    for m in mined:
        if not m.selected:
            continue
        obs = [f for f in m.tube.frames if f.observed]
        hits = sum(1 for f in obs if len(cars.get(f.frame, [])) and
                   box_iou(f.box[None].astype(np.float64), cars[f.frame]).max() >= COVER_IOU)
        if not obs or hits * 2 < len(obs):
            continue
        on_car += 1
        c = m.category
        key = c.call if c.call != "known" else "car" if c.category == "car" else "other known"
        called[key] += 1
    return {"tubes_on_cars": on_car, "called": called, "car_share": called["car"] / on_car if on_car else float("nan"),
            "selected": sum(m.selected for m in mined)}


# --- the union's mask choice ----------------------------------------------------------------

def mask_choice(seeds: Sequence[str], n_frames: int, cfg: JobConfig, step: int = 5) -> dict:
    """For each learned/stereo pair the union merges: the truth IoU of the learned mask, of the
    stereo mask and of the one the depth rule keeps (best-matching truth object of either)."""
    from mining.masks import mask_iou
    from mining.pipeline.frames import plan_geometry
    from mining.proposals.make import make_one
    from mining.proposals.union import baseline_focal, depth_agreement

    union_cfg = cfg.proposals.union
    rows = []
    for seed in seeds:
        src = open_source("synthetic", None, n_frames=n_frames)
        plan = src.plan(seed)
        size = (plan.calib.height, plan.calib.width)
        learned, stereo = make_one("onnx", cfg.proposals, size), make_one("stereo", cfg.proposals, size)
        for pos, frame, geom, _ in plan_geometry(src, plan, 0, len(plan), cfg.geometry):
            if pos % step:
                continue
            gt = gt_frame(frame.truth)
            a, b = learned(frame, geom), stereo(frame, geom)
            if not len(a) or not len(b) or not len(gt.rles):
                continue
            pair = mask_iou(a.rles, b.rles)
            bf = baseline_focal(geom.disparity, geom.depth)
            ta, tb = mask_iou(a.rles, gt.rles), mask_iou(b.rles, gt.rles)
            for i in range(len(a)):
                j = int(np.argmax(pair[i]))
                if pair[i, j] <= union_cfg.mask_iou:
                    continue
                g = int(np.argmax(np.maximum(ta[i], tb[j])))
                da, db = depth_agreement(a.rles[i], b.rles[j], geom.disparity, union_cfg, bf)
                rows.append((ta[i, g], tb[j, g], tb[j, g] if db > da + union_cfg.better_mask_margin else ta[i, g], da, db))
    r = np.asarray(rows, np.float64).reshape(-1, 5)
    if not len(r):
        return {"pairs": 0}
    better = np.abs(r[:, 0] - r[:, 1]) > 0.02
    right = (r[better, 2] == r[better, :2].max(axis=1)).mean() if better.any() else float("nan")
    by_margin = {m: float(np.where(r[:, 4] > r[:, 3] + m, r[:, 1], r[:, 0]).mean()) for m in (0.0, 0.1, 0.2, 0.3, 0.4)}
    return {"pairs": len(r), "learned": float(r[:, 0].mean()), "stereo": float(r[:, 1].mean()),
            "rule": float(r[:, 2].mean()), "oracle": float(r[:, :2].max(axis=1).mean()),
            "right_choice": float(right), "differing_pairs": int(better.sum()), "rule_by_margin": by_margin}


# --- the bench ------------------------------------------------------------------------------

def run_classify_bench(data: Path, cfg: JobConfig, train_seeds: Sequence[str] = ("0000", "0001", "0002"),
                       test_seed: str = "0007", n_frames: int = 200, train_frames: int = 100,
                       json_out: str | None = None, overwrite: bool = False) -> int:
    t0 = time.perf_counter()
    root = data / "kitti_tracking"
    doc: dict = {"proposer": cfg.proposals.proposer, "train_seeds": list(train_seeds), "test_seed": test_seed}
    print(f"1. Detectability of COCO-class objects by the learned proposer (covered: a proposal at box IoU ≥ {COVER_IOU})")
    hk, ck = kitti_samples(root, "0005", range(16), cfg)
    hs, cs = synthetic_samples(train_seeds, train_frames, cfg)
    for name, (h, c) in (("KITTI 0005 frames 0–15", (hk, ck)), (f"synthetic seeds {', '.join(train_seeds)}", (hs, cs))):
        print(f"  {name}: {len(h)} objects, covered {c.mean():.3f}; " + "; ".join(_by_height(h, c)))
    h50, scale = fit_detectability(np.concatenate([hk, hs]), np.concatenate([ck, cs]))
    h50k, scalek = fit_detectability(hk, ck) if 0 < ck.sum() < len(ck) else (float("nan"), float("nan"))
    print(f"  fit (both): detect_h50_px = {h50:.1f}, detect_log_scale = {scale:.2f}   "
          f"(KITTI alone: {h50k:.1f}, {scalek:.2f}; config now {cfg.proposals.union.detect_h50_px:g}, "
          f"{cfg.proposals.union.detect_log_scale:g})")
    doc["detectability"] = {"h50_px": h50, "log_scale": scale, "kitti_only": [h50k, scalek],
                            "kitti": {"objects": len(hk), "covered": float(ck.mean())},
                            "synthetic": {"objects": len(hs), "covered": float(cs.mean())}}

    print(f"\n2. Known margin on the training seeds ({train_frames} frames each, proposer {cfg.proposals.proposer})")
    calls = []
    for seed in train_seeds:
        mined, res = run_synthetic(seed, train_frames, cfg)
        calls += tube_calls(mined, res["tube_split"])
        print(f"  seed {seed}: {res['tubes']['known']} tubes on known, {res['tubes']['unknown']} on unknown objects "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)
    grid = {m: balanced_accuracy(calls, m) for m in MARGIN_GRID}
    best = max(grid, key=lambda m: (grid[m][0], -abs(m)))
    n_known = sum(t == "known" for t, _ in calls)
    n_unknown = len(calls) - n_known
    one_tube = 0.5 / max(1, min(n_known, n_unknown))
    chosen = best if grid[best][0] - grid[0.0][0] > one_tube else 0.0
    print(f"  {n_known} tubes on known, {n_unknown} on unknown objects; balanced accuracy at margin 0 (paper): "
          f"{grid[0.0][0]:.3f} (known {grid[0.0][1]:.3f}, unknown {grid[0.0][2]:.3f}); best {best:+.2f}: "
          f"{grid[best][0]:.3f} (known {grid[best][1]:.3f}, unknown {grid[best][2]:.3f}) → margin {chosen:+.2f}")
    doc["margin"] = {"grid": {str(m): v for m, v in grid.items()}, "best": best, "chosen": chosen,
                     "tubes": {"known": n_known, "unknown": n_unknown}}

    mc = mask_choice(train_seeds, train_frames, cfg)
    if mc["pairs"]:
        print(f"\n   Merged learned/stereo pairs on the training seeds: {mc['pairs']}; mean truth IoU: learned mask "
              f"{mc['learned']:.3f}, stereo mask {mc['stereo']:.3f}, the depth rule's choice {mc['rule']:.3f} "
              f"(the better of the two {mc['oracle']:.3f}); where they differ (> 0.02, {mc['differing_pairs']} pairs) "
              f"the rule picks the better one in {100 * mc['right_choice']:.0f} %")
    doc["mask_choice"] = mc

    print(f"\n3. Held out: synthetic seed {test_seed}, {n_frames} frames; KITTI 0005 frames 0–15 "
          f"(config margin {cfg.score.known_margin.reference:+.2f})")
    mined, res = run_synthetic(test_seed, n_frames, cfg)
    t = res["tubes"]
    ev = t["evaluated"]
    line = (f"  synthetic {test_seed}: {ev} evaluated; on known {t['known']} → {100 * t['known_called_known_share']:.0f} % "
            f"called known; on unknown {t['unknown']} → {100 * t['unknown_called_unknown_share']:.0f} % called unknown; "
            f"clutter {100 * t['clutter_share']:.0f} %; unknown frame recall {res['unknown']['frame_recall']:.3f}, "
            f"tube recall {res['unknown']['tube_recall']:.3f}")
    print(line)
    kitti = kitti_car_calls(root, "0005", range(16), cfg)
    print(f"  KITTI 0005: {kitti['tubes_on_cars']} selected tubes on labelled cars, called {kitti['called']}: "
          f"{100 * kitti['car_share']:.0f} % car")
    doc["held_out"] = {"synthetic": {k: v for k, v in res.items() if k not in ("truths", "tube_split")}, "kitti": kitti}
    print(f"  ({time.perf_counter() - t0:.0f} s)")
    if json_out:
        text = json.dumps(doc, indent=1, default=lambda x: x.item() if isinstance(x, np.generic) else str(x))
        safe_files.write_file(json_out, text.encode(), overwrite)
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine bench classify``'s options."""
    add_job_options(p)
    add_data_option(p)
    p.add_argument("--train-seeds", nargs="+", default=["0000", "0001", "0002"], help="synthetic training seeds")
    p.add_argument("--train-frames", type=count(), default=100, help="frames per training seed")
    p.add_argument("--test-seed", default="0007", help="the held-out synthetic seed")
    p.add_argument("--frames", type=count(), default=200, help="frames of the held-out seed")
    p.add_argument("--json", type=output_file, help="also write the results as JSON here")
    add_overwrite_option(p, "the --json file")


def run(args: argparse.Namespace) -> int:
    """``mine bench classify``."""
    return run_classify_bench(Path(args.data), job_config(args), train_seeds=args.train_seeds,
                              test_seed=args.test_seed, n_frames=args.frames, train_frames=args.train_frames,
                              json_out=args.json, overwrite=args.overwrite)
