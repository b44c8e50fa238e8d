"""``mine embed``: the tubes a predicate selects, embedded by the user's image encoder (``embed.py``)
on actors like the proposal stage's, into the ``tube_embeddings`` table (``catalog/embeddings.py``).

Order of work, so that nothing is written for a bad model or a wrong catalogue:

1. the catalogue and its ``job.json`` are read, the model is loaded and checked (``Encoder``);
2. the writer lock of ``--out`` is taken (``catalog/lock.py``: never beside a ``mine submit``);
3. per sequence, the tubes whose vector by this model (sha256), settings and views is stored are
   skipped (incremental: a second run embeds nothing, a changed model embeds all again); files
   a killed run left unrecorded are swept;
4. the others go to the actors ``tubes_per_task`` at a time; each task re-reads its frames
   through the job's source (each frame once), crops the views, runs the model and returns a
   vector per tube, or the reason a tube failed (a frame the source lacks, a bad mask): such a
   tube fails alone, named, and the command exits 2 after writing the others;
5. each finished task is written as one file and recorded in its marker at once, so a killed run
   resumes after the last recorded task.

Actors (``EmbedWorker``): ``embed.actors`` (-1: one per GPU Ray lists, each holding
``embed.gpus_per_actor``, onnxruntime's CUDA provider where it has one; without GPUs, or 0, one
per CPU, on the CPU provider; N: N actors). ``use_ray=False`` runs the same worker in this process.

``mine submit`` runs the same as its last stage where ``embed.model_path`` is set
(``embed_after_job``): the model checked in its preflight, the tubes embedded under its lock.
"""

from __future__ import annotations

import os
import sys
from collections import deque
from contextlib import nullcontext
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from mining.catalog import embeddings
from mining.catalog.lock import OutputLock
from mining.catalog.rows import mask_rle
from mining.catalog.store import Store
from mining.catalog.views import connect
from mining.config import EmbedConfig, JobConfig, SourceConfig
from mining.discovery.embed import Encoder, best_views, settings_key, tube_vector, views_key
from mining.errors import InputError, MiningError
from mining.export.selection import by_sequence, frames_by_tube, read_job, selected_rows
from mining.masks import areas

FAILED = 2  # exit status: some tubes failed (named), the others were written
ACTOR_RETRIES = 1  # ours: a dead actor restarts once and its task runs again (then its tubes fail, named)


@dataclass
class Task:
    """Tubes of one sequence to embed: per tube its views (frame, bbox)."""

    dataset: str
    sequence: str
    tubes: list[tuple[str, str, list[tuple[int, list[float]]]]]  # (tube id, views key, [(frame, bbox)])


@dataclass
class EmbedResult:
    vectors: dict[str, tuple[np.ndarray, list[int]]]  # tube id → (unit vector, view frames)
    failed: dict[str, str]  # tube id → why


