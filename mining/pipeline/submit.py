"""``mine submit``: plan windows, run the steps on an executor, report.

``open_job`` plans the windows, records the job (``job.json``) and reads what earlier
runs left; the ``Schedule`` (``schedule.py``) orders the steps; ``run_job`` is the loop
that hands them to an executor (``executors.py``: this process, or Ray) and writes what
a step that could not run leaves behind. ``mine_job`` does all of it in one call.

Scheduling: a window is *tracked* once the observe steps of every window its context
touches have finished, so tracking starts while later windows are still being
observed; a sequence is *finalized* (stitched, compacted) once all its windows are
settled. Resubmitting resumes: windows whose manifest row says done (same params) are
skipped, and a sequence whose catalogue already holds exactly its done windows is not
rewritten. A finished job resubmitted does nothing.

``mine_on_ray`` is ``mine submit`` without a Ray Jobs address (that one is
``rayjobs.py``): the scheduler runs here and the steps run on a Ray of its own, or on
the cluster at ``--address``.
"""

from __future__ import annotations

import json
import os
import sys
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from mining.catalog.layout import (
    LEGACY_CACHE_SUFFIX,
    PART_TABLES,
    JobRecord,
    cache_path,
    done_path,
    manifest_path,
    part_path,
)
from mining.catalog.store import Store
from mining.config import JobConfig
from mining.errors import InputError
from mining.names import check_name
from mining.pipeline.executors import Executor, RayExecutor
from mining.pipeline.schedule import Resume, Schedule, Task
from mining.pipeline.steps import Job, StepResult, job_source, write_manifest
from mining.proposals.make import classifiers_line
from mining.sources.base import Source
from mining.types import Window, plan_windows


@dataclass
class Summary:
    windows: int = 0
    skipped: int = 0
    ok: int = 0
    failed: dict[str, str] = field(default_factory=dict)  # window → error
    frames: int = 0
    tubes: int = 0
    candidates: int = 0
    known: int = 0
    unknown: int = 0
    unclassified: int = 0
    seconds: float = 0.0
    sequences_written: int = 0
    classifiers: str = ""  # which proposers classified (proposals.make.classifiers_line)
    recomputed: dict[str, str] = field(default_factory=dict)  # window → why its observation cache did not read back

    def lines(self) -> list[str]:
        out = [f"windows: {self.ok} ok, {len(self.failed)} failed, {self.skipped} already done (of {self.windows})",
               f"tubes written this run: {self.tubes} selected ({self.known} known, {self.unknown} unknown, "
               f"{self.unclassified} unclassified) of {self.candidates} candidates, in {self.sequences_written} sequence(s)",
               *([self.classifiers] if self.classifiers else []),
               f"time: {self.seconds:.1f} s, {self.frames / max(self.seconds, 1e-9):.2f} frames/s"]
        for w, e in sorted(self.failed.items()):
            out.append(f"FAILED {w}: {e.strip().splitlines()[0] if e.strip() else 'unknown error'}")
        for w, e in sorted(self.recomputed.items()):
            out.append(f"RECOMPUTED {w}: its observation cache did not read back ({e})")
        return out

    def count(self, task: Task, result: StepResult, dataset: str) -> None:
        """Add the result of a task."""
        if task.step == "observe" and result.extra.get("recomputed"):
            self.recomputed[task.target.name] = result.extra["recomputed"]
        if task.step == "track":
            self.frames += result.frames
            if result.ok:
                self.ok += 1
            else:
                self.failed[task.target.name] = result.error
        elif task.step == "finalize":
            if not result.ok:
                self.failed[f"{dataset}/{task.target} (stitching)"] = result.error
                return
            self.sequences_written += 1
            for k in ("tubes", "candidates", "known", "unknown", "unclassified"):
                setattr(self, k, getattr(self, k) + result.extra[k])


