"""Where everything of a catalogue lives under ``--out``: paths only (the records, ``job.json``
among them, are types in ``records.py``).

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
    labels/part-<UTC>-<hex>-<sha256>.parquet                  what people decided about tubes (labels.py): one file
    labels/compact-<UTC>-<hex>-<sha256>.parquet               per write, merged by `mine label --compact`; the
                                                              name carries the sha256 of the file's bytes
    labels/_damaged/<name>                                    label files set aside by `mine submit --verify`
    discovery/tube_descriptors/D/S/descriptors.parquet        derived by `mine describe` (derived.py): a vector per tube,
    discovery/tube_descriptors/D/S.json                       and its marker (recipe, inputs digest, sha256)
    discovery/tube_groups/groups.parquet, …/tube_groups.json  derived by `mine group`: the unknown set's groups
    embeddings/D/S/<model key>/part-<UTC>-<hex>.parquet       tube embeddings of one model (embeddings.py), one file per
                                                              write of `mine embed`
    embeddings/_markers/D/S/<model key>.json                  the size and sha256 of each of those files (what readers trust)

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

The records among them are types (``records.py``: ``JobRecord``, ``ManifestRow``,
``WindowFiles``, ``SequenceMarker``). Every path is built from names checked by
``mining/names.py`` (dataset, sequence, window), so no name can leave ``--out`` or make two
tables share a file; ``job.json``'s names are checked when it is read.
``REPLACED`` holds catalogues a ``--new-run`` moved aside (``pipeline/resume.py``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from mining.errors import InputError
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
# Tables derived from the catalogue (derived.py: descriptors, groups): no job writes them; a
# --new-run moves them aside with the catalogue whose tube ids they name.
DISCOVERY = "discovery"
# Tube embeddings (embeddings.py): `mine embed` writes them, a resubmission never touches them, a
# --new-run moves them aside with the labels (their tube ids may name other objects).
EMBEDDINGS = "embeddings"
EMBEDDING_MARKERS = f"{EMBEDDINGS}/_markers"
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


def embedding_dir(dataset: str, sequence: str, model_key: str) -> str:
    """The folder of one sequence's embedding files of one model (``model_key``: 16 hex digits of its sha256)."""
    origin = "a path under --out"
    return (f"{EMBEDDINGS}/{check_name(dataset, 'dataset', origin)}/{check_name(sequence, 'sequence', origin)}/"
            f"{check_name(model_key, 'model key', origin)}")


def embedding_marker(dataset: str, sequence: str, model_key: str) -> str:
    """The record of one sequence's embedding files of one model: their sizes and sha256."""
    origin = "a path under --out"
    return (f"{EMBEDDING_MARKERS}/{check_name(dataset, 'dataset', origin)}/{check_name(sequence, 'sequence', origin)}/"
            f"{check_name(model_key, 'model key', origin)}.json")
