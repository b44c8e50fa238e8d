"""Where the catalogue lives: a local folder or any pyarrow filesystem URI.

Every write is atomic: the bytes go to a temporary name in the destination folder
(``.<name>.tmp-<random>``), then the file is moved onto its final name. Readers (this
module, DuckDB's ``*.parquet`` globs, pyarrow datasets, which skip names starting with
``.``) never see a half-written file; a crash leaves at most a stray temporary file,
which every reader ignores and the next write of that name does not trip over.

On a local filesystem writes, moves and removals go through ``safe_files.py``: no link
below ``--out`` is followed (a link folder is refused, naming it; a link at a file's name
is replaced, not written through), the temporary file is created with ``O_EXCL``, and the
move is a rename (atomic on POSIX). Object stores (S3, GCS) have no links and no rename,
but a single object appears only once its upload completes, so the copy that ``move``
does there is just as invisible while in flight. A write that fails (a full disk…) raises
``safe_files.WriteError`` naming the file; the file it would have replaced is untouched.

A kill between a write's two halves leaves its temporary file; ``temporaries`` finds those
(the exact names writes make, ``LEFTOVER``: plain files only, no link followed) for ``mine
status`` to report and the next ``mine submit`` to remove.

``write_sequence`` compacts one table of one sequence into few large, sorted Parquet
files under ``catalog/<table>/D/S/part-<k>.parquet``, ``dataset`` and ``sequence`` inside
every file (schema v3). Which path holds what is ``layout.py``'s; this module only reads and writes.
"""

from __future__ import annotations

import os
import posixpath
import re
import stat
import uuid
from collections.abc import Iterable
from pathlib import Path

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.fs as pafs
import pyarrow.parquet as pq

from mining.catalog import safe_files
from mining.catalog.layout import JOB, JOB_ENTRIES, RUNNING, catalog_dir, catalog_file
from mining.catalog.safe_files import TMP_MARK, write_error
from mining.catalog.schema import PARTITION, SCHEMA_VERSION, file_schema
from mining.errors import InputError
from mining.files import check_regular, open_regular

COMPRESSION = "zstd"  # ours: smaller than snappy at similar decode speed in DuckDB
ROWS_PER_FILE = 2_000_000  # ours: few large files per sequence (DESIGN "never by window")
ROW_GROUP_ROWS = 122_880  # ours: DuckDB's own row group size, its unit of parallel scans
# Sort keys of the compacted tables: a tube's rows are contiguous, so one tube is a
# row-group skip away (min/max statistics on tube_id).
SORT_KEYS = {
    "tubes": [("tube_id", "ascending")],
    "tube_frames": [("tube_id", "ascending"), ("frame", "ascending")],
    "frames": [("frame", "ascending")],
    "windows": [("window", "ascending")],
}


# The temporary name of a write (``safe_files.stage``, ``Store._temporary``): ".<name>.tmp-" and 12 hex digits.
LEFTOVER = re.compile(rf"\..+{re.escape(TMP_MARK)}[0-9a-f]{{12}}")
OWN_FOLDERS = (*(e for e in JOB_ENTRIES if e != JOB), RUNNING)  # what a job writes below --out's root


def is_temporary(name: str) -> bool:
    """A file a write has not finished (or a crash left behind)."""
    base = posixpath.basename(name)
    return TMP_MARK in base or base.startswith(".")