def job_sequences(cfg: JobConfig, sequences: list[str] | None, source: Source) -> tuple[list[str], dict[str, str]]:
    """The job's sequence names, and (name → reason) the names of the source's own listing
    that are not safe names. A name the user gave (``--sequences``, the config's
    ``source.sequences``) that is not safe stops the job: InputError naming it."""
    given, origin = (sequences, "--sequences") if sequences else (cfg.source.sequences, "the config's source.sequences")
    if given:
        return [check_name(s, "sequence", origin) for s in given], {}
    listing = f"the {cfg.source.dataset} source's listing of {cfg.source.root or 'its root'}"
    names, refused = [], {}
    for seq in source.sequences():
        try:
            names.append(check_name(seq, "sequence", listing))
        except InputError as e:
            refused[seq] = str(e)
    return names, refused


def plan_job(cfg: JobConfig, sequences: list[str] | None, frames: tuple[int, int | None],
             refused: dict[str, str] | None = None) -> tuple[dict, list[Window]]:
    """Plans and windows of the job's sequences; a sequence of the source's listing whose
    name is not safe is left out and its reason put in ``refused``."""
    source = job_source(Job(cfg, "", "", {}))
    seqs, bad = job_sequences(cfg, sequences, source)
    if refused is not None:
        refused.update(bad)
    plans, windows = {}, []
    for seq in seqs:
        plan = source.plan(seq)
        plans[seq] = plan
        w = cfg.window
        windows += plan_windows(plan, w.core, w.context_before, w.context_after, frames[0], frames[1])
    return plans, windows


def record_job(store: Store, cfg: JobConfig, windows: list[Window]) -> JobRecord:
    """Write (or check and extend) ``job.json``: refuses other params, keeps the run id,
    adds the windows not planned before."""
    old = JobRecord.load(store)
    if old is not None:
        old.check(cfg.params_hash, store.uri)
    prior = old.windows if old is not None else []
    known = {w.name for w in prior}
    record = JobRecord(old.run_id if old is not None else uuid.uuid4().hex[:12], cfg.params_hash, cfg.to_dict(),
                       prior + [w for w in windows if w.name not in known])
    if record.windows != prior:  # a resubmission of the same job changes nothing
        record.save(store)
    return record


def read_resume(store: Store, dataset: str, windows: list[Window], params_hash: str) -> Resume:
    """What earlier runs left: windows whose manifest row says done with these params and
    whose parts all exist (each with whether its context was complete when it was
    tracked), and the sequences finalized with these params (the windows each holds)."""
    done = {}
    for w in windows:
        m = manifest_path(w.dataset, w.sequence, w.name)
        if not store.exists(m):
            continue
        row = store.read_table(m).to_pylist()[0]
        if row["status"] == "done" and row["params_hash"] == params_hash and all(
                store.exists(part_path(t, w.dataset, w.sequence, w.name)) for t in PART_TABLES):
            done[w.name] = row.get("context_complete") is not False
    finalized = {}
    for seq in dict.fromkeys(w.sequence for w in windows):
        if store.exists(done_path(dataset, seq)):
            marker = json.loads(store.read_bytes(done_path(dataset, seq)))
            if marker["params_hash"] == params_hash:
                finalized[seq] = frozenset(marker["windows"])
    return Resume(done, finalized)


def open_job(cfg: JobConfig, out: str, sequences: list[str] | None = None,
             frames: tuple[int, int | None] = (0, None)) -> tuple[Job, Schedule]:
    """Plan the job, record it in ``out``'s ``job.json`` and schedule what is left to do."""
    store = Store(out)
    refused: dict[str, str] = {}
    plans, windows = plan_job(cfg, sequences, frames, refused)
    record = record_job(store, cfg, windows)
    job = Job(cfg, out, record.run_id, plans, refused)
    return job, Schedule(windows, read_resume(store, cfg.source.dataset, windows, job.params_hash))


class Progress:
    def __init__(self, total: int, enabled: bool):
        self.total, self.enabled, self.t0 = total, enabled, time.perf_counter()
        self.done = self.failed = self.frames = 0

    def update(self, ok: bool, frames: int) -> None:
        self.done += 1
        self.failed += not ok
        self.frames += frames
        if self.enabled:
            dt = time.perf_counter() - self.t0
            n = 30 * self.done // max(self.total, 1)
            sys.stderr.write(f"\r[{'#' * n}{'.' * (30 - n)}] windows {self.done}/{self.total}"
                             f" ({self.failed} failed)  {self.frames / max(dt, 1e-9):.2f} frames/s  {dt:.0f} s ")
            sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")


