"""``mine bench memory``: resident memory of every process of a long job, once per window.

One sequence of ``--frames`` frames goes through the whole job — ``mine submit``'s own
``mine_job`` on a local Ray: observe, track, the stitch and the catalogue writes, caches
swept as a user's run sweeps them. The path is the cheapest a user would run: the
synthetic source (no dataset to fetch) at 414×125 with its default stereo proposer (no
model, no GPU); ``--config``/``--set``/``--option`` pick another.

After each window's track step returns (the executor's ``wait``, in the driver), the
bench reads VmRSS from /proc of every process the job runs, grouped by role:

* ``driver``: this process (the schedule, the manifest writes, the sampler itself);
* ``workers``: the pipeline's ``ray::Worker`` actors (sum over them);
* ``proposal_actors``: the proposal stage's actors, where a model runs on them;
* ``ray_other``: the raylet's other children (idle workers, Ray's agents);
* ``ray_raylet``, ``ray_gcs_server``, …: each of Ray's own daemons, named as Ray names them;
* ``object_store``: the bytes in Ray's object store (``ray memory --stats-only``, MiB resolution).

Per role: ``peak_mb`` (the highest sample, the stitch's included), ``slope_mb_per_1k_frames``
(least squares of the samples against frames done, after the first window: start-up
warms caches and imports once), ``peak_hwm_mb`` (the highest VmHWM of any one process of
the role: peaks between samples) and the samples themselves.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from mining.bench.pipeline import WORKER_TITLE, local_raylet_pid, object_store_bytes, proc_status, start_bench_ray
from mining.catalog import safe_files
from mining.checks import count, output_file, output_folder
from mining.config import JobConfig
from mining.pipeline.arguments import add_job_options, add_overwrite_option, job_config

PROPOSAL_TITLE = "ray::ProposalWorker"  # process title of the proposal stage's actors
CHEAP_SIZE = (125, 414)  # ours: a third of KITTI's sides; at 310×94 and below no tube is found
SLOPE_TARGET_MB = 1.0  # issue 42: every role's growth ≤ 1 MB per 1,000 frames
SKIP_WINDOWS = 1  # the first window's sample is left out of the slope (start-up, first imports)
MB = 2**20  # bytes in the MB the bench reports (MiB, as Ray's own figures)
LOG_EVERY = 10  # ours: a sample line on standard error every this many windows, so a long run's log shows the trend


def slope_per_1k(frames: list[int] | np.ndarray, mb: list[float] | np.ndarray, skip: int = SKIP_WINDOWS) -> float:
    """MB per 1,000 frames: the least-squares line of ``mb`` against ``frames``, first ``skip``
    samples left out; NaN with fewer than two samples (or one frame count) left."""
    f, m = np.asarray(frames, float)[skip:], np.asarray(mb, float)[skip:]
    if len(f) < 2 or np.ptp(f) == 0:
        return float("nan")
    return float(np.polyfit(f, m, 1)[0] * 1000)


def _title(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")[0].decode(errors="replace")
    except (FileNotFoundError, ProcessLookupError, PermissionError):
        return ""


def ray_system_pids() -> dict[int, str]:
    """pid → role (``ray_`` and Ray's name) of Ray's own daemons that this driver's ``ray.init``
    started (raylet, GCS, dashboard, …): each its own role, so a growing one is named."""
    import ray

    node = ray._private.worker.global_worker.node  # noqa: SLF001 - the only handle on the daemons' pids
    return {p.process.pid: f"ray_{name}" for name, procs in node.all_processes.items() for p in procs}


def processes_by_role(driver: int, raylet: int, system: dict[int, str]) -> dict[str, dict[int, dict[str, int]]]:
    """role → pid → /proc status of the job's processes: ``driver``, Ray's daemons (``system``: pid →
    role), and the ``raylet``'s children as ``workers``, ``proposal_actors`` or ``ray_other``."""
    roles: dict[str, dict[int, dict[str, int]]] = {"driver": {}, "workers": {}, "proposal_actors": {},
                                                    "ray_other": {}}
    for pid, role in system.items():
        if st := proc_status(pid):
            roles.setdefault(role, {})[pid] = st
    if st := proc_status(driver):
        roles["driver"][driver] = st
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) in system:
            continue
        st = proc_status(int(entry.name))
        if st.get("PPid") != raylet or "VmRSS" not in st:
            continue
        title = _title(int(entry.name))
        role = ("workers" if title.startswith(WORKER_TITLE) else
                "proposal_actors" if title.startswith(PROPOSAL_TITLE) else "ray_other")
        roles[role][int(entry.name)] = st
    return roles


