"""``mine submit``: plan windows, run the steps on an executor, report.

Scheduling: a window is *tracked* once the observe steps of every window its context
touches have finished, so tracking starts while later windows are still being
observed; a sequence is *finalized* (stitched, compacted) once all its windows are
settled. Resubmitting resumes: windows whose manifest row says done (same params) are
skipped, and a sequence whose catalogue already holds exactly its done windows is not
rewritten. A finished job resubmitted does nothing.

With ``--address http://HOST:8265`` the same command line is handed to the cluster
through Ray Jobs and runs there (``--address auto`` on the head node; relative --config,
--root and --out are made absolute here and read on the cluster); with any other address
the scheduler runs here and the steps run on that cluster.
"""

from __future__ import annotations

import argparse
import bisect
import json
import os
import shlex
import sys
import time
import uuid
from collections import defaultdict, deque
from dataclasses import dataclass, field

from mining.catalog.layout import PART_TABLES, JobRecord, cache_path, done_path, manifest_path, part_path
from mining.catalog.store import Store
from mining.config import JobConfig
from mining.errors import ConfigError
from mining.pipeline.steps import Job, StepResult, job_source
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
    seconds: float = 0.0
    sequences_written: int = 0

    def lines(self) -> list[str]:
        out = [f"windows: {self.ok} ok, {len(self.failed)} failed, {self.skipped} already done (of {self.windows})",
               f"tubes written this run: {self.tubes} selected ({self.known} known, {self.unknown} unknown) "
               f"of {self.candidates} candidates, in {self.sequences_written} sequence(s)",
               f"time: {self.seconds:.1f} s, {self.frames / max(self.seconds, 1e-9):.2f} frames/s"]
        for w, e in sorted(self.failed.items()):
            out.append(f"FAILED {w}: {e.strip().splitlines()[0] if e.strip() else 'unknown error'}")
        return out


def neighbours(window: Window, windows: list[Window]) -> list[Window]:
    """The windows whose core frames lie in ``window``'s context (itself included)."""
    a, b = window.context
    return [w for w in windows if w.sequence == window.sequence and w.core[0] < b and w.core[1] > a]


def neighbour_map(windows: list[Window]) -> dict[str, list[Window]]:
    """``neighbours`` of every window, by a sweep over each sequence's sorted cores
    (a recording of hours has thousands of windows: no scan over all of them per window)."""
    out: dict[str, list[Window]] = {}
    by_seq: dict[str, list[Window]] = defaultdict(list)
    for w in windows:
        by_seq[w.sequence].append(w)
    for ws in by_seq.values():
        ws = sorted(ws, key=lambda w: w.core[0])
        starts = [w.core[0] for w in ws]
        for w in ws:
            a, b = w.context
            lo = max(0, bisect.bisect_right(starts, a) - 1)
            hi = bisect.bisect_left(starts, b)
            out[w.name] = [n for n in ws[lo:hi] if n.core[0] < b and n.core[1] > a]
    return out


def plan_job(cfg: JobConfig, sequences: list[str] | None, frames: tuple[int, int | None]) -> tuple[dict, list[Window]]:
    source = job_source(Job(cfg, "", "", {}))
    seqs = sequences or cfg.source.sequences or source.sequences()
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


def done_windows(store: Store, windows: list[Window], params_hash: str) -> dict[str, bool]:
    """Windows whose manifest row says done with these params and whose parts all exist,
    each with whether its context was complete when it was tracked."""
    done = {}
    for w in windows:
        m = manifest_path(w.dataset, w.sequence, w.name)
        if not store.exists(m):
            continue
        row = store.read_table(m).to_pylist()[0]
        if row["status"] == "done" and row["params_hash"] == params_hash and all(
                store.exists(part_path(t, w.dataset, w.sequence, w.name)) for t in PART_TABLES):
            done[w.name] = row.get("context_complete") is not False
    return done


def finalized(store: Store, dataset: str, sequence: str, done: set[str], params_hash: str) -> bool:
    if not store.exists(done_path(dataset, sequence)):
        return False
    marker = json.loads(store.read_bytes(done_path(dataset, sequence)))
    return marker["params_hash"] == params_hash and set(marker["windows"]) == done


def _drop_served_caches(store: Store, served: list[Window], users: dict[str, list[Window]], ok: set[str]) -> None:
    """Remove the observation caches no track needs any more: a window's cache serves the
    windows whose context holds its core, and is kept while any of them is not done (it
    may run again). Caches are about 0.5 MB a frame: they must not pile up over hours."""
    for n in served:
        if all(m.name in ok for m in users[n.name]) and store.exists(cache_path(n)):
            store.remove(cache_path(n))


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