def system_failure(task: Task, error: BaseException, max_retries: int) -> StepResult:
    """The failed result of a step that could not run (its worker died and retries are spent)."""
    if task.step == "observe":
        return StepResult(task.target.name, False, f"system failure: {error}")
    if task.step == "track":
        return StepResult(task.target.name, False, f"system failure after {max_retries} retries: {error}")
    return StepResult(task.target, False, str(error))


def run_job(job: Job, schedule: Schedule, executor: Executor, progress: bool = False,
            keep_cache: bool = False) -> Summary:
    """Run ``schedule``'s tasks on ``executor`` until none is left.

    ``keep_cache`` keeps the observation caches no track needs any more (benchmarks, the
    sharding test); otherwise they are removed at once (about 0.5 MB a frame).
    """
    t0 = time.perf_counter()
    store, dataset = job.store(), job.cfg.source.dataset
    summary = Summary(windows=len(schedule.windows), skipped=schedule.skipped)
    bar = Progress(len(schedule.todo), progress)
    running: dict[Any, Task] = {}
    try:
        while schedule.outstanding or executor.pending():
            while executor.free() and (task := schedule.next_task()) is not None:
                running[executor.submit(task.step, *task.args)] = task
            if not executor.pending():
                continue
            ref, result, err = executor.wait()
            task = running.pop(ref)
            if err is not None:
                result = system_failure(task, err, job.cfg.run.max_retries)
                if task.step == "track":  # the step wrote no manifest row
                    write_manifest(job, task.target, "failed", None, result.error)
            served = schedule.on_result(task, result)
            if task.step == "track":
                bar.update(result.ok, result.frames)
            summary.count(task, result, dataset)
            if not keep_cache:
                for w in served:
                    for path in (cache_path(w), cache_path(w, LEGACY_CACHE_SUFFIX)):  # and a pickle of old
                        if store.exists(path):
                            store.remove(path)
    finally:
        bar.close()
    summary.seconds = time.perf_counter() - t0
    return summary


def mine_job(cfg: JobConfig, out: str, sequences: list[str] | None = None, frames: tuple[int, int | None] = (0, None),
             *, executor: Callable[[Job], Executor], progress: bool = False, keep_cache: bool = False) -> Summary:
    """Mine the job into the catalogue at ``out`` on ``executor(job)`` (``LocalExecutor``,
    ``RayExecutor`` on an initialised Ray, or any maker of one), which is made only when
    there is work and shut down at the end."""
    t0 = time.perf_counter()
    job, schedule = open_job(cfg, out, sequences, frames)
    if schedule.nothing_to_do:
        summary = Summary(windows=len(schedule.windows), skipped=schedule.skipped)
    else:
        ex = executor(job)
        try:
            summary = run_job(job, schedule, ex, progress, keep_cache)
        finally:
            ex.shutdown()
    for seq, reason in job.refused.items():  # sequences that never got a window
        summary.failed[f"{cfg.source.dataset}/{seq} (planning)"] = reason
    summary.seconds = time.perf_counter() - t0
    summary.classifiers = classifiers_line(cfg.proposals.proposer)
    return summary


def mine_on_ray(cfg: JobConfig, out: str, sequences: list[str] | None = None,
                frames: tuple[int, int | None] = (0, None), address: str | None = None,
                workers: int | None = None, progress: bool = True) -> Summary:
    """``mine submit`` here: the steps on the running cluster at ``address`` (or
    ``RAY_ADDRESS``), which decides the CPUs, or else on a Ray of its own with ``workers``
    CPUs (never one that happens to run on this machine). Ray starts only when there is
    work, and is shut down at the end."""
    import ray

    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    address = address or os.environ.get("RAY_ADDRESS")

    def on_ray(job: Job) -> RayExecutor:
        if not ray.is_initialized():
            if address:  # join a running cluster (e.g. as a Ray job's entrypoint)
                ray.init(address=address, log_to_driver=False)
            else:
                ray.init(address="local", num_cpus=workers, include_dashboard=False, log_to_driver=False)
        return RayExecutor(job, workers if not address else None)

    try:
        return mine_job(cfg, out, sequences, frames, executor=on_ray, progress=progress)
    finally:
        if ray.is_initialized():
            ray.shutdown()
