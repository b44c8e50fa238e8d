"""``mine submit``: plan windows, run the steps on an executor, report.

``open_job`` runs the preflight (``preflight.py``: config, frame range, output, every
sequence's plan and calibration, the proposer — all before job.json is written or Ray
starts; a sequence that cannot be planned is reported and the others run), records the
job (``job.json``: ``resume.record_job``) and reads what earlier runs left
(``resume.read_resume``); the ``Schedule`` (``schedule.py``) orders the steps; ``run_job`` is the loop
that hands them to an executor (``executors.py``: this process, or Ray) and writes what
a step that could not run leaves behind: the window's manifest row, or the sequence's
``stitch`` row, with why (``failures.py``); it also keeps the running-window markers
(``running.py``). ``mine_job`` does all of it in one call.

Scheduling: a window is *tracked* once the observe steps of every window its context
touches have finished, so tracking starts while later windows are still being
observed; a sequence is *finalized* (stitched, compacted) once all its windows are
settled. Resubmitting resumes (``resume.py``: what the records left by earlier runs vouch
for): windows whose manifest row says done (same params, same core and context) and whose
parts are as recorded are skipped, and a sequence whose catalogue already holds exactly its
done windows, in files as recorded, is not rewritten. A finished job resubmitted does
nothing; a damaged file is recomputed by what owns it. What the run did is counted in a
``Summary`` (``summary.py``).

One writer: ``mine_job`` holds the catalogue's lock (``catalog/lock.py``) from planning to
the last result. Holding it, it first removes the temporary files a killed run's writes
left (``resume.sweep_temporaries``: only the names those writes make, only in the job's own
folders, no link followed), counted in the summary. A resubmission must be the same job (``catalog/identity.py``), an
extension of it (``mode="extend"``) or a new run (``mode="new"``): the job's lifecycle
(record, retire, set aside, sweep) is ``resume.py``'s; this module is the loop.

``mine_on_ray`` is ``mine submit`` without a Ray Jobs address (that one is
``rayjobs.py``): the scheduler runs here and the steps run on a Ray of its own, or on
the cluster at ``--address``.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from typing import Any

from mining.catalog import labels
from mining.catalog.identity import job_identity
from mining.catalog.layout import LEGACY_CACHE_SUFFIX, cache_path
from mining.catalog.lock import OutputLock
from mining.catalog.records import UnreadableRecord
from mining.catalog.store import Store
from mining.config import JobConfig
from mining.pipeline.executors import Executor, RayExecutor
from mining.pipeline.failures import describe
from mining.pipeline.leftovers import stitched, sweep_caches
from mining.pipeline.localray import exposure_line, init_local_ray, prepare_local_ray
from mining.pipeline.preflight import Preflight, preflight
from mining.pipeline.running import RunningMarkers
from mining.pipeline.resume import read_resume, record_job, set_aside_unreadable, sweep_temporaries
from mining.pipeline.schedule import Schedule, Step, Task
from mining.pipeline.steps import Job, StepResult, job_source, observed_so_far, write_manifest, write_stitch_failure
from mining.pipeline.summary import Summary
from mining.progress import StepBar
from mining.proposals.make import classifiers_line, classify_hint


def open_job(cfg: JobConfig, out: str, sequences: list[str] | None = None,
             frames: tuple[int, int | None] = (0, None), mode: str = "resume",
             verify: bool = False, pf: Preflight | None = None) -> tuple[Job, Schedule, dict[str, str]]:
    """Preflight and plan the job (or take ``pf``, a preflight already run), record it in
    ``out``'s ``job.json`` (``record_job``: ``mode`` says what a differing identity may do)
    and schedule what is left to do; also the sequences left out (sequence → why they cannot
    be mined). Call it holding the catalogue's lock (``mine_job`` does)."""
    store = Store(out)
    pf = pf if pf is not None else preflight(cfg, out, sequences, frames)
    why = {seq: (e.strip().splitlines() or ["unknown error"])[0] for seq, e in pf.failed.items()}
    record = record_job(store, cfg, pf.windows, job_identity(cfg, pf.plans, frames, list(pf.failed)), mode, why)
    # what planning learnt (RobotCar: chunk indexes) goes to every worker with the job
    job = Job(cfg, out, record.run_id, pf.plans, job_source(Job(cfg, "", "", {})).shared_state())
    return (job, Schedule(pf.windows, read_resume(store, cfg.source.dataset, pf.windows, job.params_hash, verify)),
            pf.failed)


