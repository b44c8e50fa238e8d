"""``mine bench scale``: per-stage rates on one core, and what they project for a long job on a cluster.

Measured here, in this process pinned to one core (OpenCV single-threaded), as CPU seconds
(``time.process_time``) per frame over ``--frames`` frames of the job's source (default: the
synthetic source at RobotCar's 1280×960):

* **read** — the source's read and decode of a stereo pair (for the synthetic source a render,
  which a real job does not pay: ``--config jobs/oxford.toml --root …`` times the RobotCar
  reader's PNG decode, demosaic and undistortion);
* **geometry** — disparity, depth, features, egomotion, ground, flow (``GeometryStage``);
* **model proposals** — the proposer's network parts (``FrameProposer.propose_images``): the
  part a proposal stage runs on GPUs; absent for a stereo-only job;
* **frame proposals** — the stereo / json parts and the union (``FrameProposer.finish``);
* **localise** — 3D localisation, the geometric filter, the pose chain (``FrameLoop.step``);
* **tubes** — tube generation, linking, scores, classes and co-selection over the frames;
  **tubes: context** — the same again for the frames a window tracks beyond its core
  (``window.context_before + context_after`` over ``window.core``: 0.6 by default), which
  a short measurement in one window does not pay;
* **end to end** — a whole job in this process (``LocalExecutor``: read, observe, cache,
  track, parts, stitch, the catalogue's files), as the marginal cost of a frame: jobs of
  ``--frames`` and of 2 frames, (T_n − T_2) / (n − 2); the figure the projection uses.
  The stages are timed from the second frame on (the first pays one-off costs).

The projection for ``--project-frames`` frames (default 806,000: 14 h of RobotCar at 16 Hz) on
``--cpus`` cores and ``--gpus`` GPUs takes the slower of the CPU side (end-to-end CPU seconds
a frame, less the model part where GPUs run it, over the cores times ``--efficiency``) and the
GPU side (frames over GPUs times the model's frames/s a GPU: measured with ``--gpu-fps``
absent only where CUDA is present, otherwise an assumption printed as such). Every
assumption is printed beside the figure; ``--chart`` draws hours against cluster size.
"""

from __future__ import annotations

import argparse
import copy
import io
import json
import os
import platform
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mining.checks import count, output_file, real
from mining.config import JobConfig
from mining.errors import ConfigError
from mining.catalog import safe_files
from mining.pipeline.arguments import add_job_options, add_overwrite_option, job_config

ROBOTCAR_FRAMES = 806_000  # issue 30: 14 h of Oxford RobotCar stereo at 16 Hz
ROBOTCAR_SIZE = (960, 1280)  # Bumblebee XB3 frames, height × width
SCALING_EFFICIENCY = 0.90  # ours: `mine bench pipeline` measured 89–91 % from 1 to 2 workers (docs/RESULTS.md)
ASSUMED_GPU_FPS = 10.0  # ours: an assumption, not a measurement — Mask R-CNN R50-FPN at ~1333×1000 on one data-centre GPU, batched
CONTEXT_ROW = "tubes: context"  # the tube step again over the neighbours' frames of each window
END_TO_END_BASE = 2  # issue 30's method: marginal cost (T_n − T_2) / (n − 2), so one-off costs do not count
CHART_CORES = (8, 16, 32, 64, 128, 256, 512)  # the chart's x axis
CHART_GPUS = (0, 1, 2, 4, 8)  # GPUs per cluster, one line each


@dataclass
class StageRates:
    """CPU seconds a frame per stage on one core, and the end-to-end figure."""

    frames: int
    size: tuple[int, int]  # height, width
    proposer: str
    seconds: dict[str, float] = field(default_factory=dict)  # stage → CPU s a frame
    end_to_end: float = 0.0  # CPU s a frame, a whole job in this process

    @property
    def model(self) -> float:
        return self.seconds.get("model proposals", 0.0)

    @property
    def rest(self) -> float:
        """The stages a proposal stage leaves on the CPUs."""
        return sum(v for k, v in self.seconds.items() if k != "model proposals")


@dataclass(frozen=True)
class Cluster:
    cpus: int
    gpus: int
    efficiency: float = SCALING_EFFICIENCY


