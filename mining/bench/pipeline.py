"""``mine bench pipeline``: end-to-end throughput, scaling, Ray's overhead, worker memory, catalogue.

The rows and their targets are those of the distributed-mining issue:

* frames per second of the whole job (plan → observe → track → finalize) on a local Ray
  with 1 and with 2 workers, same synthetic job at 1242×375, a fresh catalogue each time;
  scaling efficiency = fps₂ / (2·fps₁) (target ≥ 90 %);
* Ray's overhead per window: the worker-seconds of the job not spent inside the steps,
  ``(workers · wall − Σ(seconds_observe + seconds_tubes)) / windows``, with the step
  times the steps measure themselves (the manifest, ``windows`` table) and ``wall`` the
  job's time with Ray already started (actor start-up, scheduling, argument passing,
  waiting on dependencies, the finalize step and the tail where one worker idles all
  count as overhead);
* peak resident memory per worker (VmHWM of each ``ray::Worker`` actor process, polled
  together with VmRSS from /proc) for 100-frame windows (target ≤ 2 GB), and with
  ``--long`` a 2,000-frame run whose per-window peaks show whether memory grows with
  the sequence (the peak of any worker while window k's steps run, k in plan order);
* the catalogue: bytes per tube-frame row and the README's example queries over one
  million rows (``mining.bench.catalog``; target ≤ 1 s each).

Workers run OpenCV single-threaded (``OPENCV_FOR_THREADS_NUM=1``) so that a worker is
one core and the scaling figure compares like with like.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from mining.catalog import safe_files
from mining.checks import count, output_file, output_folder
from mining.config import JobConfig
from mining.pipeline.arguments import add_job_options, add_overwrite_option, job_config
from mining.pipeline.failures import exit_reason

WORKER_TITLE = "ray::Worker"  # process title of the pipeline's actors (mining.pipeline.executors.Worker)
POLL_S = 0.2  # ours: RSS sampling period; VmHWM catches peaks between samples
GROWTH_TOLERANCE = 1.10  # ours: the later windows' peak may exceed the earlier ones' by 10 % before it counts as growth


def bench_job(cfg: JobConfig, n_frames: int, sequences: list[str], core: int = 100) -> JobConfig:
    """The bench's synthetic job: ``sequences`` of ``n_frames`` frames at the source's default 1242×375."""
    cfg = copy.deepcopy(cfg)
    cfg.source.dataset = "synthetic"
    cfg.source.sequences = list(sequences)
    cfg.source.options = {**cfg.source.options, "n_frames": int(n_frames)}
    cfg.window.core = int(core)
    return cfg


def proc_status(pid: int) -> dict[str, int]:
    """VmRSS, VmHWM (bytes) and PPid of a process; empty when it has gone."""
    out: dict[str, int] = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                out[key] = int(value.split()[0]) * 1024
            elif key == "PPid":
                out[key] = int(value)
    except (FileNotFoundError, ProcessLookupError, PermissionError):
        return {}
    return out


def worker_processes(raylet_pid: int) -> dict[int, dict[str, int]]:
    """The pipeline's actor processes started by this raylet: pid → VmRSS / VmHWM (bytes).

    Filtering by parent keeps out the actors of any other Ray instance on the machine.
    """
    out = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            title = (entry / "cmdline").read_bytes().split(b"\0")[0].decode(errors="replace")
        except (FileNotFoundError, ProcessLookupError, PermissionError):
            continue
        if not title.startswith(WORKER_TITLE):
            continue
        st = proc_status(int(entry.name))
        if st.get("PPid") == raylet_pid and "VmRSS" in st:
            out[int(entry.name)] = st
    return out


def local_raylet_pid() -> int:
    """The raylet of the Ray this driver started (``ray.init`` without an address)."""
    import ray

    node = ray._private.worker.global_worker.node  # noqa: SLF001 - the only handle on the raylet's pid
    return node.all_processes["raylet"][0].process.pid


class RssSampler:
    """Polls the workers' VmRSS/VmHWM in a thread: ``samples`` are (unix time, pid, rss bytes)."""

    def __init__(self, raylet_pid: int, period: float = POLL_S):
        self.raylet_pid, self.period = raylet_pid, period
        self.samples: list[tuple[float, int, int]] = []
        self.hwm: dict[int, int] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self) -> None:
        while not self._stop.is_set():
            t = time.time()
            for pid, st in worker_processes(self.raylet_pid).items():
                self.samples.append((t, pid, st["VmRSS"]))
                self.hwm[pid] = max(self.hwm.get(pid, 0), st.get("VmHWM", 0), st["VmRSS"])
            self._stop.wait(self.period)

    def __enter__(self) -> "RssSampler":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


