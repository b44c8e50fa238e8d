"""``mine bench stages``: the proposal stage fed two ways on the same frames — the pipeline's explicit
actor queues and Ray Data — side by side on a local Ray with logical GPUs (issue 30: decide by measurement).

Every way does the same work: the CPU front of an observe step (read and decode a stereo pair, then the
geometry stage, which carries state from frame to frame inside a window) over windows of ``window.core``
frames, and the proposer's model parts on ``--gpus`` actors holding one (logical) GPU each, in batches of
``run.proposal_batch`` frames:

* **actors** — the pipeline's shape (``proposal_stage.ahead``): ``--workers`` CPU actors take whole
  windows, each sends its left images to one proposal actor, at most ``run.proposal_queue`` batches ahead;
* **data** — Ray Data: the windows as a dataset, ``map_batches`` for the front (one window a call, so the
  geometry state stays inside it, yielding a batch of frames at a time), ``map_batches`` on a pool of ``--gpus`` actors with ``num_gpus=1``,
  pre-sized (a GPU pool left to grow adds an actor at a time), streamed into the driver;
* **data-autoscale** — the same with a pool of 1 to ``--gpus`` actors, left to grow.

Per way: wall time from the first submission and frames/s; the proposal actors' busy share of that time
(time inside a batch over actors × wall: the GPU busy share where they hold GPUs, from the first second);
when every actor had had its first batch (the ramp-up); the object store's sampled peak; and a digest of
every frame's model proposals, which must agree across the ways frame by frame.

``--gpu-ms`` stands in for the model with a wait of that many ms a frame on its actor: an emulated GPU,
whose actor leaves the CPU free while it "works", as a GPU would. On a machine without GPUs this measures
the orchestration (how frames travel, how busy the pool is kept, what the object store holds) rather than a
CPU model competing with the front for the same cores; the proposals are then empty, and so agree.

The ways run in one child process, on one local Ray (a process starts Ray once), in the order given.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mining.bench.pipeline import ObjectStoreSampler, child_result
from mining.catalog import safe_files
from mining.checks import count, output_file, real
from mining.config import JobConfig
from mining.errors import ConfigError, InputError
from mining.pipeline.arguments import add_job_options, add_overwrite_option, job_config
from mining.pipeline.proposal_stage import ProposalWorker
from mining.types import Proposals

WAYS = ("actors", "data", "data-autoscale")


def proposals_digest(parts: Sequence[Proposals]) -> str:
    """A frame's model proposals as one hash (masks, boxes, scores, posteriors, in order)."""
    h = hashlib.sha1()
    for p in parts:
        h.update(",".join(p.proposer).encode())
        for r in p.rles:
            c = r["counts"]
            h.update(c if isinstance(c, bytes) else str(c).encode())
        for a in (p.boxes, p.objectness, p.posterior):
            if a is not None:
                h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


class EmulatedModel:
    """``FrameProposer.propose_images`` of an emulated GPU: waits ``ms`` a frame, proposes nothing."""

    model_names = ("emulated",)

    def __init__(self, ms: float):
        self.ms = ms

    def propose_images(self, frames: Sequence[int], images: Sequence[np.ndarray]) -> list[list[Proposals]]:
        time.sleep(self.ms * len(frames) / 1e3)
        return [[] for _ in frames]


class ModelWorker(ProposalWorker):
    """The pipeline's proposal actor, with the emulated model at ``size`` where ``gpu_ms`` is given
    (ProposalWorker loads a model only for a size it has none for)."""

    def __init__(self, cfg: JobConfig, size: tuple[int, int], gpu_ms: float | None):
        super().__init__(cfg.proposals)
        if gpu_ms is not None:
            self.models[size] = EmulatedModel(gpu_ms)


def windows_of(n_frames: int, core: int) -> list[tuple[int, int]]:
    return [(a, min(a + core, n_frames)) for a in range(0, n_frames, core)]


class Front:
    """The CPU front of the ``actors`` way: a window's frames read, sent ahead to a proposal actor in
    batches, and the geometry stage run on each as its proposals come back (``observe_window``'s order)."""

    def __init__(self, cfg: JobConfig, sequence: str, model_actor: Any):
        from mining.pipeline.proposal_stage import RemoteModels

        self.cfg, self.sequence, self.stage = cfg, sequence, RemoteModels(model_actor)

    def run(self, start: int, stop: int) -> list[tuple[int, str]]:
        from mining.geometry.stage import GeometryStage
        from mining.pipeline.frames import plan_frames
        from mining.pipeline.proposal_stage import ahead

        source = self.cfg.source.open()
        plan = source.plan(self.sequence)
        geometry, out = None, []
        run = self.cfg.run
        for _, frame, after_gap, models in ahead(plan_frames(source, plan, start, stop), self.stage,
                                                 run.proposal_batch, run.proposal_queue):
            geometry = geometry or GeometryStage(frame.calib, self.cfg.geometry)
            if after_gap:
                geometry.reset()
            geometry.run(frame)
            out.append((frame.index, proposals_digest(models)))
        return out


