"""The pipeline as small steps with one ``run`` each, reading and writing through a Store.

* ``Observe``  — a window's core frames → observation cache (geometry, proposals, localise)
* ``Track``    — a window's context observations → tube pieces as Parquet parts + manifest row
* ``Finalize`` — a sequence's parts → stitched, compacted catalogue tables

Steps are plain objects holding the job; executors (``mining/pipeline/executors.py``)
decide where ``run`` executes (in-process, or Ray workers). Every output has a
deterministic name and is written atomically, so a retried or resubmitted step never
duplicates or half-writes anything; a step whose output exists returns at once (an
observation cache only once it reads back: a damaged or foreign one is recomputed).
Nothing read back from ``--out`` is unpickled (``cache.py``).
"""

from __future__ import annotations

import json
import time
import traceback
from dataclasses import dataclass
from datetime import datetime, timezone

import numpy as np

from mining.catalog.integrity import sequence_files, window_files
from mining.catalog.layout import PART_TABLES, STITCH_ROW, cache_path, observed_path, part_path, stitch_path
from mining.catalog.records import ManifestRow, SequenceMarker, Unreadable
from mining.catalog.rows import RunInfo, frame_rows, frames_row, to_table, tube_row
from mining.catalog.store import Store, write_sequence
from mining.config import JobConfig
from mining.errors import InputError, MiningError
from mining.pipeline.cache import decode_frames, encode_frames
from mining.pipeline.proposal_stage import ModelStage
from mining.pipeline.stitch import check_parts, concat_parts, stitch_windows
from mining.pipeline.window import ObservedFrame, observe_window, track_window
from mining.sources.base import Source
from mining.types import CALLS, SequencePlan, Window


@dataclass(frozen=True)
class TubeCounts:
    """The tubes a sequence's stitch wrote: the selected ones by class, of all candidates."""

    selected: int = 0
    candidates: int = 0
    known: int = 0
    unknown: int = 0
    clutter: int = 0
    unclassified: int = 0


@dataclass
class StepResult:
    """What a step hands back to the loop (``submit.run_job``) and the schedule."""

    window: str  # the window observed or tracked, or the sequence finalized
    ok: bool
    error: str = ""
    seconds: float = 0.0
    frames: int = 0  # observe: frames observed; track: the window's core frames
    cached: bool = False  # observe: the window's observation cache read back (nothing observed)
    recomputed: str = ""  # observe: why its cache did not read back (it was observed again)
    tubes: TubeCounts | None = None  # finalize: what the stitch wrote


@dataclass
class Job:
    """What every step needs: the config, where the catalogue goes, the run it belongs to."""

    cfg: JobConfig
    out: str
    run_id: str
    plans: dict[str, SequencePlan]  # sequence → (possibly sliced) plan
    source_state: object | None = None  # the planning source's Source.shared_state, adopted by each worker's source

    @property
    def params_hash(self) -> str:
        return self.cfg.params_hash

    def store(self) -> Store:
        return Store(self.out)

    def run_info(self, sequence: str) -> RunInfo:
        return RunInfo(self.cfg.source.dataset, sequence, self.run_id, self.params_hash, self.plans[sequence].calib.bf)


_SOURCES: dict[str, Source] = {}


def job_source(job: Job) -> Source:
    """The job's source, opened once per process (sources cache calibration and listings)."""
    s = job.cfg.source
    key = json.dumps([s.dataset, s.root, s.options], sort_keys=True, default=str)
    if key not in _SOURCES:
        _SOURCES[key] = s.open()
        if job.source_state is not None:
            _SOURCES[key].adopt_state(job.source_state)
    return _SOURCES[key]


def _now() -> datetime:
    return datetime.now(timezone.utc)


def _error(e: BaseException) -> str:
    return str(e) if isinstance(e, MiningError) else f"{type(e).__name__}: {e}\n{traceback.format_exc(limit=3)}"


class Observe:
    def __init__(self, job: Job, models: ModelStage | None = None):
        """``models``: where the proposer's model parts run when not here (a proposal actor)."""
        self.job = job
        self.models = models
        self.proposer = None  # made on first use and kept: a model loads once per worker

    def run(self, window: Window) -> StepResult:
        store, t0 = self.job.store(), time.perf_counter()
        path = cache_path(window)
        recomputed = ""
        if store.exists(path):
            try:
                read_cache(store, window)
                return StepResult(window.name, True, cached=True)
            except InputError as e:  # damaged, foreign or of another version: made again below
                recomputed = str(e)
        report = _FrameReport(store, window)
        try:
            frames = observe_window(job_source(self.job), self.job.plans[window.sequence], window, self.job.cfg,
                                    self._proposer(window), report, self.models)
        except (InputError, MiningError) as e:
            return StepResult(window.name, False, _error(e), time.perf_counter() - t0)
        finally:
            report.close()
        store.write_bytes(path, encode_frames(frames))
        return StepResult(window.name, True, seconds=time.perf_counter() - t0, frames=len(frames),
                          recomputed=recomputed)

    def _proposer(self, window: Window):
        from mining.proposals.make import FrameProposer

        calib = self.job.plans[window.sequence].calib
        if self.proposer is None:  # without its model parts where a proposal stage runs them
            self.proposer = FrameProposer(self.job.cfg.proposals, (calib.height, calib.width),
                                          models=self.models is None)
        return self.proposer