PLASMA_LINE = re.compile(r"Plasma memory usage (\d+) MiB, (\d+) objects")  # Ray 2.58's `ray memory --stats-only`


def object_store_bytes() -> int:
    """Bytes in the object store of the Ray this driver is connected to (all nodes), at MiB
    resolution: Ray's own aggregate (``ray memory --stats-only``)."""
    import ray
    from ray._private.internal_api import memory_summary  # noqa: PLC2701 - what `ray memory` itself calls

    # This driver's own Ray by address: with none, Ray refuses when another Ray runs on the machine.
    m = PLASMA_LINE.search(memory_summary(address=ray.get_runtime_context().gcs_address, stats_only=True))
    if m is None:
        raise RuntimeError("Ray's memory summary has no 'Plasma memory usage' line (another Ray version?)")
    return int(m.group(1)) * 2**20


class ObjectStoreSampler:
    """Polls the object store's usage in a thread; ``peak`` bytes, ``samples`` (unix time, bytes)."""

    def __init__(self, period: float = POLL_S):
        self.period, self.peak, self.error = period, 0, ""
        self.samples: list[tuple[float, int]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                b = object_store_bytes()
            except Exception as e:  # noqa: BLE001 - a report: said in the result, never a silent zero
                self.error = f"{type(e).__name__}: {e}"
            else:
                self.samples.append((time.time(), b))
                self.peak = max(self.peak, b)
            self._stop.wait(self.period)

    def __enter__(self) -> "ObjectStoreSampler":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


def _window_rows(out: Path) -> list[dict[str, Any]]:
    from mining.catalog.views import connect

    con = connect(out)
    try:
        cur = con.execute('SELECT sequence, "window", core_start, core_end, status, epoch(started) AS started, '
                          "epoch(finished) AS finished, seconds_observe, seconds_tubes FROM windows ORDER BY sequence, core_start")
        names = [d[0] for d in cur.description]
        return [dict(zip(names, r)) for r in cur.fetchall()]
    finally:
        con.close()


def window_peaks(out: Path, rows: list[dict[str, Any]], samples: list[tuple[float, int, int]],
                 dataset: str = "synthetic") -> list[int | None]:
    """Max RSS of any worker sampled while each window's observe or track step ran.

    Track runs from the manifest's ``started`` to ``finished``; observe ends when its
    cache file is written (the bench keeps the cache) and lasted ``seconds_observe``.
    """
    from mining.catalog.layout import cache_path
    from mining.types import Window

    t = np.array([s[0] for s in samples]) if samples else np.zeros(0)
    rss = np.array([s[2] for s in samples]) if samples else np.zeros(0, np.int64)
    peaks: list[int | None] = []
    for r in rows:
        spans = [(r["started"], r["finished"])]  # unix seconds
        w = Window(dataset, r["sequence"], (r["core_start"], r["core_end"]), (0, 0))
        cache = out / cache_path(w)
        if cache.exists() and r["seconds_observe"] is not None:
            end = cache.stat().st_mtime
            spans.append((end - r["seconds_observe"], end))
        inside = np.zeros(len(t), bool)
        for a, b in spans:
            inside |= (t >= a) & (t <= b)
        peaks.append(int(rss[inside].max()) if inside.any() else None)
    return peaks


def measure_run(cfg: JobConfig, out: str | Path, workers: int, frames: int | None = None,
                gpus: int = 0) -> dict[str, Any]:
    """Mine ``cfg`` into a fresh ``out`` on a local Ray of ``workers`` CPUs (and ``gpus`` logical
    GPUs, where a proposal stage runs; 0: the GPUs Ray finds); time, overhead, memory.

    Each run is a process of its own (``python -m mining.bench.pipeline``): Ray's core
    worker is made once per process, and a second ``ray.init`` after ``ray.shutdown`` in
    one process (the bench runs 1 and 2 workers, then the long run) can crash it at exit.
    RuntimeError names the run's exit status or signal when the child does not end with 0.
    """
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"{out} is not empty: the bench needs a fresh catalogue")
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="bench-run-", dir=out.parent) as tmp:
        job_json, result_json = Path(tmp) / "job.json", Path(tmp) / "result.json"
        job_json.write_text(json.dumps(cfg.to_dict()))
        return child_result(["mining.bench.pipeline", str(job_json), str(out), str(int(workers)), str(result_json),
                             str(int(frames or 0)), str(int(gpus))], result_json,
                            f"bench run on {workers} worker(s) into {out}")