class Store:
    """Files of one catalogue, addressed by paths relative to its root (``/`` separated)."""

    def __init__(self, uri: str | Path):
        uri = str(uri)
        if "://" in uri:
            self.fs, root = pafs.FileSystem.from_uri(uri)
        else:
            self.fs, root = pafs.LocalFileSystem(), str(Path(uri).expanduser().resolve())
        self.uri = uri
        self.root = root.rstrip("/") or "/"
        self.local = isinstance(self.fs, pafs.LocalFileSystem)

    # -- paths ---------------------------------------------------------------------

    def full(self, rel: str) -> str:
        """The filesystem path of ``rel`` (for pyarrow calls on ``self.fs``); an InputError
        for a path that could leave the catalogue (absolute, ``..``, ``.`` or empty parts)."""
        if not rel:
            return self.root
        if rel.startswith("/") or any(p in ("", ".", "..") for p in rel.split("/")):
            raise InputError("not a path inside the catalogue", f"{self.root}/{rel}")
        return posixpath.join(self.root, rel)

    # -- queries -------------------------------------------------------------------

    def root_exists(self) -> bool:
        return self.fs.get_file_info(self.root).type == pafs.FileType.Directory

    def exists(self, rel: str) -> bool:
        return self.fs.get_file_info(self.full(rel)).type == pafs.FileType.File

    def anything_at(self, rel: str) -> bool:
        """Whether anything is at ``rel``: a file, a folder, or a FIFO or device (which ``exists`` is not)."""
        return self.fs.get_file_info(self.full(rel)).type != pafs.FileType.NotFound

    def open_stream(self, rel: str) -> pa.NativeFile:
        """``rel`` opened for reading; a local one only when it is a regular file (``files.
        open_regular``: an InputError naming a FIFO, which would block the read for ever)."""
        if self.local:
            return pa.PythonFile(open_regular(self.full(rel)), mode="r")
        return self.fs.open_input_stream(self.full(rel), compression=None)

    def list(self, prefix: str = "", suffix: str = ".parquet") -> list[str]:
        """Finished files under ``prefix`` (recursive) whose names end with ``suffix``, sorted."""
        sel = pafs.FileSelector(self.full(prefix), recursive=True, allow_not_found=True)
        out = []
        for info in self.fs.get_file_info(sel):
            if info.type != pafs.FileType.File or not info.base_name.endswith(suffix) or is_temporary(info.base_name):
                continue
            out.append(posixpath.relpath(info.path, self.root))
        return sorted(out)

    def temporaries(self, folders: Iterable[str] = OWN_FOLDERS) -> list[str]:
        """The temporary files of unfinished writes (``LEFTOVER`` names) in the root and
        under ``folders`` (recursive; default: the job's own), sorted. Plain files only, and
        no link is followed: a folder that is a link is not entered, a link with such a name
        is not one."""
        if not self.root_exists():
            return []
        if not self.local:
            infos = self.fs.get_file_info(pafs.FileSelector(self.root, allow_not_found=True))
            for f in folders:
                infos += self.fs.get_file_info(pafs.FileSelector(self.full(f), recursive=True, allow_not_found=True))
            return sorted(posixpath.relpath(i.path, self.root) for i in infos
                          if i.type == pafs.FileType.File and LEFTOVER.fullmatch(i.base_name))
        out = []
        with os.scandir(self.root) as top:
            out += [e.name for e in top if e.is_file(follow_symlinks=False) and LEFTOVER.fullmatch(e.name)]
        for f in folders:
            start = self.full(f)
            try:
                if not stat.S_ISDIR(os.lstat(start).st_mode):
                    continue  # absent, a file, or a link: none of our folders
            except FileNotFoundError:
                continue
            for where, _, names in os.walk(start, followlinks=False):
                for name in names:
                    path = os.path.join(where, name)
                    if LEFTOVER.fullmatch(name) and stat.S_ISREG(os.lstat(path).st_mode):
                        out.append(posixpath.relpath(path, self.root))
        return sorted(out)

    # -- reads ---------------------------------------------------------------------

    def read_table(self, rel: str, columns: list[str] | None = None) -> pa.Table:
        """One Parquet file as written (no partition columns are added from the path)."""
        try:
            if self.local:
                check_regular(self.full(rel))  # a FIFO would block the read for ever
            with self.fs.open_input_file(self.full(rel)) as f:
                return pq.ParquetFile(f).read(columns=columns)
        except FileNotFoundError:
            raise InputError("catalogue file not found", self.full(rel)) from None
        except (pa.ArrowInvalid, OSError) as e:
            raise InputError(f"cannot read Parquet file: {e}", self.full(rel)) from None

    def read_schema(self, rel: str) -> pa.Schema:
        """One Parquet file's Arrow schema, from its footer alone (errors as ``read_table``'s)."""
        try:
            if self.local:
                check_regular(self.full(rel))
            with self.fs.open_input_file(self.full(rel)) as f:
                return pq.ParquetFile(f).schema_arrow
        except FileNotFoundError:
            raise InputError("catalogue file not found", self.full(rel)) from None
        except (pa.ArrowInvalid, OSError) as e:
            raise InputError(f"cannot read Parquet file: {e}", self.full(rel)) from None

    def read_bytes(self, rel: str) -> bytes:
        try:
            with self.open_stream(rel) as f:
                return f.read()
        except FileNotFoundError:
            raise InputError("catalogue file not found", self.full(rel)) from None

    # -- writes --------------------------------------------------------------------

    def _rel(self, full: str) -> str:
        return posixpath.relpath(full, self.root)

    def _temporary(self, rel: str) -> str:
        folder, name = posixpath.split(self.full(rel))
        self.fs.create_dir(folder, recursive=True)
        return posixpath.join(folder, f".{name}{TMP_MARK}{uuid.uuid4().hex[:12]}")

    def _publish(self, tmp: str, rel: str) -> None:
        if self.local:
            try:
                safe_files.publish(self.root, self._rel(tmp), rel)
            except BaseException:
                self._discard(tmp)
                raise
            return
        try:
            self.fs.move(tmp, self.full(rel))
        except Exception:
            self._discard(tmp)
            raise

    def _stage(self, rel: str, fill) -> str:
        """``fill`` (bytes, or a function writing a binary file) under a temporary name
        beside ``rel``; the temporary file's full path."""
        full = self.full(rel)  # refuses a path that could leave the catalogue
        if self.local:
            return self.full(safe_files.stage(self.root, rel, fill))
        tmp = self._temporary(rel)
        try:
            with self.fs.open_output_stream(tmp, compression=None) as f:
                if isinstance(fill, bytes):
                    f.write(fill)
                else:
                    fill(f)
        except BaseException as e:
            self._discard(tmp)
            if isinstance(e, OSError):
                raise write_error(e, full) from None
            raise
        return tmp

    def write_bytes(self, rel: str, data: bytes) -> None:
        """Atomically create or replace ``rel`` with ``data``."""
        self._publish(self._stage(rel, bytes(data)), rel)

    def stage_table(self, rel: str, table: pa.Table, row_group_rows: int = ROW_GROUP_ROWS) -> str:
        """Write ``table`` under a temporary name beside ``rel``; ``publish`` it later."""
        return self._stage(rel, lambda f: pq.write_table(table, f, compression=COMPRESSION,
                                                         row_group_size=row_group_rows))

    def write_table(self, rel: str, table: pa.Table, row_group_rows: int = ROW_GROUP_ROWS) -> None:
        """Atomically create or replace the Parquet file ``rel``."""
        self._publish(self.stage_table(rel, table, row_group_rows), rel)

    def remove(self, rel: str) -> None:
        """Delete a file; a missing file is fine (removal is idempotent). A link is removed,
        never followed."""
        if self.local:
            safe_files.remove(self.root, self._rel(self.full(rel)))
            return
        try:
            self.fs.delete_file(self.full(rel))
        except FileNotFoundError:
            pass

    def make_dir(self, rel: str) -> None:
        """``mkdir -p`` of ``rel`` (locally without following a link below the root)."""
        if self.local:
            safe_files.make_folder(self.root, self._rel(self.full(rel)))
        else:
            self.fs.create_dir(self.full(rel), recursive=True)

    def move(self, src: str, dst: str) -> None:
        """Move the file or folder ``src`` to ``dst`` (a rename locally: a link moves as a link)."""
        if self.local:
            safe_files.rename(self.root, self._rel(self.full(src)), self._rel(self.full(dst)))
        else:
            self.fs.move(self.full(src), self.full(dst))

    def _discard(self, tmp: str) -> None:
        if self.local:
            safe_files.discard(self.root, self._rel(tmp))
            return
        try:
            self.fs.delete_file(tmp)
        except (FileNotFoundError, OSError):
            pass


