"""``mine bench proposals``: frames per second of the configured proposer on real KITTI 0005 frames.

Frames are read (and, for the ``stereo`` proposer, their geometry computed) first, not timed;
then the proposer runs frame by frame as the pipeline calls it, after one warm-up frame.
Loading the model is timed on its own. The torch proposer is also timed through
``propose_batch`` (``proposals.torch.batch_size`` frames per forward pass), with the time
split into its stages.

The class-agnostic ``fastsam`` and ``sam`` proposers are also timed stage by stage (``fastsam``:
network, decode; ``sam``: encoder, decoder runs, mask upsampling and filters, NMS), so the cost
of SAM's point grid (``--set proposals.sam.points_per_side=N``) shows apart from the encoder's.

``--random-weights`` lets the torch proposer be timed without a weights file: the real
maskrcnn_resnet50_fpn with random initial weights (seed 0) is saved to a temporary folder and
loaded through the proposer's own code. Weights do not change the network's cost; they only
change how many rows pass the score threshold, and random weights pass nearly every RoI, so
the mask head runs for ``max_proposals`` rows (the worst case).
"""

from __future__ import annotations

import argparse
import copy
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from mining.catalog import safe_files
from mining.checks import output_file
from mining.config import JobConfig
from mining.pipeline.arguments import add_data_option, add_job_options, add_overwrite_option, frame_range, job_config
from mining.pipeline.frames import plan_frames, plan_geometry
from mining.proposals.make import make_proposer
from mining.sources import open_source

SEQUENCE = "0005"  # KITTI tracking training sequence the benches share


def random_torch_checkpoint(folder: Path, seed: int = 0) -> Path:
    """maskrcnn_resnet50_fpn's state dict with random initial weights, saved under ``folder``."""
    import torch
    from torchvision.models.detection import maskrcnn_resnet50_fpn

    torch.manual_seed(seed)
    path = folder / f"maskrcnn_resnet50_fpn_random_seed{seed}.pt"
    torch.save(maskrcnn_resnet50_fpn(weights=None, weights_backbone=None).state_dict(), path)
    return path


def _timed(fn, *args):
    w, c = time.perf_counter(), time.process_time()
    out = fn(*args)
    return out, time.perf_counter() - w, time.process_time() - c


def bench_proposer(cfg: JobConfig, items: list) -> dict:
    """Load time and per-frame speed of ``cfg.proposals.proposer`` over (frame, geometry) items."""
    frame0 = items[0][0]
    proposer, load_s, _ = _timed(make_proposer, cfg.proposals, (frame0.calib.height, frame0.calib.width))
    proposer(*items[0])  # warm-up: first-call allocations, lazy sessions
    counts, wall, cpu = [], 0.0, 0.0
    for frame, geometry in items[1:]:
        p, w, c = _timed(proposer, frame, geometry)
        counts.append(len(p))
        wall += w
        cpu += c
    n = len(items) - 1
    return {"mode": "per frame", "frames": n, "load_s": load_s, "wall_s": wall, "cpu_s": cpu,
            "fps": n / wall, "proposals_per_frame": float(np.mean(counts))}


def bench_torch_batched(cfg: JobConfig, items: list) -> dict:
    from mining.proposals.mprcnn_torch import TorchProposer

    model = TorchProposer(cfg.proposals.torch)
    b = cfg.proposals.torch.batch_size
    model(items[0][0].index, items[0][0].left)  # warm-up
    rest = items[1:]
    stages: dict[str, float] = {}
    wall = cpu = 0.0
    counts = []
    for s in range(0, len(rest), b):
        chunk = rest[s:s + b]
        out, w, c = _timed(model.propose_batch, [f.index for f, _ in chunk], [f.left for f, _ in chunk])
        wall += w
        cpu += c
        counts.extend(len(p) for p in out)
        for k, v in model.last_timings_ms.items():
            stages[k] = stages.get(k, 0.0) + v
    n = len(rest)
    return {"mode": f"batch {b}", "frames": n, "wall_s": wall, "cpu_s": cpu, "fps": n / wall,
            "proposals_per_frame": float(np.mean(counts)),
            "ms_per_frame": {k: v / n for k, v in stages.items()}, "device": str(model.device)}