def child_result(args: list[str], result_json: Path, what: str) -> dict[str, Any]:
    """``python -m ARGS`` in a process of its own (a process starts Ray once) and the JSON it left at
    ``result_json``; RuntimeError naming ``what`` and the child's exit status or signal otherwise."""
    p = subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True)
    if p.returncode != 0 or not result_json.exists():
        tail = "\n".join((p.stdout + p.stderr).splitlines()[-20:])
        raise RuntimeError(f"{what} ended with {exit_reason(p.returncode)}:\n{tail}")
    return json.loads(result_json.read_text())


def start_bench_ray(cfg: JobConfig, out: str | Path, workers: int, gpus: int = 0) -> Path:
    """Start the local Ray of ``workers`` CPUs (and ``gpus`` logical GPUs) a bench measures in this
    process, after checking ``out`` is a fresh catalogue and no Ray runs here yet; ``out`` as a Path."""
    from mining.pipeline.localray import init_local_ray, prepare_local_ray

    prepare_local_ray(cfg.run.bind_host)  # before `import ray`: loopback unless run.bind_host says otherwise
    import ray

    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"{out} is not empty: the bench needs a fresh catalogue")
    if ray.is_initialized():
        raise RuntimeError("the bench measures a Ray of its own: this process already runs one")
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    init_local_ray(workers, cfg.run.bind_host, runtime_env={"env_vars": {"OPENCV_FOR_THREADS_NUM": "1"}},
                   **({"num_gpus": gpus} if gpus else {}))
    return out


def measure_run_here(cfg: JobConfig, out: str | Path, workers: int, gpus: int = 0,
                     frames: int | None = None) -> dict[str, Any]:
    """``measure_run`` in this process, which must not have started Ray before (and will
    not start it again): the body of the bench's child process. ``gpus``: logical GPUs the
    local Ray announces (the proposal stage's actors take them; a test without a GPU)."""
    t0 = time.perf_counter()
    out = start_bench_ray(cfg, out, workers, gpus)  # first: Ray is imported only after the bind is set
    init_s = time.perf_counter() - t0
    import ray

    from mining.pipeline.executors import RayExecutor
    from mining.pipeline.submit import mine_job

    try:
        # The samplers' threads end before Ray does.
        with RssSampler(local_raylet_pid()) as sampler, ObjectStoreSampler() as plasma:
            summary = mine_job(cfg, str(out), frames=(0, frames), executor=lambda job: RayExecutor(job, workers),
                               keep_cache=True)
    finally:
        ray.shutdown()
    if summary.failed or summary.stitch_failed:
        raise RuntimeError(f"bench job failed: {summary.lines()}")
    rows = _window_rows(out)
    step_s = sum((r["seconds_observe"] or 0.0) + (r["seconds_tubes"] or 0.0) for r in rows)
    observe_s = sum(r["seconds_observe"] or 0.0 for r in rows)
    wall = summary.seconds
    peaks = window_peaks(out, rows, sampler.samples, cfg.source.dataset)
    return {
        "workers": workers, "windows": len(rows), "frames": summary.frames, "tubes": summary.tubes,
        "ray_init_s": init_s, "wall_s": wall, "fps": summary.frames / wall,
        "step_s": step_s, "observe_s": observe_s, "tubes_s": step_s - observe_s,
        "overhead_s_per_window": (workers * wall - step_s) / max(len(rows), 1),
        "utilisation": step_s / (workers * wall),  # share of worker-seconds spent inside the steps
        "step_s_per_frame": step_s / max(summary.frames, 1),
        "peak_rss_bytes": max(sampler.hwm.values(), default=0),
        "worker_hwm_bytes": sorted(sampler.hwm.values()),
        "worker_processes": len(sampler.hwm), "rss_samples": len(sampler.samples),
        "window_peak_rss_bytes": peaks, "load_avg": os.getloadavg(),
        "object_store_peak_bytes": plasma.peak, "object_store_samples": len(plasma.samples),
        "object_store_error": plasma.error,
        "placement": summary.placement, "ray_version": ray.__version__,
        "stage_busy": summary.stage_busy(),  # the proposal actors' (GPU) busy share of the mining time
    }