def front_batches(windows: dict[str, np.ndarray], cfg: JobConfig, sequence: str) -> Iterator[dict[str, np.ndarray]]:
    """The ``data`` way's front: each window's frames read and through the geometry stage, yielded
    ``run.proposal_batch`` frames at a time (a generator: Ray Data streams them on before the window ends)."""
    from mining.pipeline.frames import plan_geometry

    source = cfg.source.open()
    plan = source.plan(sequence)
    for start, stop in zip(windows["start"], windows["stop"], strict=True):
        frames, lefts = [], []
        for _, frame, _, _ in plan_geometry(source, plan, int(start), int(stop), cfg.geometry):
            frames.append(frame.index)
            lefts.append(frame.left)
            if len(frames) == cfg.run.proposal_batch:
                yield {"frame": np.asarray(frames), "left": np.stack(lefts)}
                frames, lefts = [], []
        if frames:
            yield {"frame": np.asarray(frames), "left": np.stack(lefts)}


class DataModel:
    """The ``data`` way's model actor: a batch of rows' left images through ``ProposalWorker``."""

    def __init__(self, cfg: JobConfig, size: tuple[int, int], gpu_ms: float | None):
        self.size, self.worker = size, ModelWorker(cfg, size, gpu_ms)

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        frames = [int(f) for f in batch["frame"]]
        out = self.worker.propose(self.size, frames, list(batch["left"]))
        if isinstance(out, tuple):
            raise InputError(*out)
        n, w = len(frames), self.worker
        # Each batch carries its actor's running totals: the driver keeps the last per actor.
        return {"frame": np.asarray(frames), "digest": np.asarray([proposals_digest(p) for p in out]),
                "pid": np.full(n, os.getpid()), "busy_s": np.full(n, w.busy_s), "first_t": np.full(n, w.first_t)}


def _run_actors(cfg: JobConfig, sequence: str, windows: list[tuple[int, int]], size: tuple[int, int],
                gpus: int, workers: int, gpu_ms: float | None) -> tuple[dict[int, str], list[dict]]:
    import ray

    models = [ray.remote(num_gpus=1)(ModelWorker).remote(cfg, size, gpu_ms) for _ in range(gpus)]
    fronts = [ray.remote(Front).remote(cfg, sequence, models[i % gpus]) for i in range(workers)]
    idle, busy, todo, digests = list(fronts), {}, list(windows), {}
    while todo or busy:
        while idle and todo:
            a = idle.pop()
            busy[a.run.remote(*todo.pop(0))] = a
        ready, _ = ray.wait(list(busy), num_returns=1)
        idle.append(busy.pop(ready[0]))
        digests.update(ray.get(ready[0]))
    actors = ray.get([m.where.remote() for m in models])
    for a in fronts + models:
        ray.kill(a)
    return digests, [{"pid": a["pid"], "busy_s": a["busy_s"], "first_t": a["first_t"]} for a in actors]


def _run_data(cfg: JobConfig, sequence: str, windows: list[tuple[int, int]], size: tuple[int, int],
              gpus: int, gpu_ms: float | None, autoscale: bool) -> tuple[dict[int, str], list[dict]]:
    import ray.data

    ctx = ray.data.DataContext.get_current()
    ctx.enable_progress_bars = False
    ds = ray.data.from_items([{"start": a, "stop": b} for a, b in windows], override_num_blocks=len(windows))
    ds = ds.map_batches(front_batches, fn_args=(cfg, sequence), batch_size=1)  # a window a call
    # num_cpus=0: like the pipeline's proposal actors, the GPU actors hold no core (the front keeps them).
    ds = ds.map_batches(DataModel, fn_constructor_args=(cfg, size, gpu_ms), batch_size=cfg.run.proposal_batch,
                        num_gpus=1, num_cpus=0, concurrency=(1, gpus) if autoscale else gpus)
    digests, actors = {}, {}
    for batch in ds.iter_batches(batch_size=None, batch_format="numpy"):
        for f, d in zip(batch["frame"], batch["digest"], strict=True):
            digests[int(f)] = str(d)
        for pid, b, t in zip(batch["pid"], batch["busy_s"], batch["first_t"], strict=True):
            a = actors.setdefault(int(pid), {"pid": int(pid), "busy_s": 0.0, "first_t": float(t)})
            a["busy_s"], a["first_t"] = max(a["busy_s"], float(b)), min(a["first_t"], float(t))
    return digests, list(actors.values())


