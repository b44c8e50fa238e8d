"""The records a mining job writes under ``--out`` (``layout.py`` says where), as types.

* ``JobRecord``: the job a catalogue belongs to (``job.json``): the resolved config, its
  ``params_hash``, the job's identity (``identity.py``: config, source root, recording
  fingerprint, sequences, frame ranges), the run id and the windows of the job; a
  resubmission of another identity is refused (``identity.check_resubmit``);
* ``ManifestRow``: a window's row of the ``windows`` table (``manifest/…/<window>.parquet``),
  and a sequence's failed-stitch row (``manifest/…/stitch.parquet``, window ``STITCH_ROW``);
* ``WindowFiles``: the size and sha256 of a window's parts (``manifest/…/<window>.files.json``),
  written after the parts and before the window's row says done;
* ``SequenceMarker``: a finalized sequence (``catalog/_sequences/dataset=D/sequence=S.json``):
  the windows its catalogue holds, the context of each, and the size and sha256 of each of
  its compacted files; written last, after the files it vouches for.

Every ``load`` is tolerant: a record that is not there is None, and one that is there but does
not read as its record (unreadable, truncated, not JSON, of another shape, another window's or
sequence's) is an ``Unreadable`` naming the file and why. It never raises for damage: a damaged
record proves nothing, and what reads it (resume, ``mine status``, the query views) decides what
that means. ``job.json`` alone is the exception, read by the same helpers: without it a
catalogue's job is unknown and nothing can go on, so ``JobRecord.load`` raises the
``Unreadable`` as an ``UnreadableRecord`` (an InputError naming the file and why); the catalogue
beside it is kept, and ``mine submit --new-run`` moves both aside (the message says so). A record of a newer catalogue schema than this code reads is not damage (recomputing
it would overwrite a newer version's work): ``load`` raises ``versions.SchemaVersionError``. ``save`` writes through the ``Store`` (atomic, never through a link: ``safe_files.py``).

Each record has the predicate resume (``pipeline/resume.py``), ``mine status`` and the
integrity checks (``integrity.py``, which check the files a record lists against what is
there) share: ``ManifestRow.says_done``, ``WindowFiles.missing``, ``SequenceMarker.of_job``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import datetime
from typing import TYPE_CHECKING, Any

from mining.catalog.identity import legacy_identity
from mining.catalog.layout import (CATALOG, JOB, MARKERS, PART_TABLES, REPLACED, STITCH_ROW, TABLE_DIRS, catalog_layout,
                                   done_path, files_path, manifest_path, part_path, stitch_path)
from mining.catalog.rows import to_table
from mining.catalog.schema import SCHEMA_VERSION
from mining.catalog.versions import RECORD_KEY, check_columns, check_record_version
from mining.config import JobConfig, job_config_from_record
from mining.errors import ConfigError, InputError
from mining.files import check_regular
from mining.names import NAME_RULE, check_name, name_problem
from mining.types import Window

if TYPE_CHECKING:
    from mining.catalog.store import Store

# A file's record in WindowFiles and SequenceMarker: {"size": bytes, "sha256": hex digest}
# (integrity.digest), by path relative to --out.
FileDigests = Mapping[str, Mapping[str, Any]]


@dataclass(frozen=True)
class Unreadable:
    """A record that is there but does not read as one: where (relative to ``--out``) and why."""

    path: str
    reason: str


# -- reading JSON and checking its shape ------------------------------------------------------

_JSON_KINDS = {dict: "an object", list: "an array", str: "a string", bool: "a boolean", int: "a number",
               float: "a number", type(None): "null"}


def _kind(value: object) -> str:
    return _JSON_KINDS.get(type(value), type(value).__name__)


def _read_json(store: Store, rel: str) -> object | Unreadable | None:
    """The parsed JSON of ``rel``; None when there is no such file."""
    try:
        with store.open_stream(rel) as f:
            raw = f.read()
    except FileNotFoundError:
        return None
    except OSError as e:
        return Unreadable(rel, f"cannot be read ({e})")
    except InputError as e:  # a FIFO or device at the record's name
        return Unreadable(rel, e.reason)
    try:
        return json.loads(raw)
    except (ValueError, RecursionError) as e:  # not UTF-8, not JSON, nested past the parser: truncated or planted
        return Unreadable(rel, f"not valid JSON ({e})")


def check_job_names(store: Store) -> None:
    """Refuse a catalogue, whole and in one line, that holds a dataset or sequence name the
    rule no longer admits (``mining/names.py``): an older rule allowed ``_x``, whose folders
    pandas and pyarrow skip by default, so a plain read of it silently misses rows. The names
    are those of job.json's windows, or where it lists none, of the compacted tables' folders."""
    found: list[tuple[str, object, str]] = []  # (kind, name, where)
    if store.local:
        check_regular(store.full(JOB))  # a FIFO there: said at once, never read
    d = _read_json(store, JOB)
    if isinstance(d, dict) and isinstance(d.get("windows"), list):  # a record of another shape: its reader says so
        for w in d["windows"]:
            if isinstance(w, dict):
                found += [(k, w.get(k), JOB) for k in ("dataset", "sequence") if isinstance(w.get(k), str)]
    if not found:  # no job's windows (store.write_sequence alone): its folders name its sequences
        for table in TABLE_DIRS:
            for rel in store.list(f"{CATALOG}/{table}"):
                p = rel.split("/")
                if catalog_layout(rel) == "plain":  # catalog/<table>/<dataset>/<sequence>/<file>: hive folders are seen
                    found += [("dataset", p[2], rel), ("sequence", p[3], rel)]
    for kind, name, where in found:
        if (problem := name_problem(name)) is not None:
            raise InputError(f"this catalogue holds the {kind} name {name!r} ({problem}), which an older name rule "
                             f"allowed; names are now {NAME_RULE}, so that every Parquet reader sees its folders. "
                             f"Mine it again: {FRESH_START}", store.full(where))


class _Shape(Exception):
    """What makes parsed JSON not the record it should be (the key and what it holds)."""


def _key(d: dict, key: str, check, expected: str, required: bool = False) -> Any:
    if key not in d:
        if required:
            raise _Shape(f"key {key!r} is missing")
        return None
    if not check(d[key]):
        raise _Shape(f"key {key!r} holds {_kind(d[key])}, expected {expected}")
    return d[key]


def _is_int(v: object) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_digests(v: object) -> bool:
    return isinstance(v, dict) and all(
        isinstance(rel, str) and isinstance(want, dict) and _is_int(want.get("size"))
        and isinstance(want.get("sha256"), str) for rel, want in v.items())


def _is_names(v: object) -> bool:
    return isinstance(v, list) and all(isinstance(n, str) for n in v)


def _is_contexts(v: object) -> bool:
    return isinstance(v, dict) and all(isinstance(n, str) and isinstance(c, list) and len(c) == 2
                                       and all(_is_int(x) for x in c) for n, c in v.items())


def _is_str(v: object) -> bool:
    return isinstance(v, str)


def _object(d: object) -> dict:
    if not isinstance(d, dict):
        raise _Shape(f"expected a JSON object, got {_kind(d)}")
    return d


# -- the job record ---------------------------------------------------------------------------

# What a refusal over a lost or unreadable job.json offers: never "move job.json away", which
# leaves the catalogue without its record (the next submit would then mine over it).
FRESH_START = (f"mine submit --new-run moves the old catalogue (job.json included) to {REPLACED}/ inside --out "
               "and starts a new one; or use another --out")


class UnreadableRecord(InputError):
    """OUT/job.json exists but is not a job record."""


def _is_span(v: object) -> bool:
    """[start, end] frame positions, 0 ≤ start < end."""
    return isinstance(v, list) and len(v) == 2 and all(_is_int(x) and x >= 0 for x in v) and v[0] < v[1]


def _is_reasons(v: object) -> bool:
    return isinstance(v, dict) and all(isinstance(r, str) for r in v.values())


def _is_object(v: object) -> bool:
    return isinstance(v, dict)


def _is_list(v: object) -> bool:
    return isinstance(v, list)


def _job_window(d: object) -> Window:
    d = _object(d)
    return Window(_key(d, "dataset", _is_str, "a name", required=True),
                  _key(d, "sequence", _is_str, "a name", required=True),
                  tuple(_key(d, "core", _is_span, "[start, end] frame positions", required=True)),
                  tuple(_key(d, "context", _is_span, "[start, end] frame positions", required=True)))


def _window_entry(w: Window) -> dict:
    return {"dataset": w.dataset, "sequence": w.sequence, "window": w.name, "core": list(w.core),
            "context": list(w.context)}


@dataclass
class JobRecord:
    """``job.json``: the job a catalogue belongs to."""

    run_id: str
    params_hash: str
    config: dict  # the resolved JobConfig, as JobConfig.to_dict()
    windows: list[Window]  # the job's windows, in planning order
    identity: dict[str, Any] = field(default_factory=dict)  # identity.job_identity; legacy_identity for old records
    unplanned: dict[str, str] = field(default_factory=dict)  # sequence asked for → why it could not be planned (last submit)

    @classmethod
    def load(cls, store: Store) -> JobRecord | None:
        """The record in ``store``, or None when it has none; ``UnreadableRecord`` (naming the
        file, why, and ``FRESH_START``) when job.json is there but does not read as one."""
        if not store.anything_at(JOB):  # a FIFO there is no job.json, but not "no job" either
            return None
        d = _read_json(store, JOB)
        if d is None:  # removed since it was seen
            return None
        if isinstance(d, Unreadable):
            raise UnreadableRecord(f"job.json is not a job record: {d.reason}; {FRESH_START}", store.full(JOB))
        check_record_version(d, store.full(JOB))  # a newer version's record is refused, not set aside
        try:
            d = _object(d)
            run_id = _key(d, "run_id", _is_str, "a run id", required=True)
            params_hash = _key(d, "params_hash", _is_str, "a params hash", required=True)
            config = _key(d, "config", _is_object, "a job config", required=True)
            windows = []
            for i, w in enumerate(_key(d, "windows", _is_list, "a list of windows", required=True)):
                try:
                    windows.append(_job_window(w))
                except _Shape as e:
                    raise _Shape(f"windows[{i}]: {e}") from None
            unplanned = _key(d, "unplanned", _is_reasons, "{sequence: reason}")
            identity = _key(d, "identity", _is_object, "{key: value}")
        except _Shape as e:
            raise UnreadableRecord(f"job.json is not a job record: {e}; {FRESH_START}", store.full(JOB)) from None
        try:
            for w in windows:
                check_name(w.dataset, "dataset", "job.json", store.full(JOB))
                check_name(w.sequence, "sequence", "job.json", store.full(JOB))
        except InputError as e:
            raise UnreadableRecord(f"{e.reason}; {FRESH_START}", store.full(JOB)) from None
        return cls(run_id, params_hash, config, windows, legacy_identity(config) if identity is None else identity,
                   unplanned or {})

    def job_config(self, where: str = JOB) -> JobConfig:
        """The recorded config as a typed ``JobConfig`` (``config.job_config_from_record``: keys of
        older versions renamed); ``UnreadableRecord`` naming the key when it does not fit."""
        try:
            return job_config_from_record(self.config, where)
        except ConfigError as e:
            raise UnreadableRecord(f"job.json's config does not read as a job config: {e}", where) from None

    def check(self, params_hash: str, out: str) -> None:
        """Refuse a job of other params than the catalogue at ``out`` was made with (the
        identity names the keys: ``identity.check_resubmit``; this is the last guard)."""
        if self.params_hash != params_hash:
            raise ConfigError(f"{out} holds a catalogue made with params {self.params_hash}; this job has "
                              f"{params_hash}. Use another --out, or the same config to resume.")

    def save(self, store: Store) -> None:
        record = {"run_id": self.run_id, "params_hash": self.params_hash, "identity": self.identity,
                  "config": self.config, "windows": [_window_entry(w) for w in self.windows]}
        if self.unplanned:
            record["unplanned"] = self.unplanned
        record[RECORD_KEY] = SCHEMA_VERSION
        store.write_bytes(JOB, json.dumps(record, indent=1, default=str).encode())


# -- the window's files record ----------------------------------------------------------------

@dataclass(frozen=True)
class WindowFiles:
    """``manifest/…/<window>.files.json``: the size and sha256 of each of a window's parts."""

    window: Window
    files: FileDigests  # part path → {"size", "sha256"}

    @property
    def path(self) -> str:
        return files_path(self.window.dataset, self.window.sequence, self.window.name)

    @classmethod
    def load(cls, store: Store, window: Window) -> WindowFiles | Unreadable | None:
        """The record of ``window``; None when it has none, ``Unreadable`` when it is not one."""
        rel = files_path(window.dataset, window.sequence, window.name)
        d = _read_json(store, rel)
        if d is None or isinstance(d, Unreadable):
            return d
        check_record_version(d, store.full(rel))
        try:
            d = _object(d)
            name = _key(d, "window", _is_str, "a window name")
            if name is not None and name != window.name:
                raise _Shape(f"it records window {name!r}, not {window.name!r}")
            files = _key(d, "files", _is_digests, "{path: {size, sha256}}", required=True)
        except _Shape as e:
            return Unreadable(rel, f"not a window's files record: {e}")
        return cls(window, files)

    def save(self, store: Store) -> None:
        record = {"window": self.window.name, "files": dict(self.files), RECORD_KEY: SCHEMA_VERSION}
        store.write_bytes(self.path, json.dumps(record, indent=1).encode())

    def missing(self) -> list[str]:
        """The window's parts this record does not list (sorted): each a part the window's
        manifest row cannot vouch for."""
        w = self.window
        want = {part_path(t, w.dataset, w.sequence, w.name) for t in PART_TABLES}
        return sorted(want - self.files.keys())


