"""Labels: what a person decided about mined tubes, kept beside the catalogue, never in it.

A label is an *event*: one row saying that ``author`` set (or unset) a verdict or a tag on a
tube at a time. Events are only ever added, so two writers cannot lose each other's work:

    labels/part-<UTC>-<hex>-<sha256>.parquet       one file per write (``append``): one or many events
    labels/compact-<UTC>-<hex>-<sha256>.parquet    earlier parts merged (``compact``)
    labels/_damaged/…                              files whose bytes no longer match their name (set aside)

* Every write is a new file under a name of its own, written under a temporary name and
  renamed (``Store.write_bytes``): no lock, no read-modify-write, so two ``mine view``
  servers, a ``mine label`` and a running ``mine submit`` write side by side.
* The name carries the sha256 of the file's bytes (they are serialised in memory first, so
  the name is known before the file appears). Every read checks it before anything else is
  read from the file: a flipped bit is ``DamagedLabels`` ("sha256 mismatch: damaged"), never
  a changed tag; ``mine status`` lists such files and ``mine submit --verify`` moves them,
  byte-identical, to ``labels/_damaged/`` (``set_aside_damaged``), which no reader lists. A
  file named before names carried a digest reads unchecked; a compaction writes its events
  into a digested file.
* ``compact`` merges the parts into one file under the catalogue's one-writer lock
  (``lock.OutputLock``, so never beside a submit or another compaction), dropping events
  seen twice (by ``label_id``), and only then removes the files it merged: a part written
  meanwhile is not among them and stays. A crash between the two leaves duplicates, which
  every reader drops.
* The mined tables are never rewritten, and a resubmission never touches ``labels/``
  (it is not one of ``layout.JOB_ENTRIES``); ``--new-run``, whose tubes may be other
  objects under the same ids, moves it aside with the catalogue it described.

A tube's state is the replay of its events in time order (``tube_labels`` in views.sql): its
verdict is the last verdict event (``unset``: none), its tags those whose last event is
``set``. Readers: ``read_labels`` (every event, duplicates dropped), the DuckDB tables
``labels`` / ``tube_labels`` / ``labelled_tubes`` (``views.connect``).
"""

from __future__ import annotations

import getpass
import hashlib
import os
import posixpath
import re
import uuid
from datetime import datetime, timezone

import pyarrow as pa
import pyarrow.parquet as pq

from mining.catalog.layout import LABELS
from mining.catalog.lock import OutputLock
from mining.catalog.store import COMPRESSION, Store
from mining.errors import InputError

# The built-in verdicts (issue 31): an object, not an object, part of another tube's object,
# a duplicate of another tube.
VERDICTS = ("object", "not_object", "part_of", "duplicate")
KINDS = ("verdict", "tag")
OPS = ("set", "unset")
VIA = ("view", "cli", "propagated")  # which tool wrote an event (propagated: `mine label --like`, from a source tube)
MAX_TAG_CHARS = 64  # ours: a tag is a word or a short phrase (a category name), not a note
MAX_AUTHOR_CHARS = 64  # ours
MAX_EVENTS_PER_WRITE = 100_000  # ours: one `mine label` over a whole drive's tubes, in one file
_PRINTABLE = re.compile(r"[^\x00-\x1f\x7f-\x9f]+")  # no control characters (C0, DEL, C1)
_DIGEST = re.compile(r"-([0-9a-f]{64})\.parquet")  # the sha256 a label file's name ends with
DAMAGED = f"{LABELS}/_damaged"  # where ``mine submit --verify`` sets damaged label files aside
RELIST_TRIES = 20  # ours: a reader lists again when a compaction removed a file it listed


class DamagedLabels(InputError):
    """A label file whose bytes do not hash to the sha256 its name records."""