class MemoryProbe:
    """Samples every role's resident memory (and the object store) when asked: ``sample(frames)``."""

    def __init__(self, driver: int, raylet: int, system: dict[int, str]):
        self.driver, self.raylet, self.system = driver, raylet, system
        self.samples: list[dict[str, Any]] = []  # {"frames", "at", "stitch", role: MB, …}
        self.hwm: dict[str, int] = {}  # role → highest VmHWM (bytes) of any one of its processes
        self.processes: dict[str, set[int]] = {}
        self.store_error = ""
        self.stitch_reset = True  # every worker's peak was reset before the stitch (False: a reset was refused)
        self.stitch_peak_mb: float | None = None  # the highest worker peak from the stitch's start to its end

    def reset_peaks(self) -> None:
        """Reset every worker's VmHWM (``clear_refs`` 5), so the peak read after the stitch is the stitch's."""
        for pid in processes_by_role(self.driver, self.raylet, self.system)["workers"]:
            try:
                Path(f"/proc/{pid}/clear_refs").write_text("5")
            except OSError:
                self.stitch_reset = False

    def sample(self, frames: int, stitch: bool = False) -> None:
        row: dict[str, Any] = {"frames": int(frames), "at": time.time(), "stitch": stitch}
        for role, procs in processes_by_role(self.driver, self.raylet, self.system).items():
            row[role] = sum(st["VmRSS"] for st in procs.values()) / MB
            if stitch and role == "workers" and self.stitch_reset:
                self.stitch_peak_mb = max((st.get("VmHWM", 0) for st in procs.values()), default=0) / MB
            self.processes.setdefault(role, set()).update(procs)
            for st in procs.values():
                self.hwm[role] = max(self.hwm.get(role, 0), st.get("VmHWM", 0), st["VmRSS"])
        try:
            row["object_store"] = object_store_bytes() / MB
        except Exception as e:  # noqa: BLE001 - a report: said in the result, never a silent zero
            self.store_error = f"{type(e).__name__}: {e}"
        self.samples.append(row)
        if stitch or len(self.samples) % LOG_EVERY == 0:
            mbs = ", ".join(f"{k} {v:.0f}" for k, v in row.items() if isinstance(v, float) and k != "at")
            print(f"memory after {'the stitch' if stitch else f'{frames} frames'} (MB): {mbs}", file=sys.stderr,
                  flush=True)

    def roles(self) -> dict[str, dict[str, Any]]:
        """Per role: peak_mb, slope_mb_per_1k_frames (window samples only), peak_hwm_mb, processes, samples."""
        out = {}
        names = [k for k in self.samples[0] if k not in ("frames", "at", "stitch")] if self.samples else []
        for role in names:
            rows = [s for s in self.samples if role in s]
            if role != "object_store" and not self.processes.get(role):
                continue  # a role this job has no process of (no proposal stage, say)
            win = [s for s in rows if not s["stitch"]]
            out[role] = {"peak_mb": max(s[role] for s in rows),
                         "slope_mb_per_1k_frames": slope_per_1k([s["frames"] for s in win], [s[role] for s in win]),
                         "peak_hwm_mb": self.hwm[role] / MB if role in self.hwm else None,
                         "processes": len(self.processes.get(role, ())),
                         "samples": [[s["frames"], round(s[role], 2)] for s in rows]}
        return out


class SamplingExecutor:
    """``mine submit``'s executor with a probe: after each window's track step (and the stitch,
    the ``finalize`` step) the probe samples. Everything else is the wrapped executor's."""

    def __init__(self, inner: Any, probe: MemoryProbe):
        self.inner, self.probe = inner, probe
        self.steps: dict[Any, str] = {}
        self.frames = 0

    def free(self) -> bool:
        return self.inner.free()

    def submit(self, step: str, *args: Any) -> Any:
        if step == "finalize":  # the peak from here to the stitch's end is the stitch's (nothing else runs then)
            self.probe.reset_peaks()
        ref = self.inner.submit(step, *args)
        self.steps[ref] = step
        return ref

    def pending(self) -> int:
        return self.inner.pending()

    def wait(self, timeout: float | None = None):
        got = self.inner.wait(timeout)
        if got is not None:
            ref, result, _ = got
            step = self.steps.pop(ref, "")
            if result is not None and result.ok and step in ("track", "finalize"):
                self.frames += result.frames if step == "track" else 0
                self.probe.sample(self.frames, stitch=step == "finalize")
        return got

    def placement(self) -> dict[str, list[dict[str, Any]]]:
        return self.inner.placement()

    def shutdown(self) -> None:
        self.inner.shutdown()


def memory_job(cfg: JobConfig, frames: int) -> JobConfig:
    """The job's first sequence, ``frames`` frames long (the synthetic source at ``CHEAP_SIZE``
    unless the options name a size)."""
    cfg = copy.deepcopy(cfg)
    cfg.source.sequences = list(cfg.source.sequences[:1]) or ["0000"]
    if cfg.source.dataset == "synthetic":
        h, w = CHEAP_SIZE
        cfg.source.options = {"width": w, "height": h, **cfg.source.options, "n_frames": int(frames)}
    return cfg


