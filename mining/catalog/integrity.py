"""Integrity of a catalogue: the size and sha256 of every file as written, against what is there.

Each output a later step or a reader trusts is recorded when it is written (the records are
``records.py``'s types):

* a window's parts (``_parts/<table>/…/<window>.part``) in ``manifest/…/<window>.files.json``
  (``WindowFiles``), written after the parts and before the window's manifest row says done;
* a sequence's compacted files (``catalog/<table>/…/part-<k>.parquet``, all four tables) in
  its finished marker ``catalog/_sequences/…`` (``SequenceMarker``), written after them. A
  marker of a catalogue before schema v3 records its files' hive paths
  (``catalog/<table>/dataset=D/sequence=S/…``): they are checked the same way, and a file in
  either layout's folder of a sequence that its marker does not record is a left-over.

A record that does not read vouches for nothing: its window runs again, its sequence is
stitched again, and ``mine status`` names it with the reason.

Checking costs a listing and a ``stat`` per file (sizes: a deleted or truncated file), or
reads every byte with ``verify`` (checksums: a file damaged in place). Three callers:
resume (``pipeline/resume.read_resume``: a window with a damaged part runs again, a sequence with a
damaged compacted file is stitched again from its parts), ``mine status`` (names every
damaged file and what a resubmission recomputes) and the query views (``views.connect``
through ``vouched_files``: they read only the files the markers vouch for, each checked
by size and sha256 once per process; a table with a damaged file refuses queries, naming
it; the other tables answer).
"""

from __future__ import annotations

import hashlib
import json
import threading
from collections.abc import Iterable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import pyarrow.fs as pafs

from mining.catalog.layout import (CATALOG, JOB, MANIFEST, MARKERS, PART_TABLES, catalog_dir, catalog_layout, files_path,
                                   part_path)
from mining.catalog.records import SequenceMarker, Unreadable, WindowFiles
from mining.catalog.store import Store, is_temporary
from mining.catalog.versions import SchemaVersionError, check_file, check_record_version
from mining.errors import InputError
from mining.types import Window

CHUNK = 1 << 20  # ours: bytes read per step while hashing
TABLES = ("tubes", "tube_frames", "frames", "windows")  # the compacted tables a finalize writes


@dataclass(frozen=True)
class Damage:
    """One file that is not as recorded."""

    path: str  # relative to the catalogue root
    reason: str  # "missing", "1200 bytes, 5310 recorded", …
    owner: str  # what recomputes it: "window W" (runs again) or "sequence S" (stitched again)

    @property
    def table(self) -> str:
        """The table a compacted file belongs to ("" for other files)."""
        parts = self.path.split("/")
        return parts[1] if len(parts) > 2 and parts[0] == CATALOG and parts[1] in TABLES else ""


def digest(store: Store, rel: str) -> dict:
    """``{"size", "sha256"}`` of one file, read back from the store."""
    h, size = hashlib.sha256(), 0
    with store.fs.open_input_stream(store.full(rel)) as f:
        while chunk := f.read(CHUNK):
            h.update(chunk)
            size += len(chunk)
    return {"size": size, "sha256": h.hexdigest()}


def mismatch(got: str, want: Mapping, record: str = "marker") -> str:
    """The reason of a file whose sha256 is not the one its ``record`` holds: damage, named so."""
    return f"sha256 {got[:12]}… does not match its {record}'s {str(want.get('sha256'))[:12]}…: damaged"


def record_files(store: Store, rels: Iterable[str]) -> dict[str, dict]:
    """``digest`` of each file: the record a manifest keeps."""
    return {rel: digest(store, rel) for rel in rels}


def read_json(store: Store, rel: str) -> dict | None:
    """A JSON object (``job.json`` for ``mined``), or None when it is missing or unreadable."""
    try:
        with store.open_stream(rel) as f:
            d = json.loads(f.read())
    except (FileNotFoundError, OSError, ValueError, RecursionError, InputError):  # RecursionError: nested past the parser
        return None
    return d if isinstance(d, dict) else None


