"""Catalogue schema versions, checked on read: what this code does not read is refused, never guessed.

``schema.SCHEMA_VERSION`` is written in every ``tubes`` row (its ``schema_version`` column) and
in each JSON record (``job.json``, the sequence markers, the windows' files records: key
``schema_version``; records written before the key existed are v2, the version of their rows).
A reader meets

* a version NEWER than this code's (a row, a record, or a Parquet file with a column its table
  does not have: a newer writer's column would be dropped without a word): refused by every
  reader, by ``mine status`` and by ``mine submit`` (a resubmission, ``--extend`` and
  ``--new-run`` alike), naming the file, the version found and the version this code reads.
  A newer version may mean other things by the same columns; only it may read or replace that
  catalogue (or mine into another ``--out``).
* rows OLDER than ``OLDEST_ROWS`` (v1, before unclassified tubes: its rows kept no class
  evidence, so there is no migration): refused by the readers with the command that replaces
  it, ``mine submit … --new-run``; a submission reads it as before (v1 markers record no
  checksums, so its sequences are stitched again; ``--new-run`` moves it aside). No JSON
  record of v1 carries a version: an older record does not exist to be refused.

The versions: v1 (no class evidence), v2 (unclassified tubes, class evidence), v3 (the same
columns; the compacted tables moved from hive folders ``catalog/<table>/dataset=D/sequence=S/``,
which left ``dataset`` / ``sequence`` out of the files, to ``catalog/<table>/D/S/`` with both
inside every file, so any Parquet reader's default read gives them as strings: ``layout.py``).
A v2 catalogue is read as it is (``views.py`` reads each file by its layout) and refused by a
resubmission or ``--extend`` naming ``--new-run`` (``layout.check_resumable``); v2 code meets a
v3 catalogue's rows and records as newer and refuses them.

``SchemaVersionError`` is an ``InputError`` (exit 2, one line), not an ``UnreadableRecord``:
a catalogue of a newer version is not damage to recompute or move aside.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import TYPE_CHECKING

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from mining.catalog.schema import SCHEMA_VERSION, SCHEMAS
from mining.errors import InputError

if TYPE_CHECKING:
    from mining.catalog.store import Store

OLDEST_ROWS = 2  # v1 rows lack classified_frames / class_evidence and read known / category as never null
RECORD_KEY = "schema_version"  # the key of a JSON record, the column of a tubes row
UNVERSIONED_RECORD = 2  # a record without the key: written by v2 code before records carried it


class SchemaVersionError(InputError):
    """A catalogue file or record of a schema version this code does not read."""


def newer(found: object, path: str | Path, what: str = "catalogue schema") -> SchemaVersionError:
    return SchemaVersionError(f"{what} v{found}, but this tube-miner reads v{SCHEMA_VERSION}: a newer version "
                              "wrote it and may mean other things by its columns; read it with that version "
                              "(or mine into another --out)", path)


def older(found: object, path: str | Path, out: str) -> SchemaVersionError:
    return SchemaVersionError(
        f"catalogue schema v{found}, but this tube-miner reads v{SCHEMA_VERSION} (and no older than v{OLDEST_ROWS}): "
        f"v{found} kept no class evidence, so there is no migration: mine it again with `mine submit --config JOB --out {out} "
        "--new-run` (the old catalogue is moved to _replaced/ inside --out)", path)


def check_record_version(record: object, path: str | Path) -> None:
    """Refuse a JSON record whose ``schema_version`` is newer than this code's (or not a version)."""
    if not isinstance(record, dict) or RECORD_KEY not in record:
        return  # not an object: the record's own shape check names it; no key: v2
    v = record[RECORD_KEY]
    if not isinstance(v, int) or isinstance(v, bool):
        raise SchemaVersionError(f"{RECORD_KEY} {v!r} is not a catalogue schema version (this tube-miner reads "
                                 f"v{SCHEMA_VERSION})", path)
    if v > SCHEMA_VERSION:
        raise newer(v, path)


def unknown_columns(names: list[str], table: str) -> list[str]:
    """The columns among ``names`` that a file of ``table`` does not have (``dataset`` / ``sequence``
    are in a v3 compacted file, in the folder names of a manifest row or an older file)."""
    known = set(SCHEMAS[table].names)
    return [n for n in names if n not in known]


def check_columns(names: list[str], table: str, path: str | Path) -> None:
    """Refuse a file of ``table`` with a column the table does not have."""
    if extra := unknown_columns(names, table):
        raise SchemaVersionError(
            f"column{'s' if len(extra) > 1 else ''} {', '.join(map(repr, extra))}, which table {table} does not have: "
            f"written by a newer version? This tube-miner reads v{SCHEMA_VERSION}, and a column it does not know "
            "would be dropped without a word", path)


def _row_versions(f: pq.ParquetFile) -> tuple[int, int] | None:
    """The least and greatest ``schema_version`` of a tubes file's rows (from the footer's
    statistics; the column itself where a row group has none); None: no rows."""
    names = f.schema_arrow.names
    if RECORD_KEY not in names:
        return None
    i, md = names.index(RECORD_KEY), f.metadata
    lo = hi = None
    for g in range(md.num_row_groups):
        col = md.row_group(g).column(i)
        if md.row_group(g).num_rows == 0:
            continue
        st = col.statistics
        if st is not None and st.has_min_max:
            a, b = int(st.min), int(st.max)
        else:
            values = f.read_row_group(g, columns=[RECORD_KEY]).column(0)
            a, b = int(pc.min(values).as_py()), int(pc.max(values).as_py())
        lo, hi = (a, b) if lo is None else (min(lo, a), max(hi, b))
    return None if lo is None else (lo, hi)


# (root, rel, size, mtime_ns) → (its rows' least and greatest version or None, its unknown columns)
_CHECKED: dict[tuple[str, str, int, int | None], tuple[tuple[int, int] | None, list[str]]] = {}
_LOCK = threading.Lock()


def check_file(store: Store, rel: str, table: str, size: int, mtime_ns: int | None, oldest: bool = True) -> None:
    """Refuse a Parquet file of ``table`` written in a schema this code does not read: a tubes
    row newer than ``SCHEMA_VERSION`` (or, with ``oldest``, older than ``OLDEST_ROWS``), or a
    column the table does not have. A file whose footer does not read is left to the damage
    checks (``integrity.py``), which name it. Each file is read once per process while its
    size and mtime stay the same."""
    key = (store.root, rel, size, mtime_ns)
    with _LOCK:
        found = _CHECKED.get(key)
    if found is None:
        try:
            with store.fs.open_input_file(store.full(rel)) as fh:
                f = pq.ParquetFile(fh)
                found = (_row_versions(f) if table == "tubes" else None, unknown_columns(f.schema_arrow.names, table))
        except (pa.ArrowInvalid, OSError):
            return
        with _LOCK:
            _CHECKED[key] = found
    versions, extra = found
    if versions is not None and versions[1] > SCHEMA_VERSION:  # the version first: it says what the columns are
        raise newer(versions[1], store.full(rel))
    check_columns(extra, table, store.full(rel))
    if versions is not None and oldest and versions[0] < OLDEST_ROWS:
        raise older(versions[0], store.full(rel), store.uri)
