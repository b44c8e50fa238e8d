"""Where everything of a catalogue lives under ``--out``, and the job record ``job.json``.

One owner for every relative path a mining job reads or writes (``schemas/README.md``
draws the same tree); ``store.py`` does the I/O on them::

    job.json                                                  the job record (JobRecord)
    .mine.lock                                                the writer's lock (lock.py): who holds it
    catalog/<table>/D/S/part-<k>.parquet                      compacted tables (tubes, tube_frames, frames, windows),
                                                              dataset and sequence inside every file (schema v3)
    catalog/_sequences/dataset=D/sequence=S.json              a finalized sequence: which windows its catalogue holds,
                                                              and the size and sha256 of each of its compacted files
                                                              (SequenceMarker)
    manifest/dataset=D/sequence=S/<window>.parquet            the windows table, one row per window (ManifestRow)
    manifest/dataset=D/sequence=S/<window>.files.json         size and sha256 of the window's parts (WindowFiles)
    manifest/dataset=D/sequence=S/stitch.parquet              a sequence whose stitch failed (its row, until one succeeds)
    _running/dataset=D/sequence=S/<window>.json               a window a driver has started and not finished
    _parts/<table>/dataset=D/sequence=S/<window>.part         a window's parts before stitching (Parquet)
    _cache/obs/dataset=D/sequence=S/<window>.npz.zst          a window's observations, until no track needs them
    labels/part-<UTC>-<hex>.parquet                           what people decided about tubes (labels.py): one file
    labels/compact-<UTC>-<hex>.parquet                        per write, merged by `mine label --compact`

The compacted tables are what people read with their own tools, so their folders have plain
names and their files hold ``dataset`` / ``sequence`` as strings: a default read of
``catalog/tubes`` in pandas, pyarrow, polars or DuckDB gives ``sequence`` "0005", never 5
(hive names ``sequence=0005`` are read as integers unless the reader is told otherwise, and
a file column beside a hive name of another inferred type breaks pandas' read). Before
schema v3 they lay under ``catalog/<table>/dataset=D/sequence=S/`` without those columns
(``HIVE_CATALOGUE``): such a catalogue is still read (``catalog_layout``, ``views.py``), and
resuming or extending it is refused (``check_resumable``). The working folders (manifest,
parts, running markers, caches, sequence markers) keep their hive names: only this code reads
them, and a catalogue keeps resuming across this change where nothing was compacted yet.

The records among them are types: ``JobRecord`` here, the others in ``records.py``.
Every path is built from names checked by ``mining/names.py`` (dataset, sequence, window),
so no name can leave ``--out`` or make two tables share a file; ``job.json``'s names are
checked when it is read.

``job.json`` records the resolved config, its ``params_hash``, the job's identity
(``identity.py``: config, source root, recording fingerprint, sequences, frame ranges),
the run id and the windows of the job; a resubmission of another identity is refused
(``identity.check_resubmit``). ``REPLACED`` holds catalogues a ``--new-run`` moved aside.
A job.json that does not read as a job record is an ``UnreadableRecord``: the catalogue
beside it is kept, and ``mine submit --new-run`` moves both aside (the message says so).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from mining.catalog.identity import legacy_identity
from mining.catalog.schema import SCHEMA_VERSION
from mining.catalog.versions import RECORD_KEY, check_record_version
from mining.errors import ConfigError, InputError
from mining.names import check_name
from mining.types import Window

if TYPE_CHECKING:
    from mining.catalog.store import Store

JOB = "job.json"
CATALOG = "catalog"
MANIFEST = "manifest"
MARKERS = f"{CATALOG}/_sequences"  # one finished marker per finalized sequence (records.SequenceMarker)
# Working files (per-window parts, caches, running markers) sit under "_"-prefixed folders,
# which Hive-style readers (DuckDB, Spark, pyarrow datasets) skip: a glob over the output
# folder finds the catalogue and the manifest, never a half-stitched piece.
PARTS = "_parts"
PART_SUFFIX = ".part"  # Parquet inside, but not "*.parquet": a DuckDB glob over the output folder (which does not skip "_" folders) never picks a part up
CACHE = "_cache/obs"
LOCK = ".mine.lock"  # a dot name: every reader skips it (store.is_temporary)
REPLACED = "_replaced"  # catalogues moved aside by --new-run, one folder each
# What a job writes under --out (a --new-run moves exactly these aside).
JOB_ENTRIES = (JOB, CATALOG, MANIFEST, PARTS, "_cache")
# People's labels of the tubes (labels.py): no job writes or resumes them; a --new-run moves them
# aside with the catalogue whose tube ids they name.
LABELS = "labels"
RUNNING = "_running"
STITCH_ROW = "stitch"  # the ``window`` of a sequence's failed-stitch row (no window is named so: windows are S-start-end)
CACHE_SUFFIX = ".npz.zst"  # the observation cache's format: mining/pipeline/cache.py
LEGACY_CACHE_SUFFIX = ".pkl"  # caches before issue 11 (pickle): never read, removed with their window's
PART_TABLES = ("tubes", "tube_frames", "frames")  # what a tracked window writes, and a sequence stitches
# The folder of each table a query reads: the compacted tables, and the manifest as ``windows``.
TABLE_DIRS = {"tubes": f"{CATALOG}/tubes", "tube_frames": f"{CATALOG}/tube_frames", "frames": f"{CATALOG}/frames",
              "windows": MANIFEST}


CATALOGUE = f"{CATALOG}/<table>/<dataset>/<sequence>/part-<k>.parquet"  # the compacted tables (schema v3)
HIVE_CATALOGUE = f"{CATALOG}/<table>/dataset=<dataset>/sequence=<sequence>/part-<k>.parquet"  # before v3

# What a refusal over a lost or unreadable job.json offers: never "move job.json away", which
# leaves the catalogue without its record (the next submit would then mine over it).
FRESH_START = (f"mine submit --new-run moves the old catalogue (job.json included) to {REPLACED}/ inside --out "
               "and starts a new one; or use another --out")


class UnreadableRecord(InputError):
    """OUT/job.json exists but is not a job record."""


def _where(dataset: str, sequence: str, window: str | None = None) -> str:
    """``dataset=D/sequence=S`` (and ``/<window>``) from checked names: the working folders."""
    origin = "a path under --out"
    where = f"dataset={check_name(dataset, 'dataset', origin)}/sequence={check_name(sequence, 'sequence', origin)}"
    return where if window is None else f"{where}/{check_name(window, 'window', origin)}"


def part_path(table: str, dataset: str, sequence: str, window: str) -> str:
    """A window's part of ``table`` (one of ``PART_TABLES``)."""
    if table not in PART_TABLES:
        raise ValueError(f"no part table {table!r}")
    return f"{PARTS}/{table}/{_where(dataset, sequence, window)}{PART_SUFFIX}"


