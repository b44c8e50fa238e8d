"""A read-only DuckDB over a catalogue: the four tables and the views of schemas/v3.

Tables (all columns of ``schema.SCHEMAS``; ``dataset`` / ``sequence`` as VARCHAR, so "0005"
stays "0005"):

* ``tubes``, ``tube_frames``, ``frames`` — ``OUT/catalog/<table>/D/S/*.parquet``, both columns
  in the files (schema v3); a catalogue before v3 keeps them in hive folders
  (``OUT/catalog/<table>/dataset=D/sequence=S/``), read back from the folder names: each file
  is read by its layout (``layout.catalog_layout``), so old catalogues stay readable
* ``windows`` — the manifest, ``OUT/manifest/dataset=D/sequence=S/*.parquet`` (hive folders)

The compacted tables read exactly the files the finished markers vouch for
(``integrity.vouched_files``), never a glob: a sequence whose first stitch has not
finished, a folder no marker records and a file its marker does not list are not served
(the provisional views show an unstitched sequence's windows). Each vouched file's size
and sha256 are checked against its marker once per process (cached by path, size and
mtime), so a flipped bit is an error naming the file, never a value. A catalogue that no
mining job wrote (no marker, a job.json planning no window: ``store.write_sequence``
alone) is read as listed, unchecked.

``tube_embeddings`` (``embeddings.py``, written by ``mine embed``) reads the embedding files their
markers vouch for (size and sha256, as above), the newest row per tube and model, of the tubes
``tubes`` holds; a file that does not check out makes it fail naming the file.

A table without files is an empty view with the right columns, so queries work on a
fresh catalogue. A table with a damaged file (missing, truncated, of another size or
sha256 than its sequence's finished marker records, or whose Parquet footer does not
read: ``integrity.py``) is a view that fails every query that reads it, naming the file;
the other tables answer as usual. A local catalogue is read by DuckDB's own Parquet reader (projection
and row-group pushdown); any other pyarrow filesystem through registered pyarrow datasets.

Read-only, in two layers: the connection may touch no file but those its views read
(``enable_external_access`` off, configuration locked): each compacted file a marker vouches
for, by its exact path (``allowed_paths``: checked by sha256 above, so a damaged or unvouched
file under ``catalog/`` is refused to DuckDB's file functions — ``read_parquet``, ``glob``,
``read_text`` … — in a user's SQL as it is to the named tables), and the ``manifest`` and
``_parts`` folders, which the ``windows`` table and the provisional views read as listed
(``allowed_directories``); nothing else under ``--out`` (``job.json``, ``_replaced/``) or outside it.
``file_refused`` says which rule refused a file. ``check_read_only`` admits only statements
that read (SELECT, and the DESCRIBE / SHOW / SUMMARIZE / FROM forms DuckDB parses as SELECT;
EXPLAIN without ANALYZE).

DuckDB allows its temporary (spill) folder as well, by default ``<cwd>/.tmp``: the
connection spills into a private folder of its own instead (made by ``mkdtemp``, mode
0700, removed with the connection), so no file of the caller's becomes readable.
``memory_limit`` and ``threads`` bound what one query may take (``mine query`` flags).
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
import weakref
from dataclasses import dataclass
from pathlib import Path

import duckdb
import pyarrow as pa
import pyarrow.dataset as ds

from mining.catalog import derived
from mining.catalog.embeddings import EMBEDDING_SCHEMA, vouched_embeddings
from mining.catalog.integrity import Damage, check_versions, unreadable_parquet, vouched_files
from mining.catalog.labels import LABEL_SCHEMA, DamagedLabels, label_files, read_label_files
from mining.catalog.layout import MANIFEST, PART_SUFFIX, PARTS, TABLE_DIRS, catalog_layout
from mining.catalog.schema import (ADDED_COLUMNS, PARTITION, SCHEMAS, column_doc, file_schema, hive_file_schema,
                                   part_schema)
from mining.catalog.records import check_job_names
from mining.catalog.store import Store
from mining.errors import InputError

VIEWS_SQL = Path(__file__).with_name("views.sql")  # package data; schemas/v2/views.sql is its published copy
READ_STATEMENTS = {duckdb.StatementType.SELECT}


class ReadOnlyError(InputError):
    """A statement that would change something, given to the read-only catalogue."""


def sql_string(s: str) -> str:
    """``s`` as a SQL string literal: quoted, with its quotes doubled (DuckDB's own escaping)."""
    return "'" + s.replace("'", "''") + "'"


def _as_read(schema: pa.Schema) -> pa.Schema:
    """Types as DuckDB's Parquet reader returns them: fixed-size lists become lists
    (Parquet stores both alike), so every path gives the same column types."""
    def plain(t: pa.DataType) -> pa.DataType:
        return pa.list_(t.value_type) if pa.types.is_fixed_size_list(t) else t
    return pa.schema([f.with_type(plain(f.type)) for f in schema])


def _damaged_view(con: duckdb.DuckDBPyConnection, store: Store, table: str, damage: list[Damage],
                  schema: pa.Schema | None = None, msg: str | None = None) -> None:
    """``table`` as a view with its columns that raises, naming the damaged files, when read."""
    files = "; ".join(f"{store.full(d.path)} ({d.reason})" for d in damage[:5])
    more = f" and {len(damage) - 5} more" if len(damage) > 5 else ""
    msg = msg or (f"table {table} is damaged: {files}{more}. `mine status --out {store.uri}` lists all; `mine "
                  "submit --verify` repairs them (the job resubmitted); the other tables can be queried")
    # Every column is the error, and so is the filter: the optimizer can prune neither, so
    # any query that reads a row of the table (joins, counts, views over it) raises.
    con.register(f"_schema_{table}", _as_read(SCHEMAS[table] if schema is None else schema).empty_table())
    types = con.sql(f"DESCRIBE _schema_{table}").fetchall()
    con.unregister(f"_schema_{table}")
    err = f"error({sql_string(msg)})"
    cols = ", ".join(f'CAST({err} AS {t}) AS "{n}"' for n, t, *_ in types)
    con.execute(f"CREATE VIEW {table} AS SELECT {cols} FROM range(1) WHERE {err}")


def _base_view(con: duckdb.DuckDBPyConnection, store: Store, table: str, native: bool,
               damage: list[Damage] | None = None, files: list[str] | None = None) -> None:
    if damage:
        _damaged_view(con, store, table, damage)
        return
    try:
        _files_view(con, store, table, native, files)
    except (duckdb.Error, pa.ArrowInvalid, OSError) as e:
        # A file no checksum vouches for (a manifest row, an unmarked catalogue's file)
        # broke the view: find which, and make this table fail alone.
        bad = unreadable_parquet(store, store.list(TABLE_DIRS[table]) if files is None else files)
        damage = [Damage(rel, reason, "") for rel, reason in bad] or [Damage(TABLE_DIRS[table], str(e), "")]
        con.execute(f"DROP VIEW IF EXISTS {table}")
        _damaged_view(con, store, table, damage)


def _duck_type(con: duckdb.DuckDBPyConnection, t: pa.DataType) -> str:
    """The DuckDB name of Arrow type ``t``."""
    con.register("_type_probe", pa.schema([pa.field("x", t)]).empty_table())
    try:
        return con.execute("DESCRIBE _type_probe").fetchone()[1]
    finally:
        con.unregister("_type_probe")


def _folder_view(con: duckdb.DuckDBPyConnection, store: Store, name: str, folder: str, suffix: str,
                 schema: pa.Schema, cols: str, native: bool, files: list[str] | None = None,
                 added: frozenset[str] = frozenset(), plain: pa.Schema | None = None) -> None:
    """View ``name`` over the hive-named files ``folder/*/*/*<suffix>`` of ``schema`` (partition
    columns last, read from the folder names), or over exactly ``files`` (relative paths under
    ``folder``) when given: each by its layout (``layout.catalog_layout``), a hive-named file
    as above and a plain one (schema v3, ``plain``: its own ``dataset`` / ``sequence``) as it
    is, both in one view when a catalogue holds both. Empty when there are no files. DuckDB's
    own Parquet reader, or registered pyarrow datasets (``native`` False)."""
    if not (store.list(folder, suffix) if files is None else files):
        con.register(f"_empty_{name}", _as_read(schema).empty_table())
        con.execute(f"CREATE VIEW {name} AS SELECT {cols} FROM _empty_{name}")
        return
    groups: dict[str, list[str] | None] = {"hive": None} if files is None else {}
    for f in files or []:
        groups.setdefault("plain" if plain is not None and catalog_layout(f) == "plain" else "hive", []).append(f)
    selects = []
    for layout, group in sorted(groups.items()):
        hive = layout == "hive"
        if native:
            what = (sql_string(f"{store.full(folder)}/*/*/*{suffix}") if group is None
                    else "[" + ", ".join(sql_string(store.full(f)) for f in group) + "]")
            # Explicit either way: a folder above the catalogue named "k=v" must not add a column.
            opts = ("hive_partitioning = true, hive_types = {'dataset': 'VARCHAR', 'sequence': 'VARCHAR'}" if hive
                    else "hive_partitioning = false")
            picked = cols
            if added:  # files written before a nullable column was added (ADDED_COLUMNS)
                opts += ", union_by_name = true"
                have = {r[0] for r in con.execute(f"DESCRIBE SELECT * FROM read_parquet({what}, {opts})").fetchall()}
                types = {f.name: f.type for f in schema}
                names = [n.strip('"') for n in cols.split(", ")]
                picked = ", ".join(f'"{n}"' if n in have or n not in added
                                   else f'CAST(NULL AS {_duck_type(con, types[n])}) AS "{n}"' for n in names)
            selects.append(f"SELECT {picked} FROM read_parquet({what}, {opts})")
            continue
        source = store.full(folder) if group is None else [store.full(f) for f in group]
        if hive:
            part = pa.schema([pa.field(n, pa.string()) for n in PARTITION])
            dset = ds.dataset(source, filesystem=store.fs, format="parquet", partition_base_dir=store.full(folder),
                              partitioning=ds.partitioning(part, flavor="hive"), schema=_as_read(schema))
        else:
            dset = ds.dataset(source, filesystem=store.fs, format="parquet", schema=_as_read(plain))
        con.register(f"_arrow_{name}_{layout}", dset)
        selects.append(f"SELECT {cols} FROM _arrow_{name}_{layout}")
    con.execute(f"CREATE VIEW {name} AS " + " UNION ALL ".join(selects))


def _with_partition(schema: pa.Schema) -> pa.Schema:
    return pa.schema(list(schema) + [pa.field(n, pa.string()) for n in PARTITION])


def _files_view(con: duckdb.DuckDBPyConnection, store: Store, table: str, native: bool,
                files: list[str] | None = None) -> None:
    cols = ", ".join(f'"{n}"' for n in SCHEMAS[table].names)
    _folder_view(con, store, table, TABLE_DIRS[table], ".parquet", _with_partition(hive_file_schema(table)), cols,
                 native, files, ADDED_COLUMNS.get(table, frozenset()), file_schema(table))


PROVISIONAL = ("tubes", "tube_frames")  # the part tables the provisional views read


def _part_view(con: duckdb.DuckDBPyConnection, store: Store, table: str, native: bool) -> None:
    """``_part_<table>``: the per-window parts of ``table`` (partition columns included), for
    the provisional views; empty when there are none. A part that cannot be read makes the
    provisional views fail naming it, never the final tables."""
    _folder_view(con, store, f"_part_{table}", f"{PARTS}/{table}", PART_SUFFIX,
                 _with_partition(part_schema(table)), "*", native)


@dataclass(frozen=True)
class _Readable:
    """What a connection's SQL may read (``connect``), to say why a file was refused."""

    store: Store
    vouched: frozenset[str]  # compacted files that checked out (relative paths)
    damage: dict[str, Damage]  # compacted files that did not, by relative path
    folders: tuple[str, ...]  # folders read as listed (relative)


_READABLE: weakref.WeakKeyDictionary[duckdb.DuckDBPyConnection, _Readable] = weakref.WeakKeyDictionary()
_REFUSED = re.compile(r'Cannot access (?:file|directory) "(.*)"')


def file_refused(con: duckdb.DuckDBPyConnection, err: duckdb.PermissionException) -> InputError:
    """The error for a file DuckDB refused to ``con``'s SQL: damaged, not vouched for, or
    outside the catalogue, naming the file."""
    m, r = _REFUSED.search(str(err)), _READABLE.get(con)
    if m is None or r is None:
        return InputError(str(err))
    path = m.group(1)
    full = os.path.realpath(os.path.join(os.getcwd(), path))  # relative: to the caller's folder, as DuckDB reads it
    root = r.store.root  # resolved (Store)
    if full != root and not full.startswith(root + "/"):
        return InputError(f"outside the catalogue {root}: access to any other file is disabled", path)
    rel = os.path.relpath(full, root)
    if rel in r.vouched:  # a vouched file by another spelling (a link on the way): DuckDB matches exact paths
        return InputError(f"the catalogue's files are read by their own paths: read {r.store.full(rel)}", path)
    if rel in r.damage:
        return InputError(f"a damaged catalogue file ({r.damage[rel].reason}) may not be read: a query reads a "
                          "compacted file only when its size and sha256 check out against its sequence's marker. "
                          f"`mine status --out {r.store.uri}` lists the damage; resubmitting the job recomputes it",
                          path)
    return InputError(
        "not a file this catalogue vouches for: a query's file functions (read_parquet, glob, read_text, …) read "
        "only the compacted files the sequence markers vouch for (each checked by sha256, named by its exact path: "
        f"no folder, no pattern) and the {' and '.join(f + '/' for f in r.folders)} folders; access to any other "
        "file is disabled. Query the tables (tubes, tube_frames, frames, windows) instead", path)


def _comment_columns(con: duckdb.DuckDBPyConnection) -> None:
    """Each base table's column descriptions and units (schema.py, the one source) as DuckDB comments."""
    for table in SCHEMAS:
        have = {r[0] for r in con.execute("SELECT column_name FROM duckdb_columns() WHERE table_name = ?", [table]).fetchall()}
        for f in SCHEMAS[table]:
            desc, unit = column_doc(table, f.name)
            text = f"{desc} (unit: {unit})" if unit else desc
            if text and f.name in have:
                con.execute(f'COMMENT ON COLUMN {table}."{f.name}" IS {sql_string(text)}')


def refresh_labels(con: duckdb.DuckDBPyConnection, store: Store) -> list[str]:
    """(Re)register the ``labels`` table: every label event under ``OUT/labels`` (``labels.py``),
    read into memory (label files are small, and a viewer reads new ones as they appear); a file
    that does not read makes ``labels`` (and the views over it) fail naming it, and nothing else.
    The label files read."""
    try:
        con.unregister("labels")
    except duckdb.Error:
        pass
    try:
        files, table = read_label_files(store)
    except InputError as e:
        how = "; " if isinstance(e, DamagedLabels) else ". Move that file aside; "  # damage says its own repair
        con.execute("DROP VIEW IF EXISTS labels")
        _damaged_view(con, store, "labels", [], LABEL_SCHEMA,
                      f"the labels cannot be read: {e}{how}the mined tables can be queried")
        return label_files(store)
    con.execute("DROP VIEW IF EXISTS labels")
    con.register("labels", table)
    return files


def register_derived(con: duckdb.DuckDBPyConnection, store: Store) -> None:
    """(Re)register ``tube_descriptors`` and ``tube_groups`` (``derived.py``): the files their
    markers vouch for, read through pyarrow datasets (lazily: a query reads the columns it names);
    empty tables of the right columns where discovery has not run. A damaged file makes its
    table fail naming it, and nothing else."""
    files, damage = derived.vouched(store)
    empty = {derived.DESCRIPTORS: pa.schema([f.with_type(pa.list_(pa.float32())) if f.name == "vector" else f
                                            for f in derived.descriptor_schema(1)]),
             derived.GROUPS: derived.GROUP_SCHEMA}
    for table in derived.DERIVED_TABLES:
        for drop in (f"DROP VIEW IF EXISTS {table}", None):
            try:
                con.execute(drop) if drop else con.unregister(table)
            except duckdb.Error:
                pass
        bad = [Damage(rel, why, "mine describe / mine group") for rel, why in damage if rel.split("/")[1] == table]
        if bad:
            _damaged_view(con, store, table, bad, empty[table],
                          f"table {table} is damaged: {store.full(bad[0].path)} ({bad[0].reason}); "
                          f"`mine {'describe' if table == derived.DESCRIPTORS else 'group'} --out {store.uri}` recomputes it")
        elif files[table]:
            con.register(table, ds.dataset([store.full(f) for f in files[table]], filesystem=store.fs, format="parquet"))
        else:
            con.register(table, empty[table].empty_table())


def _embedding_view(con: duckdb.DuckDBPyConnection, store: Store, native: bool) -> list[str]:
    """The view ``tube_embeddings`` (``embeddings.py``): the newest row per tube and model over the
    embedding files their markers vouch for, of the tubes the catalogue holds; a view that fails
    naming the file where one does not check out. The files it reads."""
    files, damage = vouched_embeddings(store)
    if damage:
        _damaged_view(con, store, "tube_embeddings", damage, EMBEDDING_SCHEMA,
                      "table tube_embeddings is damaged: " + "; ".join(f"{store.full(d.path)} ({d.reason})"
                                                               for d in damage[:5])
                      + ". `mine embed` with the same model embeds their tubes again; the other tables can be queried")
        return []
    cols = ", ".join(f'"{n}"' for n in EMBEDDING_SCHEMA.names)
    if not files:
        con.register("_empty_tube_embeddings", _as_read(EMBEDDING_SCHEMA).empty_table())
        source = "_empty_tube_embeddings"
    elif native:
        source = f"read_parquet([{', '.join(sql_string(store.full(f)) for f in files)}], hive_partitioning = false)"
    else:
        con.register("_arrow_tube_embeddings", ds.dataset([store.full(f) for f in files], filesystem=store.fs,
                                                          format="parquet", schema=_as_read(EMBEDDING_SCHEMA)))
        source = "_arrow_tube_embeddings"
    # Newest per tube and model: a tube embedded again (its views changed) keeps its latest vector.
    con.execute(f"CREATE VIEW tube_embeddings AS SELECT {cols} FROM {source} AS e "
                "WHERE EXISTS (SELECT 1 FROM tubes AS t WHERE t.dataset = e.dataset AND t.sequence = e.sequence "
                "AND t.tube_id = e.tube_id) "
                "QUALIFY row_number() OVER (PARTITION BY dataset, sequence, tube_id, model_sha256 "
                "ORDER BY embedded_at DESC) = 1")
    return files


def connect(out: str | Path, native: bool | None = None, memory_limit: str | None = None,
            threads: int | None = None, verify: bool = True) -> duckdb.DuckDBPyConnection:
    """An in-memory DuckDB with the catalogue's tables and views (see module docstring).

    ``native`` chooses DuckDB's Parquet reader (default for a local catalogue) over
    pyarrow datasets (default for other filesystems). ``memory_limit`` (e.g. "2GB") and
    ``threads`` limit queries (default: DuckDB's). ``verify`` (default) checks the sha256 of
    every compacted file against its marker, once per process per file (``integrity.
    vouched_files``; False: sizes only, for measuring its cost). Raises InputError when
    ``out`` is not a catalogue folder, or for a limit DuckDB does not accept, and
    ``versions.SchemaVersionError`` for a catalogue of a schema version this code does not
    read (``integrity.check_versions``).
    """
    store = Store(out)
    if not store.root_exists():
        raise InputError("catalogue folder not found", out)
    if not VIEWS_SQL.is_file():
        raise InputError("the catalogue views are missing: a broken install (views.sql ships inside the mining.catalog package)", VIEWS_SQL)
    native = store.local if native is None else native
    if native and not store.local:
        raise InputError("DuckDB's own reader needs a local catalogue; use pyarrow datasets", out)
    con = duckdb.connect(":memory:")
    spill = tempfile.mkdtemp(prefix="tube-miner-duckdb-")  # private (0700); DuckDB makes and removes spill/ in it
    weakref.finalize(con, shutil.rmtree, spill, True)
    con.execute(f"SET temp_directory = {sql_string(spill + '/spill')}")
    try:
        if memory_limit is not None:
            con.execute(f"SET memory_limit = {sql_string(memory_limit)}")
        if threads is not None:
            con.execute(f"SET threads = {int(threads)}")
    except duckdb.Error as e:
        con.close()
        raise InputError(f"DuckDB refuses the query limits (memory {memory_limit!r}, threads {threads!r}): {e}") from None
    try:
        check_versions(store)  # a catalogue of a schema this code does not read is refused whole
        check_job_names(store)  # so is one holding a name an older rule allowed (names.py)
        vouched = vouched_files(store, verify=verify)
    except InputError:
        con.close()
        raise
    for table in SCHEMAS:  # windows: the manifest's rows (the live status), as listed
        _base_view(con, store, table, native, vouched.damage.get(table),
                   None if table == "windows" else vouched.files[table])
    for table in PROVISIONAL:
        _part_view(con, store, table, native)
    refresh_labels(con, store)
    register_derived(con, store)
    con.execute(VIEWS_SQL.read_text())
    embedded = _embedding_view(con, store, native)
    _comment_columns(con)
    # From here on: no file access but what the views read, and no way to turn that back on.
    folders = (MANIFEST, PARTS)
    paths = sorted({store.full(f) for t in SCHEMAS for f in vouched.files[t]} | {store.full(f) for f in embedded}) \
        if native else []
    dirs = [store.full(f) + "/" for f in folders] if native else []
    con.execute(f"SET allowed_paths = [{', '.join(map(sql_string, paths))}]")
    con.execute(f"SET allowed_directories = [{', '.join(map(sql_string, dirs))}]")
    _READABLE[con] = _Readable(store, frozenset([*(f for t in SCHEMAS for f in vouched.files[t]), *embedded]),
                               {d.path: d for ds_ in vouched.damage.values() for d in ds_}, folders)
    con.execute("SET enable_external_access = false")
    con.execute("SET autoinstall_known_extensions = false")
    con.execute("SET autoload_known_extensions = false")
    con.execute("SET lock_configuration = true")
    return con


def check_read_only(sql: str) -> None:
    """Raise ReadOnlyError unless every statement in ``sql`` only reads."""
    try:
        statements = duckdb.extract_statements(sql)
    except duckdb.Error as e:
        raise InputError(f"SQL does not parse: {e}") from None
    if not statements:
        raise InputError("no SQL statement given")
    for st in statements:
        if st.type == duckdb.StatementType.EXPLAIN:
            text = st.query.strip()
            if re.match(r"(?is)explain\s+analy[sz]e\b", text):
                raise ReadOnlyError("the catalogue is read-only: EXPLAIN ANALYZE runs its statement (plain EXPLAIN is allowed)")
            check_read_only(re.sub(r"(?is)^explain\s+", "", text))
            continue
        if st.type not in READ_STATEMENTS:
            raise ReadOnlyError(f"the catalogue is read-only: {st.type.name} statements are not allowed "
                                f"(only SELECT, WITH, FROM, DESCRIBE, SHOW, SUMMARIZE, EXPLAIN)")


def execute_read_only(con: duckdb.DuckDBPyConnection, sql: str) -> duckdb.DuckDBPyRelation | None:
    """Check ``sql`` and run it; the relation of its last statement."""
    check_read_only(sql)
    rel = None
    for st in duckdb.extract_statements(sql):
        rel = con.sql(st.query)
    return rel