def measure_here(cfg: JobConfig, sequence: str, n_frames: int, gpus: int, workers: int, gpu_ms: float | None,
                 ways: Sequence[str], rounds: int = 1) -> dict[str, Any]:
    """Every way of ``ways`` on one local Ray of ``workers`` CPUs and ``gpus`` logical GPUs started here
    (the child process's body: this process must not have started Ray before)."""
    from mining.pipeline.localray import init_local_ray, prepare_local_ray

    prepare_local_ray(cfg.run.bind_host)  # before `import ray`: loopback unless run.bind_host says otherwise
    import ray

    source = cfg.source.open()
    plan = source.plan(sequence)
    size = (plan.calib.height, plan.calib.width)
    n_frames = min(n_frames, len(plan))
    windows = windows_of(n_frames, cfg.window.core)
    init_local_ray(workers, cfg.run.bind_host, num_gpus=gpus,
                   runtime_env={"env_vars": {"OPENCV_FOR_THREADS_NUM": "1"}})
    out: dict[str, Any] = {"ray_version": ray.__version__, "frames": n_frames, "windows": len(windows),
                           "size": list(size), "gpus": gpus, "workers": workers, "gpu_ms": gpu_ms,
                           "batch": cfg.run.proposal_batch, "queue": cfg.run.proposal_queue, "ways": {}}
    try:
        # Round r runs the ways in turn, reversed every other round: what one way leaves warm (worker
        # processes, imports, caches) helps the next, so an order would favour one way.
        for way in [w for r in range(rounds) for w in (ways if r % 2 == 0 else ways[::-1])]:
            t0 = time.time()
            with ObjectStoreSampler() as plasma:
                if way == "actors":
                    digests, actors = _run_actors(cfg, sequence, windows, size, gpus, workers, gpu_ms)
                else:
                    digests, actors = _run_data(cfg, sequence, windows, size, gpus, gpu_ms, way == "data-autoscale")
            wall = time.time() - t0
            busy = sum(a["busy_s"] for a in actors)
            firsts = [a["first_t"] for a in actors if a["first_t"] is not None]
            out["ways"].setdefault(way, []).append({
                "wall_s": wall, "fps": len(digests) / wall, "frames": len(digests),
                # Over the GPUs asked for: an actor the pool never started counts as idle.
                "busy_share": busy / (gpus * wall), "busy_s": busy,
                "all_busy_after_s": (max(firsts) - t0) if len(firsts) == gpus else None,
                "model_actors": len(firsts),  # those that had a batch
                "object_store_peak_bytes": plasma.peak, "object_store_error": plasma.error,
                "digests": {str(k): v for k, v in sorted(digests.items())}})
    finally:
        ray.shutdown()
    return out


def measure(cfg: JobConfig, sequence: str, n_frames: int, gpus: int, workers: int, gpu_ms: float | None,
            ways: Sequence[str], rounds: int = 1) -> dict[str, Any]:
    """``measure_here`` in a process of its own (Ray is started once a process)."""
    with tempfile.TemporaryDirectory(prefix="bench-stages-") as tmp:
        job_json, result_json = Path(tmp) / "job.json", Path(tmp) / "result.json"
        job_json.write_text(json.dumps({"job": cfg.to_dict(), "sequence": sequence, "frames": n_frames,
                                        "gpus": gpus, "workers": workers, "gpu_ms": gpu_ms, "ways": list(ways),
                                        "rounds": rounds}))
        return child_result(["mining.bench.stages", str(job_json), str(result_json)], result_json,
                            "bench stages' run")


def agreement(result: dict[str, Any]) -> dict[str, int]:
    """Frames whose proposals differ from the first run's, per way over its rounds (0: the same, frame by frame)."""
    runs = [(name, x) for name, xs in result["ways"].items() for x in xs]
    first = runs[0][1]["digests"] if runs else {}
    out: dict[str, int] = {}
    for name, x in runs:
        d = x["digests"]
        out[name] = out.get(name, 0) + sum(d.get(f) != v for f, v in first.items()) + len(set(d) - set(first))
    return out