def run_job(cfg: JobConfig, out: str, sequences: list[str] | None = None, frames: tuple[int, int | None] = (0, None),
            executor: str = "ray", workers: int | None = None, progress: bool = False,
            keep_cache: bool = False, connect=None) -> Summary:
    """Mine the job into the catalogue at ``out``.

    ``executor="ray"`` runs the steps on Ray: ``connect()`` is called first when there is
    work (it initialises Ray), unless Ray is initialised already. ``keep_cache`` keeps the
    observation cache of complete sequences (benchmarks, the sharding test).
    """
    t0 = time.perf_counter()
    store = Store(out)
    plans, windows = plan_job(cfg, sequences, frames)
    job = Job(cfg, out, record_job(store, cfg, windows).run_id, plans)
    dataset = cfg.source.dataset
    by_seq: dict[str, list[Window]] = defaultdict(list)
    for w in windows:
        by_seq[w.sequence].append(w)

    complete = done_windows(store, windows, job.params_hash)
    done = set(complete)
    # A window tracked while a neighbour had failed saw less context; once that neighbour
    # runs again, track it again too (its observations are cached), so a repaired job ends
    # as a clean run would.
    nbrs = neighbour_map(windows)
    users: dict[str, list[Window]] = defaultdict(list)  # the windows whose context holds a window's core
    for w in windows:
        for n in nbrs[w.name]:
            users[n.name].append(w)
    rerun = {w.name for w in windows if w.name not in done}
    for w in windows:
        if w.name in done and not complete[w.name]:
            if any(n.name in rerun for n in nbrs[w.name]):
                done.discard(w.name)
    todo = [w for w in windows if w.name not in done]
    summary = Summary(windows=len(windows), skipped=len(done))
    to_finalize = {s for s, ws in by_seq.items()
                   if any(w.name not in done for w in ws) or not finalized(store, dataset, s, done & {w.name for w in ws}, job.params_hash)}
    if not todo and not to_finalize:
        summary.seconds = time.perf_counter() - t0
        return summary

    need_obs = {n.name for w in todo for n in nbrs[w.name]}
    obs_queue = deque(w for w in windows if w.name in need_obs)
    todo_names = {w.name for w in todo}
    waiting = {w.name: len(nbrs[w.name]) for w in todo}  # observe results a track still waits for
    ready: deque[Window] = deque()
    obs_result: dict[str, StepResult] = {}
    ok_windows: dict[str, set[str]] = {s: {w.name for w in ws if w.name in done} for s, ws in by_seq.items()}
    left = {s: sum(1 for w in ws if w.name not in done) for s, ws in by_seq.items()}
    fin_queue = deque(s for s in sorted(to_finalize) if left[s] == 0)
    kinds: dict = {}

    if executor == "ray":
        from mining.pipeline.executors import RayExecutor

        import ray
        if not ray.is_initialized():
            (connect or ray.init)()
        n = workers or max(1, int(ray.available_resources().get("CPU", 1)))
        ex = RayExecutor(job, n, cfg.run.max_retries)
    else:
        from mining.pipeline.executors import LocalExecutor

        ex = LocalExecutor(job)
    bar = Progress(len(todo), progress)
    try:
        while obs_queue or ready or any(waiting.values()) or fin_queue or ex.pending():
            while ex.free():
                # Tracks first (they write the parts), then observes (tracks wait on them);
                # a sequence's stitching has no dependents, so it fills otherwise idle workers.
                if ready:
                    w = ready.popleft()
                    nb = nbrs[w.name]
                    kinds[ex.submit("track", w, nb, [obs_result[n.name] for n in nb])] = ("track", w)
                elif obs_queue:
                    w = obs_queue.popleft()
                    kinds[ex.submit("observe", w)] = ("observe", w)
                elif fin_queue:
                    seq = fin_queue.popleft()
                    kinds[ex.submit("finalize", seq, by_seq[seq], sorted(ok_windows[seq]))] = ("finalize", seq)
                else:
                    break
            if not ex.pending():
                continue
            ref, result, err = ex.wait()
            kind, what = kinds.pop(ref)
            if kind == "observe":
                obs_result[what.name] = result if err is None else StepResult(what.name, False, f"system failure: {err}")
                for u in users[what.name]:
                    if u.name in todo_names:
                        waiting[u.name] -= 1
                        if waiting[u.name] == 0:
                            ready.append(u)
            elif kind == "track":
                if err is not None:
                    result = StepResult(what.name, False, f"system failure after {cfg.run.max_retries} retries: {err}")
                    from mining.pipeline.steps import write_manifest

                    write_manifest(job, what, "failed", None, result.error)
                bar.update(result.ok, result.frames)
                summary.frames += result.frames
                if result.ok:
                    summary.ok += 1
                    ok_windows[what.sequence].add(what.name)
                    if not keep_cache:
                        _drop_served_caches(store, nbrs[what.name], users, ok_windows[what.sequence])
                else:
                    summary.failed[what.name] = result.error
                left[what.sequence] -= 1
                if left[what.sequence] == 0 and what.sequence in to_finalize:
                    fin_queue.append(what.sequence)
            else:
                if err is not None or not result.ok:
                    summary.failed[f"{dataset}/{what} (stitching)"] = str(err) if err is not None else result.error
                    continue
                summary.sequences_written += 1
                for k in ("tubes", "candidates", "known", "unknown"):
                    setattr(summary, k, getattr(summary, k) + result.extra[k])
    finally:
        bar.close()
        ex.shutdown()
    summary.seconds = time.perf_counter() - t0
    return summary