def manifest_path(dataset: str, sequence: str, window: str) -> str:
    """A window's manifest row (its row of the ``windows`` table)."""
    return f"{MANIFEST}/{_where(dataset, sequence, window)}.parquet"


def files_path(dataset: str, sequence: str, window: str) -> str:
    """Size and sha256 of a window's parts, written before its manifest row says done."""
    return f"{MANIFEST}/{_where(dataset, sequence, window)}.files.json"


def stitch_path(dataset: str, sequence: str) -> str:
    """The manifest row of a sequence whose stitch (finalize) failed; removed when one succeeds."""
    return f"{MANIFEST}/{_where(dataset, sequence)}/{STITCH_ROW}.parquet"


def observed_path(dataset: str, sequence: str, window: str) -> str:
    """How many core frames a window's observe step has done so far (its worker writes it as it
    goes, for the driver's progress bar; removed when the step ends)."""
    return f"{RUNNING}/{_where(dataset, sequence, window)}.frames"


def running_path(dataset: str, sequence: str, window: str) -> str:
    """The marker of a window a driver has started (its observe or track step) and not finished."""
    return f"{RUNNING}/{_where(dataset, sequence, window)}.json"


def catalog_dir(table: str, dataset: str, sequence: str, hive: bool = False) -> str:
    """The folder of one sequence's compacted files of ``table``: ``catalog/<table>/D/S``
    (``hive``: where a catalogue before schema v3 kept them, ``catalog/<table>/dataset=D/sequence=S``)."""
    if table not in TABLE_DIRS:
        raise ValueError(f"no catalogue table {table!r}")
    if hive:
        return f"{CATALOG}/{table}/{_where(dataset, sequence)}"
    origin = "a path under --out"
    return f"{CATALOG}/{table}/{check_name(dataset, 'dataset', origin)}/{check_name(sequence, 'sequence', origin)}"


def catalog_file(table: str, dataset: str, sequence: str, k: int) -> str:
    """The ``k``-th compacted file of one sequence's ``table``."""
    return f"{catalog_dir(table, dataset, sequence)}/part-{int(k)}.parquet"


def catalog_layout(rel: str) -> str | None:
    """Which layout the compacted file ``rel`` lies in: ``"plain"`` (``catalog/<table>/D/S/<file>``,
    schema v3), ``"hive"`` (``catalog/<table>/dataset=D/sequence=S/<file>``, before v3), or None
    (not a table's file at a table file's depth). Checked names hold no ``=``, so the two never meet."""
    p = rel.split("/")
    if len(p) != 5 or p[0] != CATALOG or p[1] not in TABLE_DIRS:
        return None
    if p[2].startswith("dataset=") and p[3].startswith("sequence="):
        return "hive"
    return None if "=" in p[2] + p[3] else "plain"