def median_run(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The round with the median wall time (the lower middle of an even count)."""
    return sorted(runs, key=lambda x: x["wall_s"])[(len(runs) - 1) // 2]


def run_stages_bench(cfg: JobConfig, sequence: str, n_frames: int, gpus: int, workers: int, gpu_ms: float | None,
                     ways: Sequence[str], rounds: int = 3, json_path: str | None = None,
                     overwrite: bool = False) -> dict[str, Any]:
    from mining.pipeline.proposal_stage import has_models

    if gpu_ms is None and not has_models(cfg.proposals):
        raise ConfigError(f"proposer {cfg.proposals.proposer!r} runs no network: name one that does "
                          "(--set proposals.proposer=...) or emulate the GPU with --gpu-ms")
    r = measure(cfg, sequence, n_frames, gpus, workers, gpu_ms, ways, rounds)
    differ = agreement(r)
    h, w = r["size"]
    model = f"emulated GPU, {gpu_ms:g} ms a frame" if gpu_ms is not None else cfg.proposals.proposer
    print(f"The proposal stage fed two ways, Ray {r['ray_version']}: {cfg.source.dataset} {sequence}, {r['frames']} "
          f"frames at {w}×{h} in {r['windows']} window(s), {workers} CPU worker(s), {gpus} logical GPU(s), "
          f"batch {r['batch']}, model: {model}; the median of {rounds} round(s), alternating order")
    print(f"  {'way':<15} {'wall s':>7} {'frames/s':>9} {'GPU busy':>9} {'all busy after':>15} "
          f"{'object store peak':>18} {'frames differing':>17}  {'walls of the rounds'}")
    r["median"] = {}
    for name, runs in r["ways"].items():
        x = r["median"][name] = median_run(runs)
        ramp = f"{x['all_busy_after_s']:.1f} s" if x["all_busy_after_s"] is not None else \
            f"never ({x['model_actors']} of {gpus})"
        peak = max(y["object_store_peak_bytes"] for y in runs)
        walls = " ".join(f"{y['wall_s']:.1f}" for y in runs)
        print(f"  {name:<15} {x['wall_s']:>7.1f} {x['fps']:>9.2f} {100 * x['busy_share']:>8.0f}% {ramp:>15} "
              f"{peak / 2**20:>14.0f} MiB {differ[name]:>17}  {walls}")
    print("  GPU busy: the model actors' time inside a batch over GPUs × wall, from the first submission; "
          "object store: the highest of the rounds")
    r["frames_differing"] = differ
    if json_path:
        safe_files.write_file(json_path, json.dumps(r, indent=1).encode(), overwrite)
    return r


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine bench stages``' options."""
    add_job_options(p)
    p.add_argument("--sequence", default=None, help="the sequence (default: the config's first, or 0000)")
    p.add_argument("--frames", type=count(1, 1_000_000), default=400, help="frames fed (default 400)")
    p.add_argument("--gpus", type=count(1, 64), default=2, help="logical GPUs, one model actor each (default 2)")
    p.add_argument("--workers", type=count(1, 1024), default=None,
                   help="CPU workers (default: this machine's cores)")
    p.add_argument("--gpu-ms", type=real(0.0, 60_000.0), default=None,
                   help="emulate the model: its actor waits this many ms a frame (default: run the job's proposer)")
    p.add_argument("--ways", nargs="+", choices=WAYS, default=list(WAYS), help="which ways, in this order")
    p.add_argument("--rounds", type=count(1, 20), default=3,
                   help="rounds of every way, the order reversed every other round (default 3)")
    p.add_argument("--json", type=output_file, default=None, help="every figure as JSON")
    add_overwrite_option(p, "the --json file")


def run(args: argparse.Namespace) -> int:
    """``mine bench stages``."""
    cfg = job_config(args)
    sequence = args.sequence or (cfg.source.sequences[0] if cfg.source.sequences else "0000")
    r = run_stages_bench(cfg, sequence, args.frames, args.gpus, args.workers or os.cpu_count() or 1, args.gpu_ms,
                         args.ways, args.rounds, args.json, args.overwrite)
    return 0 if not any(r["frames_differing"].values()) else 1


def _main(argv: list[str]) -> int:
    """``python -m mining.bench.stages JOB.json RESULT.json``: ``measure``'s child."""
    from mining.config import section_from_dict

    job_json, result_json = argv
    spec = json.loads(Path(job_json).read_text())
    cfg = section_from_dict(JobConfig, spec["job"], job_json)
    r = measure_here(cfg, spec["sequence"], spec["frames"], spec["gpus"], spec["workers"], spec["gpu_ms"], spec["ways"],
                     spec["rounds"])
    Path(result_json).write_text(json.dumps(r))
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
