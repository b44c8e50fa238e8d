"""``mine submit``: plan windows, run the steps on an executor, report.

``open_job`` runs the preflight (``preflight.py``: config, frame range, output, every
sequence's plan and calibration, the proposer — all before job.json is written or Ray
starts; a sequence that cannot be planned is reported and the others run), records the
job (``job.json``) and reads what earlier runs left; the ``Schedule`` (``schedule.py``) orders the steps; ``run_job`` is the loop
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
left (``sweep_temporaries``: only the names those writes make, only in the job's own
folders, no link followed), counted in the summary. A resubmission must be the same job (``catalog/identity.py``), an
extension of it (``mode="extend"``) or a new run (``mode="new"``).

``mine_on_ray`` is ``mine submit`` without a Ray Jobs address (that one is
``rayjobs.py``): the scheduler runs here and the steps run on a Ray of its own, or on
the cluster at ``--address``.
"""

from __future__ import annotations

import os
import sys
import time
import uuid
from collections.abc import Callable
from typing import Any

import pyarrow.fs as pafs

from mining.catalog.identity import check_resubmit, job_identity
from mining.catalog.layout import (FRESH_START, JOB, JOB_ENTRIES, LABELS, LEGACY_CACHE_SUFFIX, PART_TABLES, REPLACED,
                                   JobRecord, UnreadableRecord, cache_path, check_resumable, files_path, manifest_path,
                                   part_path)
from mining.catalog.lock import OutputLock
from mining.catalog.store import Store
from mining.config import JobConfig
from mining.errors import ConfigError, InputError
from mining.pipeline.executors import Executor, RayExecutor
from mining.pipeline.failures import describe
from mining.pipeline.localray import exposure_line, init_local_ray, prepare_local_ray
from mining.pipeline.preflight import Preflight, preflight
from mining.pipeline.running import RunningMarkers
from mining.pipeline.resume import read_resume
from mining.pipeline.schedule import Schedule, Step, Task
from mining.pipeline.steps import Job, StepResult, observed_so_far, write_manifest, write_stitch_failure
from mining.pipeline.summary import Summary
from mining.progress import StepBar
from mining.proposals.make import classifiers_line, classify_hint
from mining.types import Window


def _retire(store: Store, prior: list[Window], windows: list[Window]) -> None:
    """Remove what the windows of ``prior`` that are no longer the job's left behind (an
    extension re-cuts the windows at the old range's end): their manifest rows, parts,
    integrity records and caches. A window of the same name stays (it is resumed or, when
    its context changed, runs again and overwrites them)."""
    names = {w.name for w in windows}
    for w in prior:
        if w.name in names:
            continue
        d, q = w.dataset, w.sequence
        for rel in (manifest_path(d, q, w.name), files_path(d, q, w.name), cache_path(w),
                    *(part_path(t, d, q, w.name) for t in PART_TABLES)):
            store.remove(rel)


def _move_aside(store: Store, run_id: str | None) -> str:
    """``--new-run``: move the old catalogue's files into ``REPLACED/<run id>-<UTC time>/``
    inside ``--out`` (a rename each; readers never look there); ``unknown-run`` stands for
    the run id of a catalogue whose job.json is lost or unreadable. Only a local folder can:
    object stores have no rename, so there the old catalogue must be removed by hand."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    name = f"{run_id or 'unknown-run'}-{stamp}"
    # The labels go too: the new run's tube ids may name other objects.
    present = [e for e in (*JOB_ENTRIES, LABELS) if store.fs.get_file_info(store.full(e)).type != pafs.FileType.NotFound]
    if not store.local:
        raise ConfigError(f"{store.uri}: --new-run cannot move the old catalogue (run {run_id or 'unknown'}) aside on "
                          f"this filesystem (no rename); delete {', '.join(present)} there, or use another --out")
    taken = {info.base_name for info in store.fs.get_file_info(
        pafs.FileSelector(store.full(REPLACED), allow_not_found=True))}
    k = 1
    while (dest := f"{REPLACED}/{name}" + (f"-{k}" if k > 1 else "")).rsplit("/", 1)[1] in taken:
        k += 1  # two new runs in one second: never move into a folder that holds an older catalogue
    store.make_dir(dest)  # never through a link planted at OUT/_replaced (safe_files)
    for e in present:
        store.move(e, f"{dest}/{e}")
    return dest


def catalogue_data(store: Store) -> list[str]:
    """The entries of a job's catalogue (``JOB_ENTRIES`` but job.json) that hold files."""
    return [f"{e}/" for e in JOB_ENTRIES if e != JOB and store.list(e, suffix="")]