REFRESH_S = 1.0  # ours: the bar redraws at least this often while steps run


def system_failure(task: Task, error: BaseException, max_retries: int) -> StepResult:
    """The failed result of a step that raised, or whose worker died with its retries spent:
    the step, the exception's type and message first (``failures.describe``)."""
    return StepResult(task.name, False, describe(error, task.step, max_retries))


def run_job(job: Job, schedule: Schedule, executor: Executor, progress: bool = False,
            keep_cache: bool = False) -> Summary:
    """Run ``schedule``'s tasks on ``executor`` until none is left.

    ``keep_cache`` keeps the observation caches no track needs any more (benchmarks, the
    sharding test); otherwise they are removed at once (about 0.5 MB a frame).
    """
    t0 = time.perf_counter()
    store, dataset = job.store(), job.cfg.source.dataset
    summary = Summary(windows=len(schedule.windows), skipped=schedule.skipped, started_at=time.time())
    bar = StepBar(len(schedule.todo), progress, sum(w.core[1] - w.core[0] for w in schedule.todo))
    running: dict[Any, Task] = {}
    started: dict[Any, float] = {}  # when each step in flight was submitted (its time, for the ETA)
    markers = RunningMarkers(store, job.run_id, job.params_hash)
    todo = {w.name for w in schedule.todo}
    markers.sweep(todo)
    try:
        while schedule.outstanding or executor.pending():
            while executor.free() and (task := schedule.next_task()) is not None:
                if task.window is not None and task.window.name in todo:
                    markers.mark(task.window, task.step)
                ref = executor.submit(task.step, *task.args)
                running[ref], started[ref] = task, time.perf_counter()
            if not executor.pending():
                continue
            bar.running([t.step for t in running.values()])
            got = executor.wait(REFRESH_S if progress else None)
            if got is None:  # nothing finished yet: redraw (frames the workers report, elapsed, ETA), wait again
                bar.observing = observed_so_far(store, [t.window for t in running.values() if t.step == Step.OBSERVE])
                bar.draw()
                continue
            ref, result, err = got
            task = running.pop(ref)
            if err is not None:
                result = system_failure(task, err, job.cfg.run.max_retries)
                if task.step == Step.TRACK:  # the step wrote no manifest row
                    write_manifest(job, task.window, "failed", None, result.error)
            if task.step == Step.FINALIZE and not result.ok:  # a row in the manifest, for `mine status`
                write_stitch_failure(job, task.sequence, schedule.by_seq[task.sequence], result.error)
            elif (task.step == Step.FINALIZE and not keep_cache  # stitched whole: no track of it needs a cache,
                  and {w.name for w in schedule.by_seq[task.sequence]} <= schedule.ok[task.sequence]):
                sweep_caches(store, dataset, [task.sequence])  # those of windows a killed run observed too
            served = schedule.on_result(task, result)
            if task.window is not None and task.window.name in todo:
                bar.step_finished(task.step, task.window.core[1] - task.window.core[0],
                                  time.perf_counter() - started.pop(ref, time.perf_counter()))
            if task.step == Step.TRACK:
                markers.clear(task.window)
                bar.update(result.ok, result.frames)
            summary.count(task, result, dataset)
            if not keep_cache:
                for w in served:
                    for path in (cache_path(w), cache_path(w, LEGACY_CACHE_SUFFIX)):  # and a pickle of old
                        if store.exists(path):
                            store.remove(path)
    finally:
        bar.close()
        markers.clear_all()  # stopped early (an error, Ctrl-C): what was under way is pending again
    summary.seconds = summary.mining_seconds = time.perf_counter() - t0
    return summary