def project_hours(frames: int, cpu_s_per_frame: float, model_s_per_frame: float, cluster: Cluster,
                  gpu_fps: float | None, rest_s_per_frame: float = 0.0) -> dict[str, float]:
    """Hours for ``frames``: the CPU side and, where GPUs run the model part, the GPU side; the job
    takes the slower. Without GPUs the model part runs on the CPUs (``cpu_s_per_frame`` includes it).
    ``rest_s_per_frame``: the other stages' sum, a floor for the CPU side where a large model part is
    taken off a noisy end-to-end figure."""
    on_gpu = cluster.gpus > 0 and model_s_per_frame > 0 and gpu_fps is not None
    cpu_s = max(cpu_s_per_frame - model_s_per_frame, rest_s_per_frame) if on_gpu else cpu_s_per_frame
    cpu_h = frames * cpu_s / (cluster.cpus * cluster.efficiency) / 3600
    gpu_h = frames / (cluster.gpus * gpu_fps) / 3600 if on_gpu else 0.0
    return {"cpu_hours": cpu_h, "gpu_hours": gpu_h, "hours": max(cpu_h, gpu_h), "cpu_s_per_frame": cpu_s}


def measure_stages(cfg: JobConfig, sequence: str, n_frames: int) -> StageRates:
    """Per-stage CPU seconds a frame over the sequence's first ``n_frames`` frames (module doc)."""
    from mining.pipeline.frames import FrameLoop, plan_frames
    from mining.pipeline.mine import judge, tube_generator, with_links
    from mining.proposals.make import FrameProposer

    source = cfg.source.open()
    plan = source.plan(sequence)
    size = (plan.calib.height, plan.calib.width)
    models = FrameProposer(cfg.proposals, size, frame_parts=False)
    here = FrameProposer(cfg.proposals, size, models=False)
    loop, gen = FrameLoop(cfg, here), tube_generator(cfg)
    t = dict.fromkeys(("read", "geometry", "model proposals", "frame proposals", "localise", "tubes"), 0.0)
    frames = 0
    clock = time.process_time
    it = plan_frames(source, plan, 0, n_frames)
    # The first frame is not timed: it pays the one-off costs (a source's scene or LUT, a model's session).
    _, first, _ = next(it)
    g = loop.geometry(first)
    parts = models.propose_images([first.index], [first.left])[0] if models.model_names else []
    gen.step(loop.step(first, geometry=g, proposals=here.finish(first, g, parts)).tracking)
    while True:
        t0 = clock()
        item = next(it, None)
        t["read"] += clock() - t0
        if item is None:
            break
        _, frame, after_gap = item
        if after_gap:
            loop.recording_gap()
        t0 = clock()
        geom = loop.geometry(frame)
        t1 = clock()
        parts = models.propose_images([frame.index], [frame.left])[0] if models.model_names else []
        t2 = clock()
        props = here.finish(frame, geom, parts)
        t3 = clock()
        rec = loop.step(frame, geometry=geom, proposals=props)
        t4 = clock()
        gen.step(rec.tracking)
        t5 = clock()
        for k, a, b in (("geometry", t0, t1), ("model proposals", t1, t2), ("frame proposals", t2, t3),
                        ("localise", t3, t4), ("tubes", t4, t5)):
            t[k] += b - a
        frames += 1
    t0 = clock()
    judge(with_links(gen.finish(), cfg), cfg)
    t["tubes"] += clock() - t0
    if not frames:
        raise ConfigError(f"sequence {sequence} has no frames to measure")
    rates = StageRates(frames, size, cfg.proposals.proposer, {k: v / frames for k, v in t.items() if v or k != "model proposals"})
    if not models.model_names:
        rates.seconds.pop("model proposals", None)
    return rates


def measure_end_to_end(cfg: JobConfig, sequence: str, n_frames: int) -> float:
    """CPU seconds a frame of a whole job in this process (``LocalExecutor``), into a temporary catalogue."""
    from mining.pipeline.executors import LocalExecutor
    from mining.pipeline.submit import mine_job

    spent = {}
    for n in (END_TO_END_BASE, END_TO_END_BASE, n_frames):  # the first pays this process's imports: measured again
        with tempfile.TemporaryDirectory(prefix="bench-scale-") as tmp:
            t0 = time.process_time()
            summary = mine_job(cfg, str(Path(tmp) / "out"), [sequence], (0, n), executor=LocalExecutor)
            spent[n] = time.process_time() - t0
        if summary.any_failed:
            raise RuntimeError(f"bench scale's job failed: {summary.lines()}")
    # The marginal cost: what one more frame costs, the job's one-off costs (planning, models, stitch) apart.
    return (spent[n_frames] - spent[END_TO_END_BASE]) / (n_frames - END_TO_END_BASE)