def measure_memory(cfg: JobConfig, frames: int, out: str | Path, workers: int) -> dict[str, Any]:
    """Mine ``frames`` frames of ``cfg``'s first sequence into a fresh ``out`` on a local Ray of
    ``workers`` CPUs started here (once a process: Ray's core worker is made once), sampling."""
    out = start_bench_ray(cfg, out, workers)  # first: Ray is imported only after the bind is set
    import ray

    from mining.pipeline.executors import RayExecutor
    from mining.pipeline.submit import mine_job

    try:
        probe = MemoryProbe(os.getpid(), local_raylet_pid(), ray_system_pids())
        probe.sample(0)  # Ray started, nothing mined: the baseline (not in the slope either)
        t0 = time.perf_counter()
        summary = mine_job(cfg, str(out), frames=(0, frames),
                           executor=lambda job: SamplingExecutor(RayExecutor(job, workers), probe))
        seconds = time.perf_counter() - t0
    finally:
        ray.shutdown()
    if summary.failed or summary.stitch_failed:
        raise RuntimeError(f"bench job failed: {summary.lines()}")
    probe.samples = probe.samples[1:]  # the baseline was for the eye; slopes and peaks are of the job
    return {"frames": summary.frames, "windows": summary.windows, "tubes": summary.tubes, "seconds": seconds,
            "fps": summary.frames / max(seconds, 1e-9), "workers": workers,
            "path": f"{cfg.source.dataset} sequence {cfg.source.sequences[0]}, options {cfg.source.options}, "
                    f"proposer {cfg.proposals.proposer}, {cfg.window.core}-frame windows, local Ray of {workers} "
                    "worker(s), mine submit's job with its caches swept",
            "ray_version": ray.__version__, "object_store_error": probe.store_error,
            "load_avg": os.getloadavg(), "stitch_peak_mb": probe.stitch_peak_mb, "roles": probe.roles()}


def report(r: dict[str, Any]) -> bool:
    """Print the table; True when every role's slope is within ``SLOPE_TARGET_MB``."""
    print(f"Memory over one sequence of {r['frames']:,} frames ({r['windows']} windows, {r['tubes']} tubes): "
          f"{r['seconds']:.0f} s, {r['fps']:.2f} frames/s, load avg {r['load_avg'][0]:.2f}")
    print(f"  path: {r['path']}")
    print(f"  {'role':<16} {'processes':>9} {'peak MB':>9} {'peak HWM MB':>12} {'MB / 1k frames':>15} {'samples':>8}")
    ok = True
    for role, v in r["roles"].items():
        s = v["slope_mb_per_1k_frames"]
        ok &= bool(np.isfinite(s) and s <= SLOPE_TARGET_MB)
        hwm = "-" if v["peak_hwm_mb"] is None else f"{v['peak_hwm_mb']:.0f}"
        print(f"  {role:<16} {v['processes']:>9} {v['peak_mb']:9.0f} {hwm:>12} {s:+15.3f} {len(v['samples']):>8}")
    if r.get("stitch_peak_mb") is not None:
        print(f"  the stitch's peak (the worker that ran it, VmHWM reset as it began): {r['stitch_peak_mb']:.0f} MB")
    if r["object_store_error"]:
        print(f"  object store not read: {r['object_store_error']}")
    print("  MB: resident (VmRSS), summed over the role's processes, sampled after each window's track step and "
          "after the stitch; slope: least squares after the first window")
    print(f"  [{'ok' if ok else 'MISS'}] every role's slope ≤ {SLOPE_TARGET_MB:g} MB per 1,000 frames")
    return ok


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine bench memory``'s options."""
    add_job_options(p)
    p.add_argument("--frames", type=count(200, 10**8), default=2000,
                   help="frames of the one sequence mined (default 2,000; an hour at 16 Hz is 57,600)")
    p.add_argument("--workers", type=count(1, 1024), default=None,
                   help="CPU workers of the local Ray (default: this machine's cores)")
    p.add_argument("--dir", type=output_folder, help="where the catalogue goes (default: the system temporary folder)")
    p.add_argument("--json", type=output_file, help="also write the results as JSON here")
    add_overwrite_option(p, "the --json file")


def run(args: argparse.Namespace) -> int:
    """``mine bench memory``: 0 when every role's slope holds, 1 otherwise."""
    cfg = memory_job(job_config(args), args.frames)
    workers = args.workers or len(os.sched_getaffinity(0))
    if args.dir:
        Path(args.dir).mkdir(parents=True, exist_ok=True)  # a --dir not there yet is made, as --out is
    with tempfile.TemporaryDirectory(prefix="bench-memory-", dir=args.dir) as tmp:
        r = measure_memory(cfg, args.frames, Path(tmp) / "out", workers)
    ok = report(r)
    if args.json:
        safe_files.write_file(args.json, json.dumps(r, indent=1, default=float).encode(), args.overwrite)
    return 0 if ok else 1