def conform(table: str, data: pa.Table, dataset: str, sequence: str) -> pa.Table:
    """``data`` as a compacted file of ``table`` of one sequence: exactly ``file_schema(table)``'s
    columns, types and non-null fields, in its order. ``dataset`` / ``sequence``, when present,
    must hold only the given names; when absent (rows of a part or the manifest), they are
    added holding them. Raises ValueError naming every mismatch."""
    schema = file_schema(table)
    problems = []
    for name, want in zip(PARTITION, (dataset, sequence)):
        if name in data.column_names:
            col = data.column(name)
            values = set(pc.unique(col).to_pylist()) if len(col) else set()
            if values - {want}:
                problems.append(f"column {name} holds {sorted(map(str, values))}, expected only {want!r}")
            data = data.drop_columns([name])
        data = data.append_column(name, pa.array([want] * len(data), pa.string()))
    names = set(data.column_names)
    missing = [f.name for f in schema if f.name not in names]
    extra = sorted(names - set(schema.names))
    if missing:
        problems.append(f"missing columns {missing}")
    if extra:
        problems.append(f"unexpected columns {extra}")
    for f in schema:
        if f.name not in names:
            continue
        col = data.column(f.name)
        if col.type != f.type:
            problems.append(f"column {f.name} has type {col.type}, schema v{SCHEMA_VERSION} says {f.type}")
        elif not f.nullable and col.null_count:
            problems.append(f"column {f.name} has {col.null_count} nulls but is not nullable")
    if problems:
        raise ValueError(f"{table}: does not match catalogue schema v{SCHEMA_VERSION}: " + "; ".join(problems))
    return data.select(schema.names).cast(schema)