class EmbedWorker:
    """The model and the job's source on one actor (or in this process): ``embed`` a Task."""

    def __init__(self, source: SourceConfig, model: str, cfg: EmbedConfig):
        import ray

        gpus = ray.get_gpu_ids() if ray.is_initialized() else []
        # auto: the CUDA provider only where Ray gave this actor a GPU (a CPU actor leaves the GPUs alone)
        device = "cpu" if cfg.device == "auto" and ray.is_initialized() and not gpus else cfg.device
        self.encoder = Encoder(model, cfg, device)
        self.source = source.open()
        self.root = source.root
        self.plans: dict[str, tuple[Any, dict[int, int]]] = {}
        self.tubes = 0

    def _plan(self, sequence: str):
        if sequence not in self.plans:
            survey = self.source.survey(sequence)
            self.plans[sequence] = (survey, {f: p for p, f in enumerate(survey.frames)})
        return self.plans[sequence]

    def _frames(self, sequence: str, frames: list[int]) -> dict[int, np.ndarray | InputError]:
        """Each frame's left image, or the error reading it (a missing frame fails its tubes only)."""
        plan, position = self._plan(sequence)
        out: dict[int, np.ndarray | InputError] = {}
        for f in sorted(set(frames)):
            if f not in position:
                out[f] = InputError(f"frame {f} of the catalogue is not in the source's sequence {sequence!r}",
                                    self.root, f)
                continue
            try:
                out[f] = self.source.read_frame(plan, position[f]).left
            except InputError as e:
                out[f] = e
        return out

    def embed(self, task: Task) -> EmbedResult:
        """A vector per tube of ``task``, or why it failed."""
        images = self._frames(task.sequence, [f for _, _, views in task.tubes for f, _ in views])
        crops, owner, failed = [], [], {}
        for tube_id, _, views in task.tubes:
            bad = next((images[f] for f, _ in views if isinstance(images[f], InputError)), None)
            if bad is not None:
                failed[tube_id] = str(bad)
                continue
            for f, bbox in views:
                crops.append(self.encoder.crop(images[f], bbox))
                owner.append((tube_id, f))
        vectors: dict[str, tuple[np.ndarray, list[int]]] = {}
        if crops:
            v = self.encoder.embed_crops(crops)
            by_tube: dict[str, list[int]] = {}
            for i, (tube_id, _) in enumerate(owner):
                by_tube.setdefault(tube_id, []).append(i)
            for tube_id, rows in by_tube.items():
                vectors[tube_id] = (tube_vector(v[rows]), [owner[i][1] for i in rows])
        self.tubes += len(vectors)
        return EmbedResult(vectors, failed)

    def where(self) -> dict[str, Any]:
        """This process, the GPUs Ray gave it, the providers its model runs on and the tubes it embedded."""
        import ray

        gpus = [str(g) for g in ray.get_gpu_ids()] if ray.is_initialized() else []
        return {"pid": os.getpid(), "gpu_ids": gpus, "providers": self.encoder.session.get_providers(),
                "tubes": self.tubes}