LABEL_SCHEMA = pa.schema([
    pa.field("label_id", pa.string(), False),  # uuid4 hex of the event: readers drop an event seen twice
    pa.field("dataset", pa.string(), False),
    pa.field("sequence", pa.string(), False),
    pa.field("tube_id", pa.string(), False),
    pa.field("kind", pa.string(), False),  # verdict | tag
    pa.field("value", pa.string()),  # the verdict (one of VERDICTS) or the tag; null: a verdict unset
    pa.field("op", pa.string(), False),  # set | unset
    pa.field("author", pa.string(), False),
    # When it was decided, UTC (a plain timestamp: every reader, DuckDB's Python results too, reads it without a zone library).
    pa.field("at", pa.timestamp("us"), False),
    pa.field("via", pa.string(), False),  # view | cli | propagated
    # Added by issue 41 (nullable: files written before them read them as null). A propagated label's source:
    pa.field("source_tube", pa.string()),  # the tube labelled first, whose decision this event copies (null: decided directly)
    pa.field("distance", pa.float32()),  # cosine distance of the two tubes' descriptors (null: decided directly)
])
ADDED_LABEL_COLUMNS = frozenset({"source_tube", "distance"})  # a label file written before them reads them as null


def default_author() -> str:
    """The login name, the author of labels a user does not name."""
    try:
        return getpass.getuser()
    except (KeyError, OSError):
        return f"uid-{os.getuid()}"


def check_text(text: object, what: str, limit: int) -> str:
    """``text`` stripped, when it is 1..``limit`` printable characters; else an InputError saying why."""
    if not isinstance(text, str):
        raise InputError(f"{what} must be text, got {type(text).__name__}")
    t = text.strip()
    if not t:
        raise InputError(f"{what} is empty")
    if len(t) > limit:
        raise InputError(f"{what} {t[:20]!r}… is {len(t)} characters; at most {limit}")
    if not _PRINTABLE.fullmatch(t):
        raise InputError(f"{what} {t!r} holds a control character")
    return t


def check_verdict(verdict: object) -> str:
    if verdict not in VERDICTS:
        raise InputError(f"verdict {verdict!r}: one of {', '.join(VERDICTS)}")
    return verdict  # type: ignore[return-value]


def events(tubes: list[tuple[str, str, str]], kind: str, value: str | None, op: str = "set",
           author: str | None = None, via: str = "cli", at: datetime | None = None,
           source_tube: str | None = None, distances: list[float] | None = None) -> pa.Table:
    """The events that apply one decision to each of ``tubes`` ((dataset, sequence, tube_id)):
    ``kind`` verdict (``value`` one of VERDICTS, or None with ``op`` unset: no verdict) or tag
    (``value`` the tag); InputError for a value these rules refuse. A propagated decision
    (``via`` propagated) names its ``source_tube`` and each tube's descriptor ``distances`` to it."""
    if (via == "propagated") != (source_tube is not None):
        raise InputError("a propagated label names its source tube, and only a propagated one does")
    if distances is not None and len(distances) != len(tubes):
        raise InputError(f"{len(distances)} distances for {len(tubes)} tubes")
    if kind not in KINDS or op not in OPS or via not in VIA:
        raise InputError(f"a label is kind {'/'.join(KINDS)}, op {'/'.join(OPS)}, via {'/'.join(VIA)}; "
                         f"got {kind!r}, {op!r}, {via!r}")
    if kind == "verdict":
        if op == "set" or value is not None:  # unsetting may name the verdict it clears
            check_verdict(value)
        value = value if op == "set" else None
    else:
        value = check_text(value, "tag", MAX_TAG_CHARS)
    author = check_text(default_author() if author is None else author, "author", MAX_AUTHOR_CHARS)
    if not tubes:
        raise InputError("no tube to label")
    if len(tubes) > MAX_EVENTS_PER_WRITE:
        raise InputError(f"{len(tubes)} tubes in one write; at most {MAX_EVENTS_PER_WRITE}: narrow --where")
    when = (at or datetime.now(timezone.utc)).astimezone(timezone.utc).replace(tzinfo=None)
    n = len(tubes)
    return pa.table({
        "label_id": [uuid.uuid4().hex for _ in range(n)],
        "dataset": [t[0] for t in tubes], "sequence": [t[1] for t in tubes], "tube_id": [t[2] for t in tubes],
        "kind": [kind] * n, "value": [value] * n, "op": [op] * n, "author": [author] * n,
        "at": pa.array([when] * n, pa.timestamp("us")), "via": [via] * n,
        "source_tube": [source_tube] * n, "distance": pa.array(distances if distances is not None else [None] * n,
                                                                pa.float32()),
    }, schema=LABEL_SCHEMA)