FRAME_REPORT_S = 1.0  # ours: a worker reports its observed frame count at most this often


class _FrameReport:
    """``observe_window``'s ``on_frame``: the worker's frame count in ``layout.observed_path``,
    written at most every ``FRAME_REPORT_S`` (the driver's bar reads it), removed at the end."""

    def __init__(self, store: Store, window: Window):
        self.store, self.window, self.last = store, window, 0.0
        self.path = observed_path(window.dataset, window.sequence, window.name)

    def __call__(self, done: int) -> None:
        now = time.perf_counter()
        if now - self.last >= FRAME_REPORT_S:
            self.last = now
            try:
                self.store.write_bytes(self.path, str(done).encode())
            except OSError:
                pass  # progress is best effort: never fail a window over it

    def close(self) -> None:
        try:
            if self.store.exists(self.path):
                self.store.remove(self.path)
        except OSError:
            pass


def observed_so_far(store: Store, windows: list[Window]) -> int:
    """Core frames the observe steps of ``windows`` have reported so far (``_FrameReport``)."""
    n = 0
    for w in windows:
        try:
            n += int(store.read_bytes(observed_path(w.dataset, w.sequence, w.name)).decode() or 0)
        except (MiningError, OSError, ValueError):
            pass  # not started, finished, or mid-write
    return n


def read_cache(store: Store, window: Window) -> list[ObservedFrame]:
    """A window's observation cache; InputError naming the file when it is not one (or not its window's)."""
    path = cache_path(window)
    frames = decode_frames(store.read_bytes(path), store.full(path))
    if any(not window.core[0] <= f.position < window.core[1] for f in frames):
        raise InputError(f"observation cache holds frames outside window {window.name}'s core", store.full(path))
    return frames


def load_context(store: Store, window: Window, neighbours: list[Window]) -> list[ObservedFrame]:
    """The observed frames of ``window``'s context, from the caches of the windows that hold them."""
    a, b = window.context
    frames: list[ObservedFrame] = []
    for w in sorted(neighbours, key=lambda w: w.core[0]):
        if w.core[1] <= a or w.core[0] >= b or not store.exists(cache_path(w)):
            continue
        frames.extend(f for f in read_cache(store, w) if a <= f.position < b)
    return frames


def _write_row(job: Job, dataset: str, sequence: str, name: str, core: tuple[int, int], context: tuple[int, int],
               status: str, started: datetime | None, error: str, **measures) -> None:
    store = job.store()
    prior = ManifestRow.load(store, dataset, sequence, name)  # a damaged row: this attempt's row replaces it
    attempts = 1 + (prior.attempts if isinstance(prior, ManifestRow) else 0)
    ManifestRow(job.run_id, name, tuple(core), tuple(context), status, attempts, job.params_hash, started, _now(),
                error=error, **measures).save(store, dataset, sequence)


def write_manifest(job: Job, window: Window, status: str, started: datetime | None, error: str = "",
                   seconds_observe: float | None = None, seconds_tubes: float | None = None,
                   n_pieces: int | None = None, context_complete: bool | None = None) -> None:
    _write_row(job, window.dataset, window.sequence, window.name, window.core, window.context, status, started, error,
               seconds_observe=seconds_observe, seconds_tubes=seconds_tubes, n_pieces=n_pieces,
               context_complete=context_complete)


def write_stitch_failure(job: Job, sequence: str, windows: list[Window], error: str,
                         started: datetime | None = None) -> None:
    """The manifest row of a sequence whose stitch failed: window ``stitch``, status failed,
    the sequence's planned range as core and context. ``Finalize`` removes it once a stitch
    of the sequence succeeds."""
    span = (min(w.core[0] for w in windows), max(w.core[1] for w in windows)) if windows else (0, 0)
    _write_row(job, job.cfg.source.dataset, sequence, STITCH_ROW, span, span, "failed", started, error)