def actor_count(cfg: EmbedConfig, resources: dict[str, float]) -> tuple[int, float]:
    """(actors, GPUs each) on a cluster with ``resources`` (``embed.actors``)."""
    gpus = resources.get("GPU", 0.0)
    each = cfg.gpus_per_actor if gpus > 0 and cfg.actors != 0 else 0.0
    if cfg.actors > 0:
        if cfg.actors * each > gpus + 1e-9:
            raise MiningError(f"--actors {cfg.actors} with {each:g} GPU(s) each: the cluster has {gpus:g} GPUs")
        return max(cfg.actors, 1), each
    if gpus > 0 and each > 0:
        return max(1, int(gpus // each)), each
    return max(1, int(resources.get("CPU", 1.0))), 0.0


class Pool:
    """Tasks on Ray actors (``ray``) or on one worker in this process; results as they finish."""

    def __init__(self, source: SourceConfig, model: str, cfg: EmbedConfig, use_ray: bool):
        self.use_ray = use_ray
        if not use_ray:
            self.local = EmbedWorker(source, model, cfg)
            return
        import ray

        self.ray = ray
        n, gpus = actor_count(cfg, ray.cluster_resources())
        actor = ray.remote(max_restarts=ACTOR_RETRIES, max_task_retries=ACTOR_RETRIES, num_gpus=gpus)(EmbedWorker)
        self.actors = [actor.remote(source, model, cfg) for _ in range(n)]

    def run(self, tasks: list[Task]) -> Iterator[tuple[Task, EmbedResult | BaseException]]:
        if not self.use_ray:
            for t in tasks:
                try:
                    yield t, self.local.embed(t)
                except MiningError as e:  # the model failing on this task's crops: its tubes fail, as on Ray
                    yield t, e
            return
        todo, idle, busy = deque(tasks), deque(self.actors), {}
        while todo or busy:
            while todo and idle:
                a, t = idle.popleft(), todo.popleft()
                busy[a.embed.remote(t)] = (a, t)
            ready, _ = self.ray.wait(list(busy), num_returns=1)
            a, t = busy.pop(ready[0])
            idle.append(a)
            try:
                yield t, self.ray.get(ready[0])
            except Exception as e:  # noqa: BLE001 - a dead actor or the model failing: the task's tubes fail, named
                yield t, e

    def placement(self) -> list[dict[str, Any]]:
        if not self.use_ray:
            return [self.local.where()]
        return self.ray.get([a.where.remote() for a in self.actors])

    def shutdown(self) -> None:
        if self.use_ray:
            for a in self.actors:
                self.ray.kill(a)


@dataclass
class EmbedSummary:
    """What ``embed_catalogue`` did."""

    model: str
    model_sha256: str
    dim: int
    matched: int = 0  # tubes the predicate selected
    embedded: int = 0
    skipped: int = 0
    failed: dict[str, str] = field(default_factory=dict)  # tube id → why
    files: list[str] = field(default_factory=list)
    placement: list[dict[str, Any]] = field(default_factory=list)

    def lines(self) -> list[str]:
        out = [f"mine embed: {self.model} (sha256 {self.model_sha256[:12]}…, D = {self.dim}): {self.embedded} tubes "
               f"embedded, {self.skipped} already embedded by this model, {len(self.failed)} failed"]
        if any(a.get("gpu_ids") for a in self.placement):
            # sorted: the actors start in whatever order Ray schedules them
            gpus = ", ".join(sorted(("+".join(a["gpu_ids"]) or "none" for a in self.placement), key=lambda g: (len(g), g)))
            out[0] += f"; {len(self.placement)} actor(s) on GPUs [{gpus}] ({self.placement[0]['providers'][0]})"
        out += [f"  tube {t}: {why}" for t, why in sorted(self.failed.items())]
        return out


def _views(rows: list[dict], k: int, root: str) -> list[dict]:
    """The tube's best ``k`` views; an InputError for a malformed mask (the tube fails alone)."""
    a = areas([mask_rle(r, None, root) for r in rows])
    return best_views(rows, [float(x) for x in a], k)


def plan_tasks(store: Store, tubes: pa.Table, frames: pa.Table, encoder: Encoder, settings: str,
               summary: EmbedSummary, root: str) -> tuple[list[Task], dict[tuple[str, str], embeddings.EmbeddingMarker]]:
    """The tasks of the tubes not embedded yet (by this model, settings and views), and each sequence's marker."""
    cfg, per_tube = encoder.cfg, frames_by_tube(frames)
    tasks, markers = [], {}
    for (dataset, sequence), seq_tubes in by_sequence(tubes).items():
        marker, rows = embeddings.existing(store, dataset, sequence, encoder.path.name, encoder.sha256)
        markers[(dataset, sequence)] = marker
        done = {(t, s, v) for t, s, v in zip(rows.column("tube_id").to_pylist(), rows.column("settings").to_pylist(),
                                             rows.column("views_key").to_pylist())}
        todo = []
        for t in seq_tubes:
            try:
                views = _views(per_tube.get(t["tube_id"], []), cfg.views, root)
            except InputError as e:
                summary.failed[t["tube_id"]] = str(e)
                continue
            if not views:
                summary.failed[t["tube_id"]] = "no observed frame to embed"
                continue
            key = views_key(views)
            if (t["tube_id"], settings, key) in done:
                summary.skipped += 1
                continue
            todo.append((t["tube_id"], key, [(int(v["frame"]), [float(x) for x in v["bbox"]]) for v in views]))
        for s in range(0, len(todo), cfg.tubes_per_task):
            tasks.append(Task(dataset, sequence, todo[s:s + cfg.tubes_per_task]))
    return tasks, markers


def result_rows(task: Task, result: EmbedResult, encoder: Encoder, settings: str) -> pa.Table:
    """The rows of a task's vectors (``embeddings.EMBEDDING_SCHEMA``)."""
    now = datetime.now(timezone.utc).replace(tzinfo=None)  # UTC, plain (embeddings.EMBEDDING_SCHEMA)
    keys = {t: k for t, k, _ in task.tubes}
    rows = [{"tube_id": t, "dataset": task.dataset, "sequence": task.sequence, "model": encoder.path.name,
             "model_sha256": encoder.sha256, "preset": encoder.cfg.preset, "settings": settings, "views_key": keys[t],
             "n_views": len(frames), "view_frames": frames, "dim": int(v.shape[0]),
             "vector": v.astype(np.float32).tolist(), "embedded_at": now}
            for t, (v, frames) in result.vectors.items()]
    return pa.Table.from_pylist(rows, schema=embeddings.EMBEDDING_SCHEMA)


def embed_catalogue(out: str, model: str, where: str = "selected", cfg: EmbedConfig | None = None,
                    use_ray: bool = True, lock_wait: float = 0.0,
                    on_ray: Callable[[], None] | None = None, lock: bool = True) -> EmbedSummary:
    """Embed the tubes of catalogue ``out`` matching ``where`` (module docstring); ``on_ray`` starts
    Ray when there is work (``use_ray``) and none is running. ``lock`` False: the caller holds the
    writer lock (``mine submit``'s stage)."""
    cfg = cfg or EmbedConfig()
    job = read_job(out)  # the catalogue and job.json first: a wrong --out writes nothing
    if job is None:
        raise InputError("mine embed re-reads the frames through the source named in job.json, which is missing",
                         Path(out) / "job.json")
    encoder = Encoder(model, cfg, "cpu")  # checked here, before anything is written (the actors load their own)
    settings = settings_key(cfg, encoder.input, encoder.output)
    summary = EmbedSummary(encoder.path.name, encoder.sha256, encoder.dim)
    store = Store(out)
    con = connect(out)
    try:
        tubes, frames = selected_rows(con, where)
    finally:
        con.close()
    summary.matched = tubes.num_rows
    if not summary.matched:  # nothing to do: not even the lock is taken
        return summary
    with OutputLock(store, lock_wait) if lock else nullcontext():
        tasks, markers = plan_tasks(store, tubes, frames, encoder, settings, summary, job.source.root)
        for marker in markers.values():
            embeddings.sweep(store, marker)
        if not tasks:
            return summary
        if use_ray and on_ray is not None:
            on_ray()
        pool = Pool(job.source, str(encoder.path), cfg, use_ray)
        try:
            for task, result in pool.run(tasks):
                if isinstance(result, BaseException):
                    last = (str(result).strip().splitlines() or [type(result).__name__])[-1]  # Ray's text ends with the cause
                    summary.failed.update({t: f"its task failed: {last}" for t, _, _ in task.tubes})
                    continue
                summary.failed.update(result.failed)
                if result.vectors:
                    summary.files.append(embeddings.append(store, markers[(task.dataset, task.sequence)],
                                                           result_rows(task, result, encoder, settings)))
                    summary.embedded += len(result.vectors)
            summary.placement = pool.placement()
        finally:
            pool.shutdown()
    return summary


def embed_after_job(cfg: JobConfig, out: str) -> EmbedSummary:
    """``mine submit``'s embedding stage (``embed.model_path`` set), under the job's lock: on the
    job's Ray where it started one (its workers are gone by then), else in this process."""
    ray = sys.modules.get("ray")
    on_ray = ray is not None and ray.is_initialized()
    return embed_catalogue(out, cfg.embed.model_path, cfg.embed.where, cfg.embed, use_ray=on_ray, lock=False)


def print_summary(summary: EmbedSummary) -> int:
    """The summary on standard output (failures on standard error); the exit status."""
    first, *rest = summary.lines()
    print(first)
    for line in rest:
        print(line, file=sys.stderr)
    return FAILED if summary.failed else 0
