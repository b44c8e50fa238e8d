"""A job's life in its catalogue: what earlier runs left (``read_resume`` → ``Resume``, for the
schedule), and the job recorded (``record_job``), its old windows retired, an old catalogue
set aside (``--new-run``), the temporaries of a killed run swept (``sweep_temporaries``).

Read from the records (``catalog/records.py``) and checked against what is there
(``catalog/integrity.py``): a window is done when its manifest row says so with these params
and this window's core and context (``ManifestRow.says_done``) and its parts are all there as
its files record lists them; a sequence is finalized when its marker is of this job
(``SequenceMarker.of_job``), its compacted files are all there as the marker records them,
and no failed-stitch row of it is unreadable. Anything else is recomputed: a record that does
not read vouches for nothing, a window with a damaged part runs again, a sequence with a
damaged compacted file (or record) is stitched again. ``mine status`` reads the same records
with the same predicates (``status.py``).

``record_job`` writes ``job.json`` (``records.JobRecord``) or checks a resubmission against it
(``identity.check_resubmit``: the same job, an extension, or a new run); a ``--new-run`` moves
the old catalogue to ``layout.REPLACED`` inside ``--out``. ``submit.py`` calls these holding the
catalogue's lock.
"""

from __future__ import annotations

import sys
import time
import uuid
from collections.abc import Mapping
from dataclasses import dataclass, field

import pyarrow.fs as pafs

from mining.catalog.identity import check_resubmit
from mining.catalog.integrity import marker_damage, window_damage
from mining.catalog.layout import (DISCOVERY, EMBEDDINGS, JOB, JOB_ENTRIES, LABELS, PART_TABLES, REPLACED, STITCH_ROW, cache_path,
                                   check_resumable, files_path, manifest_path, part_path)
from mining.catalog.records import (FRESH_START, JobRecord, ManifestRow, SequenceMarker, Unreadable,
                                    UnreadableRecord)
from mining.catalog.store import Store
from mining.config import JobConfig
from mining.errors import ConfigError, InputError
from mining.types import Window


@dataclass(frozen=True)
class Resume:
    """What earlier runs of the job left in its catalogue."""

    done: Mapping[str, bool] = field(default_factory=dict)  # window done → was its context complete then
    finalized: Mapping[str, frozenset[str]] = field(default_factory=dict)  # sequence → windows its catalogue holds


def read_resume(store: Store, dataset: str, windows: list[Window], params_hash: str, verify: bool = False) -> Resume:
    """The windows of ``windows`` that are done and vouched for (sizes of their parts; checksums
    too with ``verify``), each with whether its context was complete when it was tracked; and
    the sequences finalized with these params whose compacted files are all there as recorded
    (the windows each holds)."""
    done = {}
    for w in windows:
        row = ManifestRow.load(store, w.dataset, w.sequence, w.name)
        if isinstance(row, ManifestRow) and row.says_done(params_hash, w) and not window_damage(store, w, verify):
            done[w.name] = row.context_complete is not False
    finalized = {}
    contexts = {w.name: tuple(w.context) for w in windows}
    for seq in dict.fromkeys(w.sequence for w in windows):
        marker = SequenceMarker.load(store, dataset, seq)
        if (isinstance(marker, SequenceMarker) and marker.of_job(params_hash, contexts)
                and not isinstance(ManifestRow.load(store, dataset, seq, STITCH_ROW), Unreadable)
                and not marker_damage(store, marker, verify)):
            finalized[seq] = frozenset(marker.windows)
    return Resume(done, finalized)


# -- the job's lifecycle: recorded, its old windows retired, a catalogue set aside, temporaries swept --

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
    # The labels, what discovery derived and the embeddings go too: the new run's tube ids may name other objects.
    present = [e for e in (*JOB_ENTRIES, LABELS, DISCOVERY, EMBEDDINGS) if store.fs.get_file_info(store.full(e)).type != pafs.FileType.NotFound]
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