def gpu_rate(cfg: JobConfig, size: tuple[int, int], batches: tuple[int, ...] = (1, 4, 8, 16)) -> dict[str, Any] | None:
    """The torch proposer's frames/s on CUDA at ``size`` per batch and precision, with its peak memory;
    None where there is no CUDA device (or no torch, or no torch part in the proposer)."""
    try:
        import torch
    except ImportError:
        return None
    if not torch.cuda.is_available() or "torch" not in cfg.proposals.proposer:
        return None
    from mining.proposals.mprcnn_torch import TorchProposer

    out: dict[str, Any] = {"device": torch.cuda.get_device_name(0), "rows": []}
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (*size, 3), dtype=np.uint8) for _ in range(max(batches))]
    for precision in ("fp32", "fp16"):
        for b in batches:
            tc = copy.deepcopy(cfg.proposals.torch)
            tc.device, tc.precision, tc.batch_size = "cuda", precision, b
            model = TorchProposer(tc)
            model.propose_batch(list(range(b)), images[:b])  # warm-up: cuDNN's algorithm search
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
            t0, n = time.perf_counter(), 0
            while time.perf_counter() - t0 < 5.0:
                model.propose_batch(list(range(b)), images[:b])
                n += b
            torch.cuda.synchronize()
            out["rows"].append({"precision": precision, "batch": b, "fps": n / (time.perf_counter() - t0),
                                "peak_gpu_bytes": torch.cuda.max_memory_allocated()})
            del model
            torch.cuda.empty_cache()
    return out