# -- the sequence marker ----------------------------------------------------------------------

@dataclass(frozen=True)
class SequenceMarker:
    """``catalog/_sequences/dataset=D/sequence=S.json``: a finalized sequence.

    ``dataset`` and ``sequence`` are those of the marker's path (a marker recording others is
    another sequence's: ``Unreadable``); the optional fields are absent from markers older
    than them (before integrity records: no ``files``, no ``contexts``) and from markers
    written by ``store.write_sequence``'s callers outside a job (``bench/catalog.py``)."""

    dataset: str
    sequence: str
    windows: tuple[str, ...]  # the windows the sequence's catalogue holds
    files: FileDigests | None = None  # compacted file → {"size", "sha256"}; None: before integrity records
    params_hash: str | None = None
    run_id: str | None = None
    contexts: Mapping[str, tuple[int, int]] | None = None  # window → its context when stitched
    planned: int | None = None  # windows the job planned for the sequence
    finished: str | None = None  # ISO time of the stitch

    @property
    def path(self) -> str:
        return done_path(self.dataset, self.sequence)

    @classmethod
    def load(cls, store: Store, dataset: str, sequence: str) -> SequenceMarker | Unreadable | None:
        """The marker of one sequence; None when it has none, ``Unreadable`` when it is not one."""
        return cls._read(store, done_path(dataset, sequence), dataset, sequence)

    @classmethod
    def load_all(cls, store: Store) -> list[SequenceMarker | Unreadable]:
        """Every marker under ``catalog/_sequences`` (a file elsewhere in that folder, or of a
        name that is not one, is ``Unreadable``: it vouches for nothing)."""
        out: list[SequenceMarker | Unreadable] = []
        for rel in store.list(MARKERS, ".json"):
            names = rel[len(MARKERS) + 1: -len(".json")].split("/")
            if len(names) != 2 or not names[0].startswith("dataset=") or not names[1].startswith("sequence="):
                out.append(Unreadable(rel, "not where a sequence marker lies (dataset=D/sequence=S.json)"))
                continue
            dataset, sequence = names[0][len("dataset="):], names[1][len("sequence="):]
            try:
                if done_path(dataset, sequence) != rel:
                    raise InputError("not where a sequence marker lies (dataset=D/sequence=S.json)")
            except InputError as e:  # a name that is not one
                out.append(Unreadable(rel, e.reason))
                continue
            marker = cls._read(store, rel, dataset, sequence)
            if marker is not None:  # removed since the listing
                out.append(marker)
        return out

    @classmethod
    def _read(cls, store: Store, rel: str, dataset: str, sequence: str) -> SequenceMarker | Unreadable | None:
        d = _read_json(store, rel)
        if d is None or isinstance(d, Unreadable):
            return d
        check_record_version(d, store.full(rel))
        try:
            d = _object(d)
            for key, own in (("dataset", dataset), ("sequence", sequence)):
                got = _key(d, key, _is_str, f"a {key} name")
                if got is not None and got != own:
                    raise _Shape(f"it records {key} {got!r}, not {own!r} (another sequence's marker)")
            windows = _key(d, "windows", _is_names, "a list of window names", required=True)
            contexts = _key(d, "contexts", _is_contexts, "{window: [start, end]}")
            marker = cls(dataset, sequence, tuple(windows),
                         files=_key(d, "files", _is_digests, "{path: {size, sha256}}"),
                         params_hash=_key(d, "params_hash", _is_str, "a params hash"),
                         run_id=_key(d, "run_id", _is_str, "a run id"),
                         contexts=None if contexts is None else {n: tuple(c) for n, c in contexts.items()},
                         planned=_key(d, "planned", _is_int, "a count of windows"),
                         finished=_key(d, "finished", _is_str, "a time"))
        except _Shape as e:
            return Unreadable(rel, f"not a sequence marker: {e}")
        return marker

    def to_dict(self) -> dict[str, Any]:
        """The marker as JSON (what it does not record left out, as older writers left it; the schema
        version last)."""
        d = {"params_hash": self.params_hash, "run_id": self.run_id, "dataset": self.dataset,
             "sequence": self.sequence, "windows": list(self.windows),
             "contexts": None if self.contexts is None else {n: list(c) for n, c in self.contexts.items()},
             "planned": self.planned, "finished": self.finished,
             "files": None if self.files is None else dict(self.files), RECORD_KEY: SCHEMA_VERSION}
        return {k: v for k, v in d.items() if v is not None}

    def save(self, store: Store) -> None:
        """Write the marker: only after the files it vouches for."""
        store.write_bytes(self.path, json.dumps(self.to_dict(), indent=1).encode())

    def of_job(self, params_hash: str, contexts: Mapping[str, tuple[int, int]] | None = None) -> bool:
        """Whether this stitch was made with ``params_hash`` and, given the job's planned
        ``contexts`` (window → context), each window it holds was tracked with the context
        planned now (an extension widens the last window's)."""
        return self.params_hash == params_hash and (contexts is None or all(
            contexts.get(n) == tuple(c) for n, c in (self.contexts or {}).items()))