def record_job(store: Store, cfg: JobConfig, windows: list[Window], identity: dict, mode: str = "resume",
               unplanned: dict[str, str] | None = None) -> JobRecord:
    """Write (or check and update) ``job.json``; ``unplanned``: the sequences this submit could
    not plan and why (``mine status`` shows them).

    ``mode`` (``identity.MODES``): ``resume`` refuses another identity, naming every
    differing key; ``extend`` admits wider frame ranges and added sequences, and retires
    the old windows the new cut does not have; ``new`` moves an old catalogue aside and
    starts a new run. The run id is kept across resumes and extensions.

    A folder with catalogue data but no job.json (lost, or moved away) or an unreadable one
    is not an empty folder: mining into it would replace that catalogue, so it is refused
    unless ``new``, which moves it aside like any other. So is a catalogue whose tables lie in
    the hive folders of schema v2 (``layout.check_resumable``): ``new`` moves it aside too.
    """
    lost = ""  # why the catalogue in --out has no job record, when it has none but holds data
    try:
        old = JobRecord.load(store)
    except UnreadableRecord:
        if mode != "new":
            raise
        old, lost = None, "its job.json did not read as a job record"
    if old is None and not lost and (data := catalogue_data(store)):
        if mode != "new":
            raise InputError(f"missing, but {store.uri} holds catalogue data ({', '.join(data)}), whose job is then "
                             "unknown: it can be neither resumed nor extended, and mining there would replace it; "
                             f"{FRESH_START}", store.full(JOB))
        lost = "it had no job.json"
    if mode == "new" and (old is not None or lost):
        run_id = old.run_id if old is not None else None
        _announce(store, run_id, _move_aside(store, run_id), lost)
        old = None
    if old is not None:
        check_resumable(store)  # a catalogue before schema v3 (hive folders): read, never resumed or extended
        check_resubmit(old.identity, identity, store.uri, mode)
        old.check(cfg.params_hash, store.uri)  # every config key is in the identity: never reached
        _retire(store, old.windows, windows)
    record = JobRecord(old.run_id if old is not None else uuid.uuid4().hex[:12], cfg.params_hash, cfg.to_dict(),
                       list(windows), identity, dict(unplanned or {}))
    if (old is None or record.windows != old.windows or record.identity != old.identity
            or record.unplanned != old.unplanned):
        record.save(store)  # a resubmission of the same job changes nothing
    return record


def _announce(store: Store, run_id: str | None, dest: str, why: str = "") -> None:
    what = f"run {run_id}" if run_id else f"run unknown: {why}"
    print(f"mine: --new-run: the old catalogue ({what}) is now {store.full(dest)}; "
          "delete it when it is no longer needed", file=sys.stderr)


def set_aside_unreadable(store: Store) -> None:
    """``--new-run`` over an unreadable job.json, before the preflight that would refuse it:
    the old catalogue goes to ``REPLACED`` as ``record_job`` would move it."""
    try:
        JobRecord.load(store)
    except UnreadableRecord:
        _announce(store, None, _move_aside(store, None), "its job.json did not read as a job record")


def sweep_temporaries(store: Store) -> list[str]:
    """Remove the temporary files unfinished writes left under ``store`` (``Store.temporaries``);
    their full paths. Call it holding the catalogue's lock: then no write is in flight."""
    swept = store.temporaries()
    for rel in swept:
        store.remove(rel)  # the entry itself, its folders entered without following a link
    return [store.full(rel) for rel in swept]


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
    job = Job(cfg, out, record.run_id, pf.plans)
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
    summary.seconds = time.perf_counter() - t0
    summary.classifiers = classifiers_line(cfg.proposals.proposer)
    summary.classify_hint = classify_hint(cfg.proposals.proposer) or ""
    summary.swept = swept
    summary.unplanned = {f"{cfg.source.dataset}/{seq}": error for seq, error in unplanned.items()}
    summary.clamped = [pf.clamped[seq] for seq in sorted(pf.clamped)]
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
        prepare_local_ray(cfg.run.bind_host)  # before `import ray`; a bad --host fails before planning
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