def write_sequence(store: Store, table: str, dataset: str, sequence: str, table_data: pa.Table,
                   rows_per_file: int = ROWS_PER_FILE, row_group_rows: int = ROW_GROUP_ROWS) -> list[str]:
    """Replace the compacted files of one table of one sequence; returns the files written.

    The rows are validated against ``file_schema(table)`` (``dataset`` / ``sequence`` added where
    they are absent: ``conform``), sorted (``SORT_KEYS``) and cut
    into ``part-<k>.parquet`` files of at most ``rows_per_file`` rows. All new files are
    written under temporary names first, then moved into place, then files of the
    previous compaction that the new one does not overwrite are removed: at every moment
    the sequence's data is readable (a crash mid-way can leave old and new parts side by
    side, never neither; running the compaction again repairs it). An empty table still
    writes one empty file, so the sequence's columns are known.
    """
    if rows_per_file < 1:
        raise ValueError("rows_per_file must be at least 1")
    data = conform(table, table_data, dataset, sequence)
    if table in SORT_KEYS and len(data):
        data = data.sort_by(SORT_KEYS[table])
    old = set(store.list(catalog_dir(table, dataset, sequence)))
    n_files = max(1, -(-len(data) // rows_per_file))
    staged = []
    try:
        for k in range(n_files):
            rel = catalog_file(table, dataset, sequence, k)
            staged.append((store.stage_table(rel, data.slice(k * rows_per_file, rows_per_file), row_group_rows), rel))
    except BaseException:
        for tmp, _ in staged:
            store._discard(tmp)
        raise
    for tmp, rel in staged:
        store._publish(tmp, rel)
    written = [rel for _, rel in staged]
    for rel in sorted(old - set(written)):
        store.remove(rel)
    return written