def mine_job(cfg: JobConfig, out: str, sequences: list[str] | None = None, frames: tuple[int, int | None] = (0, None),
             *, executor: Callable[[Job], Executor], progress: bool = False, keep_cache: bool = False,
             mode: str = "resume", verify: bool = False, lock_wait: float = 0.0) -> Summary:
    """Mine the job into the catalogue at ``out`` on ``executor(job)`` (``LocalExecutor``,
    ``RayExecutor`` on an initialised Ray, or any maker of one), which is made only when
    there is work and shut down at the end.

    The catalogue's lock (``catalog/lock.py``) is held throughout, waiting up to
    ``lock_wait`` seconds for another writer; ``mode`` is ``record_job``'s, ``verify``
    checks every recorded checksum before resuming (``read_resume``).
    """
    t0 = time.perf_counter()
    try:
        pf = preflight(cfg, out, sequences, frames)  # before the lock: a refused job leaves nothing behind
    except UnreadableRecord:
        if mode != "new":
            raise
        pf = None  # --new-run over an unreadable job.json: set aside under the lock, then checked again
    with OutputLock(Store(out), lock_wait):
        swept = sweep_temporaries(Store(out))  # what a killed run left: no write of ours is in flight
        # Under the lock no compaction reads them while they move; --verify is the repair that checks every byte.
        damaged_labels = labels.set_aside_damaged(Store(out)) if verify else []
        if pf is None:
            set_aside_unreadable(Store(out))
            pf = preflight(cfg, out, sequences, frames)
        job, schedule, unplanned = open_job(cfg, out, sequences, frames, mode, verify, pf)
        if schedule.nothing_to_do:
            summary = Summary(windows=len(schedule.windows), skipped=schedule.skipped)
        else:
            ex = executor(job)
            try:
                summary = run_job(job, schedule, ex, progress, keep_cache)
                summary.placement = ex.placement()
            finally:
                ex.shutdown()
        if not keep_cache:  # job end: the caches of every stitched sequence (a finished job resubmitted too)
            planned = {q: [w.name for w in ws] for q, ws in schedule.by_seq.items()}
            sweep_caches(Store(out), cfg.source.dataset, stitched(Store(out), cfg.source.dataset, planned))
        if cfg.embed.model_path:  # the embedding stage, under the same lock: the tubes as just written
            from mining.discovery.embed_run import embed_after_job

            summary.embed = embed_after_job(cfg, out).lines()
    summary.seconds = time.perf_counter() - t0
    summary.classifiers = classifiers_line(cfg.proposals.proposer)
    summary.classify_hint = classify_hint(cfg.proposals.proposer) or ""
    summary.swept = swept
    summary.damaged_labels = damaged_labels
    summary.unplanned = {f"{cfg.source.dataset}/{seq}": error for seq, error in unplanned.items()}
    summary.clamped = [pf.clamped[seq] for seq in sorted(pf.clamped)]
    summary.notes = [pf.notes[seq] for seq in sorted(pf.notes)]
    return summary


def mine_on_ray(cfg: JobConfig, out: str, sequences: list[str] | None = None,
                frames: tuple[int, int | None] = (0, None), address: str | None = None,
                workers: int | None = None, progress: bool = True, mode: str = "resume", verify: bool = False,
                lock_wait: float = 0.0, bind_origin: str = "the job config") -> Summary:
    """``mine submit`` here: the steps on the running cluster at ``address`` (or
    ``RAY_ADDRESS``), which decides the CPUs, or else on a Ray of its own with ``workers``
    CPUs (never one that happens to run on this machine), listening on
    ``cfg.run.bind_host`` only (``localray.py``; a bind beyond loopback is one line on
    standard error, naming ``bind_origin``, where the setting came from). Ray starts only
    when there is work, and is shut down at the end."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    address = address or os.environ.get("RAY_ADDRESS")
    if not address:
        prepare_local_ray(cfg.run.bind_host, bind_origin)  # before `import ray`; a bad --host fails before planning
        if (line := exposure_line(cfg.run.bind_host, bind_origin)) is not None:
            print(line, file=sys.stderr, flush=True)  # before planning: said even when the job then stops
    import ray

    started = []  # Ray is started (and so shut down) here at most once: see the docstring

    def on_ray(job: Job) -> RayExecutor:
        if not ray.is_initialized():
            if address:  # join a running cluster (e.g. as a Ray job's entrypoint)
                ray.init(address=address, log_to_driver=False)
            else:  # every port on run.bind_host (loopback by default)
                init_local_ray(workers, cfg.run.bind_host)
            started.append(True)
        return RayExecutor(job, workers if not address else None)

    try:
        return mine_job(cfg, out, sequences, frames, executor=on_ray, progress=progress, mode=mode, verify=verify,
                        lock_wait=lock_wait)
    finally:
        # Only the Ray this call started, after the executor's actors are gone (mine_job shut
        # them down) and no thread of ours waits on Ray. A process starts Ray once: Ray's core
        # worker does not survive ray.init after ray.shutdown in one process (it can crash at
        # exit), so `mine` commands start it at most once and tests run Ray in processes of
        # their own (tests/_own_process.py).
        if started and ray.is_initialized():
            ray.shutdown()