def utc_text(when: datetime | None) -> str | None:
    """A label time as ISO-8601 UTC text ending in ``Z`` (None stays None): the one form every
    export writes. A naive time is UTC already (LABEL_SCHEMA's ``at``; DuckDB hands it back naive)."""
    if when is None:
        return None
    if when.tzinfo is not None:
        when = when.astimezone(timezone.utc).replace(tzinfo=None)
    return when.isoformat(timespec="microseconds") + "Z"


def _stamp(when: datetime) -> str:
    return when.astimezone(timezone.utc).strftime("%Y%m%dT%H%M%S%fZ")


def _write(store: Store, kind: str, table: pa.Table) -> str:
    """``table`` as a new label file named ``<kind>-<UTC>-<hex>-<sha256>.parquet``; its path."""
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression=COMPRESSION)
    data = sink.getvalue().to_pybytes()  # label files are small (MAX_EVENTS_PER_WRITE): hashed before naming
    sha = hashlib.sha256(data).hexdigest()
    rel = f"{LABELS}/{kind}-{_stamp(datetime.now(timezone.utc))}-{uuid.uuid4().hex[:12]}-{sha}.parquet"
    store.write_bytes(rel, data)
    return rel


def append(store: Store, table: pa.Table) -> str:
    """Write ``table`` (LABEL_SCHEMA) as a new part; its path relative to the catalogue."""
    if table.schema != LABEL_SCHEMA:
        raise InputError("label events of another schema than labels.LABEL_SCHEMA")
    return _write(store, "part", table)


def label_files(store: Store) -> list[str]:
    """The finished label files (parts and compactions), relative paths, sorted."""
    for attempt in range(RELIST_TRIES):
        try:
            return [f for f in store.list(LABELS) if f.count("/") == 1]
        except FileNotFoundError:  # pyarrow's listing raced the first write making the folder: list again
            if attempt == RELIST_TRIES - 1:
                raise
    raise AssertionError("unreachable")


def recorded_sha256(rel: str) -> str | None:
    """The sha256 a label file's name records; None for a file named before names carried one."""
    m = _DIGEST.search(posixpath.basename(rel))
    return m.group(1) if m and m.end() == len(posixpath.basename(rel)) else None


class _Gone(InputError):
    """A listed label file that is no longer there (a compaction merged and removed it)."""


def _bytes(store: Store, rel: str) -> bytes:
    try:
        with store.fs.open_input_stream(store.full(rel), compression=None) as f:
            return f.read()
    except FileNotFoundError:
        raise _Gone("label file not found", store.full(rel)) from None
    except OSError as e:
        raise InputError(f"cannot read label file: {e}", store.full(rel)) from None


def _mismatch(rel: str, data: bytes) -> str | None:
    """Why ``data`` is not the file its name records ("sha256 mismatch: damaged …"); None when it is."""
    want = recorded_sha256(rel)
    got = hashlib.sha256(data).hexdigest() if want else None
    if want and got != want:
        return (f"sha256 mismatch: damaged (its bytes hash to {got[:12]}…, its name records {want[:12]}…); "
                f"`mine submit --verify` moves it to {DAMAGED}/ (its labels are lost)")
    return None