class Track:
    def __init__(self, job: Job):
        self.job = job

    def run(self, window: Window, neighbours: list[Window], observe: list[StepResult]) -> StepResult:
        """Tube pieces of ``window``; ``observe`` are the observe results of its own core and neighbours."""
        job, store, started, t0 = self.job, self.job.store(), _now(), time.perf_counter()
        own = next(r for r in observe if r.window == window.name)
        seconds_observe = own.seconds if not own.cached else None
        if not own.ok:
            write_manifest(job, window, "failed", started, own.error, seconds_observe)
            return StepResult(window.name, False, own.error)
        try:
            ok = {r.window for r in observe if r.ok}
            frames = load_context(store, window, [w for w in neighbours if w.name in ok])
            mined, poses = track_window(frames, job.cfg)
            n = self._write_parts(window, frames, mined, poses)
        except (InputError, MiningError) as e:
            write_manifest(job, window, "failed", started, _error(e), seconds_observe)
            return StepResult(window.name, False, _error(e))
        seconds = time.perf_counter() - t0
        write_manifest(job, window, "done", started, "", seconds_observe, seconds, n,
                       context_complete=all(r.ok for r in observe))
        return StepResult(window.name, True, seconds=seconds, frames=window.core[1] - window.core[0])

    def _write_parts(self, window: Window, frames: list[ObservedFrame], mined,
                     poses: list[tuple[np.ndarray, int]]) -> int:
        """``poses``: each frame's camera-to-world pose and segment, as ``track_window`` chained them."""
        job, store = self.job, self.job.store()
        cam_from_world = {f.index: np.linalg.inv(p) for f, (p, _) in zip(frames, poses)}
        core_frames = {f.index for f in frames if window.core[0] <= f.position < window.core[1]}
        run = job.run_info(window.sequence)
        tubes, tframes = [], []
        for mt in mined:
            pid = f"{window.name}#{mt.tube.tube_id}"
            row = tube_row(mt, pid, run)
            row["window"] = window.name
            tubes.append(row)
            tframes.extend(frame_rows(mt, pid, cam_from_world.get, core_frames.__contains__, window.name))
        frows = [frames_row(f, pose, segment) for f, (pose, segment) in zip(frames, poses) if f.index in core_frames]
        d, s = window.dataset, window.sequence
        for table, rows in {"tubes": tubes, "tube_frames": tframes, "frames": frows}.items():
            store.write_table(part_path(table, d, s, window.name), to_table(rows, table, part=True))
        # Sizes and checksums of the parts, before the manifest row says done (integrity.py).
        window_files(store, window).save(store)
        return len(tubes)


class Finalize:
    def __init__(self, job: Job):
        self.job = job

    def run(self, sequence: str, windows: list[Window], done: list[str]) -> StepResult:
        """Stitch the parts of the ``done`` windows of a sequence into its catalogue tables."""
        job, store, t0 = self.job, self.job.store(), time.perf_counter()
        d = job.cfg.source.dataset
        ws = [w for w in windows if w.name in set(done)]
        for table in PART_TABLES:  # parts of differing schemas fail here, naming the file and the columns
            paths = [part_path(table, d, sequence, w.name) for w in ws]
            if table == "frames":
                frames = concat_parts(table, [(store.full(p), store.read_table(p)) for p in paths])
            else:  # the tube frames are read one window at a time by the stitch; the tubes parts are not needed
                check_parts(table, [(store.full(p), store.read_schema(p)) for p in paths])
        out = stitch_windows(ws, lambda w: store.read_table(part_path("tube_frames", d, sequence, w.name)),
                             frames, job.cfg, job.run_info(sequence))
        written = []
        for table, data in out.items():
            written += write_sequence(store, table, d, sequence, data)
        rows = [r for w in windows if (r := ManifestRow.load(store, d, sequence, w.name)) is not None]
        if bad := next((r for r in rows if isinstance(r, Unreadable)), None):
            raise InputError(bad.reason, store.full(bad.path))
        if rows:
            written += write_sequence(store, "windows", d, sequence, to_table([r.to_row() for r in rows], "windows"))
        store.remove(stitch_path(d, sequence))  # a failed stitch before this one is repaired
        # The marker comes last and records what it vouches for: the windows stitched, the
        # context of each, and the size and sha256 of every compacted file (integrity.py).
        SequenceMarker(d, sequence, tuple(sorted(done)), files=sequence_files(store, written),
                       params_hash=job.params_hash, run_id=job.run_id,
                       contexts={w.name: tuple(w.context) for w in ws}, planned=len(windows),
                       finished=_now().isoformat()).save(store)
        tubes = out["tubes"]
        sel = np.asarray(tubes.column("selected").to_pylist(), bool)
        calls = [c for c, s in zip(tubes.column("call").to_pylist(), sel) if s]  # mining.types.CALLS
        return StepResult(sequence, True, seconds=time.perf_counter() - t0,
                          tubes=TubeCounts(int(sel.sum()), len(sel), **{c: calls.count(c) for c in CALLS}))