def _sizes(store: Store, rels: list[str]) -> dict[str, int | None]:
    """Size of each file; None when it is not a file."""
    infos = store.fs.get_file_info([store.full(r) for r in rels]) if rels else []
    return {r: (i.size if i.type == pafs.FileType.File else None) for r, i in zip(rels, infos)}


def check_files(store: Store, recorded: Mapping[str, Mapping], owner: str, verify: bool = False,
                record: str = "marker") -> list[Damage]:
    """The recorded files that are missing, of another size or (``verify``) of another checksum."""
    out = []
    for rel, size in _sizes(store, sorted(recorded)).items():
        want = recorded[rel]
        if size is None:
            out.append(Damage(rel, "missing", owner))
        elif size != want.get("size"):
            out.append(Damage(rel, f"{size} bytes, {want.get('size')} recorded", owner))
        elif verify:
            try:
                got = digest(store, rel)["sha256"]
            except OSError as e:
                out.append(Damage(rel, f"unreadable: {e}", owner))
                continue
            if got != want.get("sha256"):
                out.append(Damage(rel, mismatch(got, want, record), owner))
    return out


def window_files(store: Store, window: Window) -> WindowFiles:
    """The record of the parts a window's tracking wrote, with their digests (``WindowFiles.save`` it)."""
    return WindowFiles(window, record_files(
        store, [part_path(t, window.dataset, window.sequence, window.name) for t in PART_TABLES]))


def window_damage(store: Store, window: Window, verify: bool = False) -> list[Damage]:
    """The damaged or missing parts of a window its manifest row says is done."""
    owner = f"window {window.name}"
    record = WindowFiles.load(store, window)
    if not isinstance(record, WindowFiles):
        return [Damage(files_path(window.dataset, window.sequence, window.name),
                       "missing or unreadable: the window's parts cannot be checked", owner)]
    parts = check_files(store, record.files, owner, verify, "files record")
    return [Damage(r, "missing", owner) for r in record.missing()] + parts


def sequence_files(store: Store, written: Iterable[str]) -> dict[str, dict]:
    """The compacted files a finalize wrote, with their digests (for the finished marker)."""
    return record_files(store, written)


def marker_damage(store: Store, marker: SequenceMarker, verify: bool = False) -> list[Damage]:
    """The damaged, missing or unexpected compacted files of a finalized sequence: what keeps
    its marker from vouching for its catalogue (resume stitches it again; status names them)."""
    owner = f"sequence {marker.sequence}"
    if marker.files is None:
        return [Damage(marker.path, "records no file sizes (written before integrity records)", owner)]
    out = check_files(store, marker.files, owner, verify)
    for table in TABLES:  # a file no finalize recorded is read by every query: a left-over
        for rel in _sequence_files(store, table, marker.dataset, marker.sequence):
            if rel not in marker.files:
                out.append(Damage(rel, "not recorded by the sequence's last finalize (left over)", owner))
    return out


def unreadable_damage(record: Unreadable, owner: str) -> Damage:
    """A record that does not read: what it vouched for cannot be checked, and ``owner`` recomputes it."""
    return Damage(record.path, f"unreadable: {record.reason}", owner)


def sequence_damage(store: Store, dataset: str, sequence: str, verify: bool = False) -> list[Damage] | None:
    """``marker_damage`` of one sequence, or its marker when it does not read; None when it has none."""
    marker = SequenceMarker.load(store, dataset, sequence)
    if isinstance(marker, Unreadable):
        return [unreadable_damage(marker, f"sequence {sequence}")]
    return None if marker is None else marker_damage(store, marker, verify)


def catalogue_damage(store: Store, verify: bool = False) -> dict[str, list[Damage]]:
    """Damaged compacted files by table, over every finalized sequence (what queries read)."""
    out: dict[str, list[Damage]] = {}
    for m in SequenceMarker.load_all(store):
        if not isinstance(m, SequenceMarker) or m.files is None:
            continue  # unreadable, or from before integrity records: nothing to check against
        for d in marker_damage(store, m, verify):
            out.setdefault(d.table, []).append(d)
    return out