def growth(peaks: list[int | None]) -> dict[str, float]:
    """Whether per-window peaks rise along the sequence: last half vs first half, and the slope."""
    p = np.array([x for x in peaks if x is not None], float)
    if len(p) < 4:
        return {"first_half_max": float("nan"), "second_half_max": float("nan"), "ratio": float("nan"),
                "slope_mb_per_100_windows": float("nan")}
    h = len(p) // 2
    slope = np.polyfit(np.arange(len(p)), p, 1)[0]
    return {"first_half_max": float(p[:h].max()), "second_half_max": float(p[h:].max()),
            "ratio": float(p[h:].max() / p[:h].max()), "slope_mb_per_100_windows": float(slope * 100 / 2**20)}


def _mb(x: float) -> str:
    return f"{x / 2**20:7.0f} MB"


def run_pipeline_bench(cfg: JobConfig, frames: int = 200, sequences: list[str] | None = None,
                       long: bool = False, long_frames: int = 2000, catalog_rows: int = 1_000_000,
                       workdir: str | None = None, json_out: str | None = None, overwrite: bool = False) -> int:
    """Print the pipeline table; returns 0 when every target holds, 1 otherwise."""
    from mining.bench.catalog import bench_catalog

    sequences = sequences or ["0000", "0001"]
    t_start = time.perf_counter()
    results: dict[str, Any] = {"load_avg_start": os.getloadavg(), "cpus": os.cpu_count()}
    checks: list[tuple[str, bool]] = []
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        job = bench_job(cfg, frames, sequences)
        runs = {n: measure_run(job, Path(tmp) / f"scaling_{n}", n) for n in (1, 2)}
        results["scaling"] = {str(n): r for n, r in runs.items()}
        eff = runs[2]["fps"] / (2 * runs[1]["fps"])
        results["scaling_efficiency"] = eff
        print(f"End to end, synthetic 1242×375, {len(sequences)} sequence(s) × {frames} frames, "
              f"{job.window.core}-frame windows (context {job.window.context_before}/{job.window.context_after}), local Ray")
        print(f"  {'workers':>7} {'windows':>7} {'wall s':>8} {'frames/s':>9} {'steps s':>8} {'step s/frame':>12} "
              f"{'busy':>6} {'overhead s/window':>18} {'peak RSS/worker':>16} {'load avg':>9}")
        for n, r in runs.items():
            print(f"  {n:>7} {r['windows']:>7} {r['wall_s']:8.1f} {r['fps']:9.2f} {r['step_s']:8.1f} "
                  f"{r['step_s_per_frame']:12.3f} {100 * r['utilisation']:5.1f}% {r['overhead_s_per_window']:18.2f} "
                  f"{_mb(r['peak_rss_bytes']):>16} {r['load_avg'][0]:9.2f}")
        slowdown = runs[2]["step_s_per_frame"] / runs[1]["step_s_per_frame"]
        results["step_slowdown_2_vs_1"] = slowdown
        print(f"  scaling efficiency fps2 / (2·fps1): {100 * eff:.1f} %  = busy share on 2 workers "
              f"({100 * runs[2]['utilisation']:.1f} %) / busy share on 1 ({100 * runs[1]['utilisation']:.1f} %) "
              f"/ step slowdown ({slowdown:.2f}×: the same steps take longer when 2 run at once on "
              f"{os.cpu_count()} shared CPUs)")
        print("  overhead = (workers · wall − Σ step seconds in the manifest) / windows; Ray start-up "
              f"({runs[1]['ray_init_s']:.1f} s, {runs[2]['ray_init_s']:.1f} s) not included")
        checks.append(("scaling efficiency on 2 workers ≥ 90 %", eff >= 0.90))
        peak = max(r["peak_rss_bytes"] for r in runs.values())
        checks.append((f"peak RSS per worker, {job.window.core}-frame windows ≤ 2 GB", 0 < peak <= 2 * 2**30))

        if long:
            ljob = bench_job(cfg, long_frames, sequences[:1])
            lr = measure_run(ljob, Path(tmp) / "long", 2)
            g = growth(lr["window_peak_rss_bytes"])
            results["long"] = {**lr, "growth": g}
            print(f"\nLong run: 1 sequence × {long_frames} frames on 2 workers: {lr['fps']:.2f} frames/s, "
                  f"peak RSS per worker {_mb(lr['peak_rss_bytes']).strip()} (load avg {lr['load_avg'][0]:.2f})")
            print("  peak RSS of any worker while window k ran (MB):")
            pk = lr["window_peak_rss_bytes"]
            for i in range(0, len(pk), 10):
                print("   " + " ".join(f"{'-' if x is None else x / 2**20:6.0f}" for x in pk[i:i + 10]))
            print(f"  first half max {_mb(g['first_half_max']).strip()}, second half max {_mb(g['second_half_max']).strip()}, "
                  f"ratio {g['ratio']:.3f}, slope {g['slope_mb_per_100_windows']:+.1f} MB per 100 windows")
            checks.append((f"no memory growth over {long_frames} frames (second-half peak ≤ "
                           f"{GROWTH_TOLERANCE:.2f} × first-half peak)", bool(g["ratio"] <= GROWTH_TOLERANCE)))
            checks.append((f"peak RSS per worker, {long_frames}-frame run ≤ 2 GB", 0 < lr["peak_rss_bytes"] <= 2 * 2**30))

        cat = bench_catalog(tmp, catalog_rows)
        results["catalog"] = cat
        print(f"\nCatalogue: {cat['tube_frame_rows']:,} tube-frame rows, {cat['tubes']:,} tubes "
              f"(built in {cat['build_s']:.1f} s)")
        print(f"  bytes per tube-frame row: {cat['bytes_per_tube_frame']:.1f} (tube_frames), "
              f"{cat['catalog_bytes_per_tube_frame']:.1f} (whole catalogue)")
        print(f"  connect, every file's size and sha256 checked against its marker: {cat['connect_s'] * 1000:.1f} ms")
        for name, s in cat["query_s"].items():
            print(f"  {name:20s} {s * 1000:8.1f} ms  {cat['query_rows'][name]:6d} rows")
            checks.append((f"query {name} over {cat['tube_frame_rows']:,} rows ≤ 1 s", s <= 1.0))
        # what a `mine query` pays once per process with read-path integrity on
        slowest = max(cat["query_s"].values(), default=0.0)
        checks.append(("first query of a process (connect with checksums + the slowest query) ≤ 1 s",
                       cat["connect_s"] + slowest <= 1.0))

    print("\nTargets")
    for name, ok in checks:
        print(f"  [{'ok' if ok else 'MISS'}] {name}")
    results["checks"] = {name: ok for name, ok in checks}
    results["load_avg_end"] = os.getloadavg()
    print(f"\n(bench took {time.perf_counter() - t_start:.0f} s; load average {results['load_avg_start'][0]:.2f} at start, "
          f"{results['load_avg_end'][0]:.2f} at end, {results['cpus']} CPUs)")
    if json_out:
        safe_files.write_file(json_out, json.dumps(results, indent=1, default=float).encode(), overwrite)
    return 0 if all(ok for _, ok in checks) else 1