def bench_stages(cfg: JobConfig, items: list, name: str) -> dict:
    """Per-frame time of the ``fastsam`` or ``sam`` proposer split into its stages (``last_timings_ms``)."""
    frame0 = items[0][0]
    if name == "fastsam":
        from mining.proposals.fastsam import FastSamProposer

        model = FastSamProposer(cfg.proposals.fastsam, frame_size=(frame0.calib.height, frame0.calib.width))
        mode = "stages"
    else:
        from mining.proposals.sam import SamProposer

        model = SamProposer(cfg.proposals.sam)
        mode = f"grid {cfg.proposals.sam.points_per_side}²"
    model(frame0.index, frame0.left)  # warm-up
    stages: dict[str, float] = {}
    wall = cpu = 0.0
    counts = []
    for frame, _ in items[1:]:
        out, w, c = _timed(model, frame.index, frame.left)
        wall += w
        cpu += c
        counts.append(len(out))
        for k, v in model.last_timings_ms.items():
            stages[k] = stages.get(k, 0.0) + v
    n = len(items) - 1
    return {"mode": mode, "frames": n, "wall_s": wall, "cpu_s": cpu, "fps": n / wall,
            "proposals_per_frame": float(np.mean(counts)), "ms_per_frame": {k: v / n for k, v in stages.items()}}


def run_proposals_bench(data: Path, cfg: JobConfig, frames: tuple[int, int | None] = (0, 9),
                        random_weights: bool = False, json_path: str | None = None, overwrite: bool = False) -> int:
    cfg = copy.deepcopy(cfg)
    names = [n.strip() for n in cfg.proposals.proposer.split("+") if n.strip()]
    source = open_source("kitti", str(data / "kitti_tracking"))
    plan = source.plan(SEQUENCE)
    a, b = frames
    b = len(plan) if b is None else min(b, len(plan))
    if b - a < 2:
        raise SystemExit("mine bench proposals: need at least 2 frames (one warms up)")
    if "stereo" in names:
        items = [(f, g) for _, f, g, _ in plan_geometry(source, plan, a, b, cfg.geometry)]
    else:
        items = [(f, None) for _, f, _ in plan_frames(source, plan, a, b)]
    with tempfile.TemporaryDirectory() as tmp:
        if "torch" in names and random_weights and not cfg.proposals.torch.model_path:
            cfg.proposals.torch.model_path = str(random_torch_checkpoint(Path(tmp)))
        rows = [bench_proposer(cfg, items)]
        if names == ["torch"]:
            rows.append(bench_torch_batched(cfg, items))
        if names in (["fastsam"], ["sam"]):
            rows.append(bench_stages(cfg, items, names[0]))
    h, w = items[0][0].left.shape[:2]
    title = f"proposer {cfg.proposals.proposer} on KITTI {SEQUENCE} frames {a}:{b} ({w}×{h}; first frame warms up)"
    if "torch" in names:
        t = cfg.proposals.torch
        title += (f"\n  torch: device {t.device}, {t.num_threads or 'default'} thread(s), input {t.min_size}/"
                  f"{t.max_size}, {t.rpn_post_nms_top_n} RoIs, ≤ {t.max_proposals} proposals"
                  f"{', random weights' if random_weights else ''}")
    if "sam" in names:
        s = cfg.proposals.sam
        title += (f"\n  sam: {s.points_per_side}×{s.points_per_side} grid ({s.points_per_side ** 2} prompts), "
                  f"input {s.input_size}, {s.points_per_batch} prompts a decoder run where the export takes a batch, "
                  f"device {s.device}")
    print(title)
    print(f"  {'mode':<10} {'frames':>6} {'frames/s':>9} {'s/frame':>8} {'CPU s/frame':>11} {'proposals':>9}  load / stages")
    for r in rows:
        extra = f"load {r['load_s']:.1f} s" if "load_s" in r else \
            ", ".join(f"{k} {v:.0f} ms" for k, v in r.get("ms_per_frame", {}).items())
        print(f"  {r['mode']:<10} {r['frames']:>6} {r['fps']:>9.3f} {r['wall_s'] / r['frames']:>8.2f} "
              f"{r['cpu_s'] / r['frames']:>11.2f} {r['proposals_per_frame']:>9.1f}  {extra}")
    if json_path:
        safe_files.write_file(json_path, json.dumps({"proposer": cfg.proposals.proposer, "frames": [a, b],
                                                     "random_weights": random_weights, "rows": rows}, indent=2).encode(),
                              overwrite)
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine bench proposals``'s options."""
    add_job_options(p)
    add_data_option(p)
    p.add_argument("--frames", type=frame_range, default=(0, 9), metavar="A:B",
                   help="KITTI 0005 frames [A, B), the first warms up")
    p.add_argument("--random-weights", action="store_true",
                   help="torch without proposals.torch.model_path: random initial weights (speed only)")
    p.add_argument("--json", type=output_file, help="also write the results as JSON here")
    add_overwrite_option(p, "the --json file")


def run(args: argparse.Namespace) -> int:
    """``mine bench proposals``."""
    return run_proposals_bench(Path(args.data), job_config(args), frames=args.frames,
                               random_weights=args.random_weights, json_path=args.json, overwrite=args.overwrite)