def unreadable_parquet(store: Store, rels: Iterable[str]) -> list[tuple[str, str]]:
    """The files among ``rels`` whose Parquet footer does not read, with the reason."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    out = []
    for rel in rels:
        if is_temporary(rel):
            continue
        try:
            with store.fs.open_input_file(store.full(rel)) as f:
                pq.ParquetFile(f).metadata  # noqa: B018 - reading the footer is the check
        except (pa.ArrowInvalid, OSError) as e:
            out.append((rel, str(e)))
    return out


# -- the read path: what the query views may read ------------------------------------------

_SHA_CACHE: dict[tuple[str, str, int, int | None], str] = {}  # (store root, rel, size, mtime_ns) → sha256
_SHA_LOCK = threading.Lock()
HASH_THREADS = 4  # ours: hashlib releases the GIL on large updates, so a few threads overlap reads and hashing


def cached_sha256(store: Store, rel: str, size: int, mtime_ns: int | None) -> str:
    """sha256 of one file, hashed once per process while its size and mtime stay the same."""
    key = (store.root, rel, size, mtime_ns)
    with _SHA_LOCK:
        if key in _SHA_CACHE:
            return _SHA_CACHE[key]
    got = digest(store, rel)
    if got["size"] != size:  # changed while it was read: not cached, checked again next time
        return got["sha256"]
    with _SHA_LOCK:
        _SHA_CACHE[key] = got["sha256"]
    return got["sha256"]


@dataclass
class Vouched:
    """The compacted files the query views read, by table, and the damaged ones."""

    files: dict[str, list[str]]  # table → files that check out (relative paths, sorted)
    damage: dict[str, list[Damage]]  # table → files that do not
    marked: bool  # False: a catalogue no mining job wrote (no marker, no planned window): served as listed, unchecked


def _sequence_dirs(table: str, dataset: str, sequence: str) -> tuple[str, str]:
    """The folders of one sequence's compacted files of ``table``, in both layouts (``layout.catalog_layout``)."""
    return catalog_dir(table, dataset, sequence), catalog_dir(table, dataset, sequence, hive=True)


def _sequence_files(store: Store, table: str, dataset: str, sequence: str) -> list[str]:
    """The finished files in a sequence's folders of ``table`` (both layouts)."""
    return [r for d in _sequence_dirs(table, dataset, sequence) for r in store.list(d) if not is_temporary(r)]


def mined(store: Store) -> bool:
    """Whether a mining job writes this catalogue (so only what its markers vouch for is served):
    it has a finished marker, or a job.json that plans windows (or does not read)."""
    if store.list(MARKERS, ".json"):
        return True
    if not store.exists(JOB):
        return False
    job = read_json(store, JOB)
    return job is None or not isinstance(job.get("windows"), list) or bool(job["windows"])


def check_versions(store: Store, oldest: bool = True) -> None:
    """Refuse a catalogue of a schema version this code does not read (``versions.py``), before
    anything of it is read: ``job.json``, every sequence marker, every Parquet file of the
    compacted tables and of the manifest (the files the query views and ``mine status`` read).
    ``oldest`` False (a submission): rows older than this code reads are not refused (see
    ``versions.py``). Raises ``versions.SchemaVersionError`` naming the file; a compacted file it
    would refuse that is not as its marker records is damage instead (left to the damage checks)."""
    check_record_version(read_json(store, JOB), store.full(JOB))
    markers = SequenceMarker.load_all(store)  # a marker of a newer version raises
    recorded = {rel: want for m in markers if isinstance(m, SequenceMarker) and m.files
                for rel, want in m.files.items()}
    rels = [r for r in store.list(CATALOG) if r.split("/")[1] in TABLES] + store.list(MANIFEST)
    infos = store.fs.get_file_info([store.full(r) for r in rels]) if rels else []
    for rel, info in zip(rels, infos):
        if info.type != pafs.FileType.File:
            continue
        try:
            check_file(store, rel, rel.split("/")[1] if rel.startswith(CATALOG + "/") else "windows", info.size,
                       info.mtime_ns, oldest)
        except SchemaVersionError:
            # Integrity comes first: a file its marker no longer vouches for is damage (one flipped bit
            # in a column name reads as a column of a newer version), which the damage checks name and
            # a resubmission with --verify recomputes; only a file as written speaks for its version.
            if rel in recorded and not _as_recorded(store, rel, recorded[rel], info):
                continue
            raise