def _main(argv: list[str]) -> int:
    """``python -m mining.bench.pipeline JOB.json OUT WORKERS RESULT.json [FRAMES [GPUS]]``: one measured run
    (``measure_run``'s child); the job is the JSON of ``JobConfig.to_dict``; FRAMES: each sequence's first
    (0: all); GPUS: logical GPUs of the local Ray (0: those Ray finds)."""
    from mining.config import JobConfig, section_from_dict

    job_json, out, workers, result_json, *rest = argv
    frames, gpus = (int(x) for x in (rest + ["0", "0"])[:2])
    cfg = section_from_dict(JobConfig, json.loads(Path(job_json).read_text()), job_json)
    result = measure_run_here(cfg, out, int(workers), gpus=gpus, frames=frames or None)
    Path(result_json).write_text(json.dumps(result, default=float))
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine bench pipeline``'s options."""
    add_job_options(p)
    p.add_argument("--frames", type=count(), default=200, help="frames per sequence of the scaling job")
    p.add_argument("--sequences", nargs="+", default=["0000", "0001"], help="synthetic sequences of the scaling job")
    p.add_argument("--long", action="store_true", help="also a long run (memory vs sequence length; ~10 min on 2 cores)")
    p.add_argument("--long-frames", type=count(), default=2000, help="frames of the long run")
    p.add_argument("--catalog-rows", type=count(1, 10**8), default=1_000_000,
                   help="tube-frame rows of the catalogue bench")
    p.add_argument("--dir", type=output_folder,
                   help="where the bench catalogues go (default: the system temporary folder)")
    p.add_argument("--json", type=output_file, help="also write the results as JSON here")
    add_overwrite_option(p, "the --json file")


def run(args: argparse.Namespace) -> int:
    """``mine bench pipeline``."""
    return run_pipeline_bench(job_config(args), frames=args.frames, sequences=args.sequences, long=args.long,
                              long_frames=args.long_frames, catalog_rows=args.catalog_rows, workdir=args.dir,
                              json_out=args.json, overwrite=args.overwrite)


if __name__ == "__main__":
    raise SystemExit(_main(sys.argv[1:]))