# -- the manifest row -------------------------------------------------------------------------

_ROW_REQUIRED = {"run_id": str, "window": str, "core_start": int, "core_end": int, "context_start": int,
                 "context_end": int, "status": str, "attempts": int, "params_hash": str}


def row_path(dataset: str, sequence: str, window: str) -> str:
    """Where the manifest row of ``window`` lies (``STITCH_ROW``: the sequence's failed stitch)."""
    return stitch_path(dataset, sequence) if window == STITCH_ROW else manifest_path(dataset, sequence, window)


@dataclass(frozen=True)
class ManifestRow:
    """One row of the ``windows`` table: a window's result (or a sequence's failed stitch,
    window ``STITCH_ROW``, its planned range as core and context)."""

    run_id: str
    window: str
    core: tuple[int, int]
    context: tuple[int, int]
    status: str  # done | failed
    attempts: int
    params_hash: str
    started: datetime | None = None
    finished: datetime | None = None
    seconds_observe: float | None = None  # None: its observation came from the cache
    seconds_tubes: float | None = None
    n_pieces: int | None = None
    context_complete: bool | None = None  # every neighbour's frames were there when it was tracked
    error: str = ""  # why it failed: the step, the exception type, the message (failures.describe)

    @classmethod
    def load(cls, store: Store, dataset: str, sequence: str, window: str) -> ManifestRow | Unreadable | None:
        """The row of ``window`` (a name, or ``STITCH_ROW``); None when it has none,
        ``Unreadable`` when the file is not such a row."""
        rel = row_path(dataset, sequence, window)
        if not store.exists(rel):
            return None
        try:
            rows = store.read_table(rel).to_pylist()
        except InputError as e:
            return Unreadable(rel, e.reason)
        check_columns(list(rows[0]) if rows else [], "windows", store.full(rel))  # a newer version's row
        if not rows:
            return Unreadable(rel, "holds no row")
        r = rows[0]
        for key, kind in _ROW_REQUIRED.items():
            if key not in r:
                return Unreadable(rel, f"not a manifest row: column {key!r} is missing")
            if not isinstance(r[key], kind) or isinstance(r[key], bool):
                return Unreadable(rel, f"not a manifest row: column {key!r} holds {r[key]!r}")
        return cls(r["run_id"], r["window"], (r["core_start"], r["core_end"]), (r["context_start"], r["context_end"]),
                   r["status"], r["attempts"], r["params_hash"], r.get("started"), r.get("finished"),
                   r.get("seconds_observe"), r.get("seconds_tubes"), r.get("n_pieces"), r.get("context_complete"),
                   r.get("error") or "")

    def to_row(self) -> dict[str, Any]:
        """The row as the ``windows`` table's columns (without the partition columns)."""
        return {"run_id": self.run_id, "window": self.window, "core_start": self.core[0], "core_end": self.core[1],
                "context_start": self.context[0], "context_end": self.context[1], "status": self.status,
                "attempts": self.attempts, "started": self.started, "finished": self.finished,
                "seconds_observe": self.seconds_observe, "seconds_tubes": self.seconds_tubes,
                "n_pieces": self.n_pieces, "context_complete": self.context_complete, "error": self.error or None,
                "params_hash": self.params_hash}

    def save(self, store: Store, dataset: str, sequence: str) -> None:
        store.write_table(row_path(dataset, sequence, self.window), to_table([self.to_row()], "windows"))

    def says_done(self, params_hash: str, window: Window | None = None) -> bool:
        """Whether the row says its window is done with ``params_hash`` (and, given ``window``,
        for that window's core and context as planned now)."""
        return (self.status == "done" and self.params_hash == params_hash
                and (window is None or (self.core, self.context) == (tuple(window.core), tuple(window.context))))