def chart(path: str, rates: StageRates, frames: int, gpu_fps: float, efficiency: float, assumed: bool,
          overwrite: bool = False) -> None:
    """Projected hours against CPU cores, one line per GPU count, with the 1 h line (PNG)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        import matplotlib.ticker
    except ImportError:
        raise ConfigError("mine bench scale --chart needs matplotlib: install the 'bench' extra "
                          "(scripts/setup.sh bench)") from None
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    for g in CHART_GPUS if rates.model else (0,):
        hours = [project_hours(frames, rates.end_to_end, rates.model, Cluster(c, g, efficiency), gpu_fps,
                               rates.rest)["hours"]
                 for c in CHART_CORES]
        ax.plot(CHART_CORES, hours, marker="o", label=f"{g} GPU{'s' if g != 1 else ''}" if rates.model else "CPUs only")
    ax.axhline(1.0, color="grey", linestyle="--", linewidth=1)
    ax.text(CHART_CORES[0], 1.05, "1 h", color="grey")
    ax.set(xscale="log", yscale="log", xlabel="CPU cores", ylabel=f"hours for {frames:,} frames",
           title=f"{rates.proposer} at {rates.size[1]}×{rates.size[0]}: "
                 f"{rates.end_to_end:.2f} CPU-s/frame" + (f", GPU {gpu_fps:g} fps{' (assumed)' if assumed else ''}"
                                                           if rates.model else ""))
    ax.set_xticks(CHART_CORES, [str(c) for c in CHART_CORES])
    ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    safe_files.write_file(path, buf.getvalue(), overwrite)


def ray_run(cfg: JobConfig, sequence: str, frames: int, workers: int | None = None, gpus: int = 0) -> dict[str, Any]:
    """A job of ``frames`` frames on a local Ray of this machine's CPUs (``mine bench pipeline``'s
    measured run in a process of its own): object store peak, worker peak memory, frames/s."""
    from mining.bench.pipeline import measure_run

    cfg = copy.deepcopy(cfg)
    cfg.source.sequences = [sequence]
    if cfg.source.dataset == "synthetic":
        cfg.source.options = {**cfg.source.options, "n_frames": max(int(cfg.source.options.get("n_frames", 0)),
                                                                      frames)}
    with tempfile.TemporaryDirectory(prefix="bench-scale-ray-") as tmp:
        return measure_run(cfg, Path(tmp) / "out", workers or 1, frames, gpus)


def _machine() -> str:
    try:
        model = next(line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                     if line.startswith("model name"))
    except (OSError, StopIteration):
        model = platform.processor() or "unknown CPU"
    return f"{model}, {os.cpu_count()} cores"


def run_scale_bench(cfg: JobConfig, sequence: str, n_frames: int, cluster: Cluster, project: int,
                    gpu_fps: float | None, chart_path: str | None, json_path: str | None,
                    end_to_end: bool = True, overwrite: bool = False, ray_frames: int = 0,
                    ray_gpus: int = 0) -> dict[str, Any]:
    import ray

    from mining.bench.geometry import pin_one_core

    cores = len(os.sched_getaffinity(0))
    pin_one_core()
    rates = measure_stages(cfg, sequence, n_frames)
    rates.end_to_end = measure_end_to_end(cfg, sequence, n_frames) if end_to_end else sum(rates.seconds.values())
    # A long job tracks each frame once per window whose context holds it: (core + before + after) / core
    # times; the frames measured here sit in one window with no neighbours, so the excess is added.
    w = cfg.window
    overlap = (w.context_before + w.context_after) / w.core
    if "tubes" in rates.seconds and overlap > 0:
        rates.seconds[CONTEXT_ROW] = rates.seconds["tubes"] * overlap
        rates.end_to_end += rates.seconds[CONTEXT_ROW]
    # Pinned to one core above; the Ray job's own process takes every core this process may use.
    ray_job = ray_run(cfg, sequence, ray_frames, cores, ray_gpus) if ray_frames else None
    measured = gpu_rate(cfg, rates.size) if rates.model else None
    assumed = gpu_fps is None and measured is None
    if gpu_fps is None:
        best = max((r["fps"] for r in measured["rows"]), default=None) if measured else None
        gpu_fps = best if best is not None else ASSUMED_GPU_FPS
    p = project_hours(project, rates.end_to_end, rates.model, cluster, gpu_fps, rates.rest)
    h, w = rates.size
    print(f"Per-stage CPU seconds a frame on one core ({_machine()}; Ray {ray.__version__}): "
          f"{cfg.source.dataset} {sequence}, {rates.frames} frames at {w}×{h}, proposer {rates.proposer}")
    print(f"  {'stage':<18} {'CPU ms/frame':>12} {'frames/s/core':>14}")
    for k, v in rates.seconds.items():
        print(f"  {k:<18} {1e3 * v:>12.1f} {1 / max(v, 1e-9):>14.1f}")
    print(f"  {'sum of stages':<18} {1e3 * sum(rates.seconds.values()):>12.1f}")
    what = "a whole job in this process" if end_to_end else "not measured (--no-job): the sum of stages"
    print(f"  {'end to end':<18} {1e3 * rates.end_to_end:>12.1f} {1 / max(rates.end_to_end, 1e-9):>14.1f}   ({what})")
    if measured:
        print(f"GPU ({measured['device']}), the torch proposer at {w}×{h}:")
        for r in measured["rows"]:
            print(f"  {r['precision']} batch {r['batch']:>2}: {r['fps']:7.1f} frames/s, "
                  f"peak {r['peak_gpu_bytes'] / 2**30:.1f} GiB")
    if ray_job:
        r = ray_job
        stage = (f"; proposal stage {len(r['placement'].get('proposal_actors', []))} actor(s)"
                 if r["placement"].get("proposal_actors") else "")
        if b := r.get("stage_busy"):
            stage += (f", busy {100 * b['share']:.0f} % of the mining time from its first second (every actor "
                      f"had work {b['all_busy_after_s']:.1f} s in)")
        print(f"On a local Ray of {r['workers']} workers, {r['frames']} frames: object store peak "
              f"{r['object_store_peak_bytes'] / 2**20:.0f} MiB, worker peak memory "
              f"{r['peak_rss_bytes'] / 2**20:.0f} MiB (stitch included), {r['fps']:.2f} frames/s{stage}")
    if rates.model and not measured:
        print("GPU: none here (no CUDA device or no torch part): the GPU rate below is "
              + ("given by --gpu-fps" if not assumed else f"ASSUMED ({ASSUMED_GPU_FPS:g} frames/s a GPU)"))
    tag = " ASSUMED" if assumed and rates.model and cluster.gpus else ""
    print(f"Projection for {project:,} frames on {cluster.cpus} CPU cores + {cluster.gpus} GPUs: {p['hours']:.2f} h")
    print(f"  CPU side {p['cpu_hours']:.2f} h = {project:,} × {p['cpu_s_per_frame']:.3f} CPU-s / "
          f"({cluster.cpus} cores × {cluster.efficiency:.2f} scaling efficiency, from `mine bench pipeline`)")
    if rates.model and cluster.gpus:
        print(f"  GPU side {p['gpu_hours']:.2f} h = {project:,} / ({cluster.gpus} GPUs × {gpu_fps:g} frames/s){tag}")
    print("  assumes: the per-frame cost measured here on this machine's cores; a core per worker; frames as "
          "hard to mine as these; Ray start-up, stitching of long sequences and stragglers beyond the "
          "scaling efficiency not included")
    result = {"ray_version": ray.__version__, "machine": _machine(), "dataset": cfg.source.dataset,
              "sequence": sequence, "frames": rates.frames, "size": list(rates.size), "proposer": rates.proposer,
              "stage_cpu_s_per_frame": rates.seconds, "end_to_end_cpu_s_per_frame": rates.end_to_end,
              "end_to_end_measured": end_to_end, "gpu": measured, "ray_job": ray_job, "gpu_fps": gpu_fps,
              "gpu_fps_assumed": assumed, "cluster": {"cpus": cluster.cpus, "gpus": cluster.gpus,
                                                      "efficiency": cluster.efficiency},
              "project_frames": project, "projection": p}
    if chart_path:
        chart(chart_path, rates, project, gpu_fps, cluster.efficiency, assumed, overwrite)
        print(f"chart: {chart_path}")
    if json_path:
        safe_files.write_file(json_path, json.dumps(result, indent=1).encode(), overwrite)
    return result


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine bench scale``'s options."""
    add_job_options(p)
    p.add_argument("--sequence", default=None, help="the sequence measured (default: the config's first, "
                                                    "or 0000 for the synthetic source)")
    p.add_argument("--frames", type=count(4, 100_000), default=16, help="frames measured (default 16)")
    p.add_argument("--cpus", type=count(1, 1_000_000), default=64, help="cluster CPU cores projected (default 64)")
    p.add_argument("--gpus", type=count(0, 100_000), default=0, help="cluster GPUs projected (default 0)")
    p.add_argument("--gpu-fps", type=real(0.0, 1e6, lo_open=True), default=None,
                   help=f"the model's frames/s a GPU (default: measured where CUDA is present, else "
                        f"{ASSUMED_GPU_FPS:g}, printed as an assumption)")
    p.add_argument("--efficiency", type=real(0.0, 1.0, lo_open=True), default=SCALING_EFFICIENCY,
                   help=f"scaling efficiency of the cluster (default {SCALING_EFFICIENCY})")
    p.add_argument("--project-frames", type=count(1, 10**9), default=ROBOTCAR_FRAMES,
                   help=f"frames projected (default {ROBOTCAR_FRAMES:,}: 14 h of RobotCar at 16 Hz)")
    p.add_argument("--no-job", action="store_true", help="skip the end-to-end job (the sum of stages projects)")
    p.add_argument("--ray-frames", type=count(0, 10**7), default=200,
                   help="frames of a job on a local Ray for the object store and worker memory peaks "
                        "(default 200; 0 skips it)")
    p.add_argument("--ray-gpus", type=count(0, 1024), default=0,
                   help="logical GPUs the local Ray job announces, so that its proposal stage runs there and its "
                        "busy share is measured without a GPU (the model then runs on the CPU; default 0: the "
                        "GPUs Ray finds)")
    p.add_argument("--chart", type=output_file, default=None, help="PNG of hours against cluster size")
    p.add_argument("--json", type=output_file, default=None, help="every figure as JSON")
    add_overwrite_option(p, "the --chart and --json files")


def run(args: argparse.Namespace) -> int:
    """``mine bench scale``."""
    cfg = job_config(args)
    if cfg.source.dataset == "synthetic" and not {"width", "height"} & set(cfg.source.options):
        cfg.source.options = {**cfg.source.options, "width": ROBOTCAR_SIZE[1], "height": ROBOTCAR_SIZE[0]}
    sequence = args.sequence or (cfg.source.sequences[0] if cfg.source.sequences else "0000")
    run_scale_bench(cfg, sequence, args.frames, Cluster(args.cpus, args.gpus, args.efficiency), args.project_frames,
                    args.gpu_fps, args.chart, args.json, end_to_end=not args.no_job, overwrite=args.overwrite,
                    ray_frames=args.ray_frames, ray_gpus=args.ray_gpus)
    return 0