def _read(store: Store, rel: str) -> pa.Table:
    data = _bytes(store, rel)
    if why := _mismatch(rel, data):  # the digest before anything else is read from the bytes
        raise DamagedLabels(why, store.full(rel))
    try:
        table = pq.read_table(pa.BufferReader(data))
    except (pa.ArrowInvalid, OSError) as e:
        raise InputError(f"cannot read Parquet file: {e}", store.full(rel)) from None
    if not set(LABEL_SCHEMA.names) - ADDED_LABEL_COLUMNS <= set(table.schema.names):
        missing = sorted(set(LABEL_SCHEMA.names) - ADDED_LABEL_COLUMNS - set(table.schema.names))
        raise InputError(f"not a labels file: no column {', '.join(missing)}", store.full(rel))
    for name in sorted(ADDED_LABEL_COLUMNS - set(table.schema.names)):  # written before the column
        table = table.append_column(name, pa.nulls(len(table), LABEL_SCHEMA.field(name).type))
    try:
        return table.select(LABEL_SCHEMA.names).cast(LABEL_SCHEMA)
    except (pa.ArrowInvalid, pa.ArrowTypeError, ValueError) as e:
        raise InputError(f"not a labels file: {e}", store.full(rel)) from None


def _once_in_time_order(tables: list[pa.Table]) -> pa.Table:
    if not tables:
        return LABEL_SCHEMA.empty_table()
    table = pa.concat_tables(tables)
    # Each event once (a compaction that crashed before removing its parts leaves copies).
    seen: set[str] = set()
    keep = []
    for k, lid in enumerate(table.column("label_id").to_pylist()):
        if lid not in seen:
            seen.add(lid)
            keep.append(k)
    table = table.take(pa.array(keep, pa.int64()))
    return table.sort_by([("at", "ascending"), ("label_id", "ascending")])


def read_label_files(store: Store) -> tuple[list[str], pa.Table]:
    """The label files and every event in them (``read_labels``). A file a compaction removed
    between the listing and its read is no loss (the compaction wrote its events first): the
    folder is listed again."""
    for attempt in range(RELIST_TRIES):
        files = label_files(store)
        try:
            return files, _once_in_time_order([_read(store, f) for f in files])
        except _Gone:
            if attempt == RELIST_TRIES - 1:
                raise
    raise AssertionError("unreachable")


def read_labels(store: Store, files: list[str] | None = None) -> pa.Table:
    """Every label event of the catalogue (or of ``files``), each once, in time order.
    InputError naming the file for one that does not read or is not a labels file;
    ``DamagedLabels`` for one whose bytes do not match the sha256 its name records."""
    if files is None:
        return read_label_files(store)[1]
    return _once_in_time_order([_read(store, f) for f in files])


def damaged_label_files(store: Store) -> dict[str, str]:
    """The label files whose bytes do not match the sha256 their name records: path → why."""
    out = {}
    for rel in label_files(store):
        try:
            why = _mismatch(rel, _bytes(store, rel))
        except _Gone:
            continue  # compacted meanwhile: its events are in the merged file
        if why:
            out[rel] = why
    return out


def set_aside_damaged(store: Store) -> list[str]:
    """Move every damaged label file (``damaged_label_files``), byte-identical, to ``labels/_damaged/``,
    where no reader lists it; their full paths there. Call it holding the writer lock (as
    ``mine submit`` does): a compaction never reads a file while it moves."""
    moved = []
    for rel in damaged_label_files(store):
        dst = f"{DAMAGED}/{posixpath.basename(rel)}"
        store.make_dir(DAMAGED)
        store.move(rel, dst)  # a rename: the bytes as found, for whoever wants to see what was lost
        moved.append(store.full(dst))
    return moved


def compact(store: Store, lock_wait_s: float = 0.0) -> tuple[int, int]:
    """Merge every label file into one, under the writer lock; (files merged, events kept).
    Nothing is removed until the merged file is in place; one file with its digest: nothing to do.
    The merged file's name carries its digest, so files named before digests are checked from then on."""
    with OutputLock(store, lock_wait_s):
        files = label_files(store)  # under the lock no other compaction removes one of them
        if not files or (len(files) == 1 and recorded_sha256(files[0])):  # one undigested file: digested now
            return 0, (read_labels(store, files).num_rows if files else 0)
        table = read_labels(store, files)  # a damaged file refuses the compaction, naming it: nothing is lost
        _write(store, "compact", table)
        for f in files:
            store.remove(f)
        return len(files), table.num_rows