def _as_recorded(store: Store, rel: str, want: Mapping, info: pafs.FileInfo) -> bool:
    """Whether one file is as its record says (size, then sha256)."""
    if info.size != want.get("size"):
        return False
    try:
        return cached_sha256(store, rel, info.size, info.mtime_ns) == want.get("sha256")
    except OSError:
        return False


def vouched_files(store: Store, verify: bool = True) -> Vouched:
    """The compacted files of every finalized sequence, checked against its marker (size always,
    sha256 with ``verify``, each file hashed once per process: ``cached_sha256``).

    Only files a readable marker records under its own sequence's folders are served: a
    sequence whose first stitch has not finished (no marker yet), a folder no marker records
    or a file its marker does not list is not read. A marker that does not read, or one from
    before integrity records (no files to check against), vouches for nothing: ``mine status``
    names it, and a resubmission stitches its sequence again. A catalogue no
    mining job wrote (``mined`` False: files written by ``store.write_sequence`` alone) is
    served as listed, unchecked.
    """
    files: dict[str, set[str]] = {t: set() for t in TABLES}
    damage: dict[str, dict[str, Damage]] = {}
    if not mined(store):
        for t in TABLES:
            files[t] = {r for r in store.list(f"{CATALOG}/{t}") if catalog_layout(r) is not None}
        return Vouched({t: sorted(v) for t, v in files.items()}, {}, False)
    recorded: dict[str, tuple[Mapping, str]] = {}  # rel → (its record, owner)
    for m in SequenceMarker.load_all(store):
        if not isinstance(m, SequenceMarker) or m.files is None:
            continue  # unreadable, or from before integrity records: vouches for nothing
        dirs = [d + "/" for t in TABLES for d in _sequence_dirs(t, m.dataset, m.sequence)]
        owner = f"sequence {m.sequence}"
        for t in TABLES:
            for rel in set(_sequence_files(store, t, m.dataset, m.sequence)) - m.files.keys():
                damage.setdefault(t, {})[rel] = Damage(rel, "not recorded by the sequence's last finalize (left over)",
                                                       owner)
        for rel, want in m.files.items():
            if any(rel.startswith(d) and "/" not in rel[len(d):] for d in dirs):
                recorded.setdefault(rel, (want, owner))
    rels = sorted(recorded)
    infos = store.fs.get_file_info([store.full(r) for r in rels]) if rels else []
    to_hash = []
    for rel, info in zip(rels, infos):
        want, owner = recorded[rel]
        table = rel.split("/")[1]
        if info.type != pafs.FileType.File:
            damage.setdefault(table, {})[rel] = Damage(rel, "missing", owner)
        elif info.size != want.get("size"):
            damage.setdefault(table, {})[rel] = Damage(rel, f"{info.size} bytes, {want.get('size')} recorded", owner)
        elif verify:
            to_hash.append((rel, info))
        else:
            files[table].add(rel)

    def check(item):
        rel, info = item
        try:
            return rel, cached_sha256(store, rel, info.size, info.mtime_ns), None
        except OSError as e:
            return rel, None, f"unreadable: {e}"

    with ThreadPoolExecutor(max_workers=max(1, min(HASH_THREADS, len(to_hash)))) as pool:
        for rel, got, problem in pool.map(check, to_hash):
            want, owner = recorded[rel]
            table = rel.split("/")[1]
            if problem is None and got != want.get("sha256"):
                problem = mismatch(got, want)
            if problem is None:
                files[table].add(rel)
            else:
                damage.setdefault(table, {})[rel] = Damage(rel, problem, owner)
    return Vouched({t: sorted(v) for t, v in files.items()},
                   {t: [d[k] for k in sorted(d)] for t, d in damage.items()}, True)