# Options of ``mine submit`` that name a local path. On the cluster the job runs in a
# working directory of Ray's, so relative paths are made absolute here before the command
# line travels; they are then read *on the cluster*, which is right when the head is this
# machine or mounts the same files at the same place (URIs such as s3://... pass as they are).
_PATH_OPTIONS = ("--config", "--root", "--out")


def _absolute(path: str) -> str:
    return path if "://" in path else os.path.abspath(path)


def _forwarded_argv(argv: list[str], out: str) -> list[str]:
    """The command line for the cluster: no ``--address``, paths absolute, ``--out`` explicit.

    ``argv`` is what followed ``mine`` (``submit`` first); ``out`` is the catalogue the
    command line means, named explicitly so that the default lands where it would here.
    """
    fwd: list[str] = []
    it = iter(argv)
    for a in it:
        opt, eq, value = a.partition("=")
        if opt == "--address":
            if not eq:
                next(it, None)
            continue
        if opt in _PATH_OPTIONS:
            value = value if eq else next(it, "")
            fwd += [opt, _absolute(value)]
            continue
        fwd.append(a)
    if "--out" not in fwd:
        fwd += ["--out", _absolute(out)]
    return fwd


def submit_ray_job(address: str, argv: list[str], out: str, poll_s: float = 1.0) -> int:
    """Hand the command line to a cluster through Ray Jobs, print its logs as they come, and
    return its driver's exit status (1 when the job failed without one, e.g. it was stopped).

    The entrypoint is ``mine ... --address auto``: ``mine`` must be on the PATH the cluster's
    Ray was started with, and the driver joins that cluster (Ray Jobs sets RAY_ADDRESS).
    """
    try:
        from ray.job_submission import JobStatus, JobSubmissionClient
    except ImportError as e:
        raise ConfigError(f"--address {address} needs Ray Jobs: pip install '.[cluster]' ({e})") from None
    try:
        client = JobSubmissionClient(address)
    except ConnectionError as e:
        raise ConfigError(f"no Ray Jobs server at --address {address}: {e}") from None
    entry = shlex.join(["mine", *_forwarded_argv(argv, out), "--address", "auto", "--no-progress"])
    job_id = client.submit_job(entrypoint=entry)
    print(f"submitted Ray job {job_id}: {entry}", file=sys.stderr)
    shown = 0
    try:
        while True:
            status = client.get_job_status(job_id)  # before the logs: a finished job's logs are complete
            logs = client.get_job_logs(job_id)
            sys.stdout.write(logs[shown:])
            sys.stdout.flush()
            shown = len(logs)
            if status.is_terminal():
                break
            time.sleep(poll_s)
    except KeyboardInterrupt:
        print(f"\nstopped following; the job goes on (stop it with: ray job stop --address {address} {job_id})",
              file=sys.stderr)
        return 130
    if status == JobStatus.SUCCEEDED:
        return 0
    info = client.get_job_info(job_id)
    reason = (info.message or "").strip().splitlines()[:1]  # the rest repeats the logs shown above
    print(f"Ray job {job_id} {status.value}: {''.join(reason)}".rstrip(), file=sys.stderr)
    code = getattr(info, "driver_exit_code", None)
    return code if code else 1


def submit_from_args(args: argparse.Namespace, cfg: JobConfig) -> int:
    address = args.address
    if address and address.startswith("http"):
        return submit_ray_job(address, args.argv, args.out)
    import ray

    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    address = address or os.environ.get("RAY_ADDRESS")

    def connect() -> None:
        if address:  # join a running cluster (e.g. as a Ray job's entrypoint): it decides the CPUs
            ray.init(address=address, log_to_driver=False)
        else:  # "local": a Ray of our own, never one that happens to run on this machine
            ray.init(address="local", num_cpus=args.workers, include_dashboard=False, log_to_driver=False)

    try:
        summary = run_job(cfg, args.out, args.sequences, args.frames, "ray",
                          workers=args.workers if not address else None, progress=not args.no_progress,
                          connect=connect)
    finally:
        if ray.is_initialized():
            ray.shutdown()
    for line in summary.lines():
        print(line)
    return 1 if summary.failed else 0