def hive_catalogue(store: Store) -> list[str]:
    """The compacted files of ``store`` in the layout before schema v3 (``HIVE_CATALOGUE``), sorted."""
    return [r for t in TABLE_DIRS for r in store.list(f"{CATALOG}/{t}") if catalog_layout(r) == "hive"]


def check_resumable(store: Store) -> None:
    """Refuse to resume or extend a catalogue whose compacted tables lie in the layout before
    schema v3: stitching its sequences again would leave two layouts side by side, and the
    markers of the old files vouch for paths this code no longer writes. Naming the fix."""
    if old := hive_catalogue(store):
        raise InputError(
            f"{store.uri} holds a catalogue of schema v2 or older, whose tables lie in hive folders "
            f"({HIVE_CATALOGUE}); this version writes {CATALOGUE} (dataset and sequence inside the files, so "
            "every Parquet reader gives them as strings) and can neither resume nor extend it. "
            "`mine query`, `mine view` and `mine export` still read it as it is. To mine it again: "
            f"mine submit --new-run moves it (job.json included) to {REPLACED}/ inside --out and starts a new one; "
            "or use another --out, or the version of the code that made it", store.full(old[0]))


def done_path(dataset: str, sequence: str) -> str:
    """The marker a finalized sequence leaves: which windows its catalogue holds."""
    return f"{MARKERS}/{_where(dataset, sequence)}.json"


def cache_path(w: Window, suffix: str = CACHE_SUFFIX) -> str:
    """A window's observation cache (its core frames' observations; ``pipeline/cache.py``)."""
    return f"{CACHE}/{_where(w.dataset, w.sequence, w.name)}{suffix}"


def _window_entry(w: Window) -> dict:
    return {"dataset": w.dataset, "sequence": w.sequence, "window": w.name, "core": list(w.core),
            "context": list(w.context)}


def _record_problem(d: object) -> str | None:
    """What makes parsed JSON not a job record (the key and what it holds), or None."""
    if not isinstance(d, dict):
        return f"expected a JSON object, got {type(d).__name__}"
    for key, kind in (("run_id", str), ("params_hash", str), ("config", dict), ("windows", list)):
        if key not in d:
            return f"key {key!r} is missing"
        if not isinstance(d[key], kind):
            return f"key {key!r} holds {type(d[key]).__name__}, expected {kind.__name__}"
    for i, w in enumerate(d["windows"]):
        if not isinstance(w, dict):
            return f"windows[{i}] holds {type(w).__name__}, expected an object"
        for key in ("dataset", "sequence"):
            if not isinstance(w.get(key), str):
                return f"windows[{i}].{key} is {w.get(key)!r}, expected a name"
        for key in ("core", "context"):
            v = w.get(key)
            if not (isinstance(v, list) and len(v) == 2 and all(isinstance(x, int) and not isinstance(x, bool)
                                                                  and x >= 0 for x in v) and v[0] < v[1]):
                return f"windows[{i}].{key} is {v!r}, expected [start, end] frame positions"
    unplanned = d.get("unplanned", {})
    if not (isinstance(unplanned, dict) and all(isinstance(v, str) for v in unplanned.values())):
        return "key 'unplanned' is not a mapping of sequence to reason"
    return None


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
        """The record in ``store``, or None when it has none."""
        if not store.exists(JOB):
            return None
        try:
            d = json.loads(store.read_bytes(JOB))
        except ValueError as e:  # not UTF-8, not JSON (a truncated or overwritten file)
            raise UnreadableRecord(f"job.json is not a job record: not valid JSON ({e}); {FRESH_START}",
                                   store.full(JOB)) from None
        check_record_version(d, store.full(JOB))  # a newer version's record is refused, not set aside
        if (problem := _record_problem(d)) is not None:
            raise UnreadableRecord(f"job.json is not a job record: {problem}; {FRESH_START}", store.full(JOB))
        identity = d["identity"] if "identity" in d else legacy_identity(d["config"])
        if not isinstance(identity, dict):
            raise UnreadableRecord(f"job.json is not a job record: key 'identity' is not a mapping; {FRESH_START}",
                                   store.full(JOB))
        windows = [Window(w["dataset"], w["sequence"], tuple(w["core"]), tuple(w["context"])) for w in d["windows"]]
        try:
            for w in windows:
                check_name(w.dataset, "dataset", "job.json", store.full(JOB))
                check_name(w.sequence, "sequence", "job.json", store.full(JOB))
        except InputError as e:
            raise UnreadableRecord(f"{e.reason}; {FRESH_START}", store.full(JOB)) from None
        return cls(d["run_id"], d["params_hash"], d["config"], windows, identity, d.get("unplanned") or {})

    def job_config(self, where: str = JOB):
        """The recorded config as a typed ``JobConfig`` (``config.job_config_from_record``: keys of
        older versions renamed); ``UnreadableRecord`` naming the key when it does not fit."""
        from mining.config import job_config_from_record

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
