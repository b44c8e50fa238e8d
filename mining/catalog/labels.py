"""Labels: what a person decided about mined tubes, kept beside the catalogue, never in it.

A label is an *event*: one row saying that ``author`` set (or unset) a verdict or a tag on a
tube at a time. Events are only ever added, so two writers cannot lose each other's work:

    labels/part-<UTC>-<hex>.parquet       one file per write (``append``): one or many events
    labels/compact-<UTC>-<hex>.parquet    earlier parts merged (``compact``)

* Every write is a new file under a name of its own, written under a temporary name and
  renamed (``Store.write_table``): no lock, no read-modify-write, so two ``mine view``
  servers, a ``mine label`` and a running ``mine submit`` write side by side.
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
import os
import re
import uuid
from datetime import datetime, timezone

import pyarrow as pa

from mining.catalog.layout import LABELS
from mining.catalog.lock import OutputLock
from mining.catalog.store import Store
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


def _stamp(when: datetime) -> str:
    return when.astimezone(timezone.utc).strftime("%Y%m%dT%H%M%S%fZ")


def append(store: Store, table: pa.Table) -> str:
    """Write ``table`` (LABEL_SCHEMA) as a new part; its path relative to the catalogue."""
    if table.schema != LABEL_SCHEMA:
        raise InputError("label events of another schema than labels.LABEL_SCHEMA")
    rel = f"{LABELS}/part-{_stamp(datetime.now(timezone.utc))}-{uuid.uuid4().hex[:12]}.parquet"
    store.write_table(rel, table)
    return rel


def label_files(store: Store) -> list[str]:
    """The finished label files (parts and compactions), relative paths, sorted."""
    return [f for f in store.list(LABELS) if f.count("/") == 1]


def _read(store: Store, rel: str) -> pa.Table:
    table = store.read_table(rel)  # InputError naming the file when it does not read as Parquet
    if not set(LABEL_SCHEMA.names) - ADDED_LABEL_COLUMNS <= set(table.schema.names):
        missing = sorted(set(LABEL_SCHEMA.names) - ADDED_LABEL_COLUMNS - set(table.schema.names))
        raise InputError(f"not a labels file: no column {', '.join(missing)}", store.full(rel))
    for name in sorted(ADDED_LABEL_COLUMNS - set(table.schema.names)):  # written before the column
        table = table.append_column(name, pa.nulls(len(table), LABEL_SCHEMA.field(name).type))
    try:
        return table.select(LABEL_SCHEMA.names).cast(LABEL_SCHEMA)
    except (pa.ArrowInvalid, pa.ArrowTypeError, ValueError) as e:
        raise InputError(f"not a labels file: {e}", store.full(rel)) from None


def read_labels(store: Store, files: list[str] | None = None) -> pa.Table:
    """Every label event of the catalogue (or of ``files``), each once, in time order.
    InputError naming the file for one that does not read or is not a labels file."""
    files = label_files(store) if files is None else files
    if not files:
        return LABEL_SCHEMA.empty_table()
    table = pa.concat_tables([_read(store, f) for f in files])
    # Each event once (a compaction that crashed before removing its parts leaves copies).
    seen: set[str] = set()
    keep = []
    for k, lid in enumerate(table.column("label_id").to_pylist()):
        if lid not in seen:
            seen.add(lid)
            keep.append(k)
    table = table.take(pa.array(keep, pa.int64()))
    return table.sort_by([("at", "ascending"), ("label_id", "ascending")])


def compact(store: Store, lock_wait_s: float = 0.0) -> tuple[int, int]:
    """Merge every label file into one, under the writer lock; (files merged, events kept).
    Nothing is removed until the merged file is in place; fewer than two files: nothing to do."""
    with OutputLock(store, lock_wait_s):
        files = label_files(store)
        if len(files) < 2:
            return 0, (read_labels(store, files).num_rows if files else 0)
        table = read_labels(store, files)
        rel = f"{LABELS}/compact-{_stamp(datetime.now(timezone.utc))}-{uuid.uuid4().hex[:12]}.parquet"
        store.write_table(rel, table)
        for f in files:
            store.remove(f)
        return len(files), table.num_rows
