"""Tube embeddings: one vector per tube and model, kept beside the catalogue (``mine embed``).

The rows (``EMBEDDING_SCHEMA``) are written by ``mining/discovery/embed_run.py`` and read as the
DuckDB view ``tube_embeddings`` (``views.connect``). Files, per dataset, sequence and model
(``model key``: the first 16 hex digits of the model file's sha256, its version)::

    embeddings/D/S/<model key>/part-<UTC>-<hex>.parquet     one file per write (a batch of tubes)
    embeddings/_markers/D/S/<model key>.json                the size and sha256 of each of those files

* Every file is written atomically (``Store.write_table``) under a name of its own, then recorded
  in its marker (written atomically too); only files a marker records, and whose size and sha256
  check out, are read. A kill between the two leaves a file no marker records: never read, and
  removed by the next ``mine embed`` of that sequence and model (``sweep``). So a killed run
  keeps every batch it recorded and resumes after it.
* A file that no longer checks out (or a marker that does not read) makes the ``tube_embeddings``
  view fail naming it; ``mine embed`` leaves such a file out of the marker and embeds its tubes again.
* A tube embedded again (its best views changed, or other settings) gets a newer row; readers
  take the newest row per (tube, model) (``embedded_at``).
* A resubmission of the job never touches ``embeddings/`` (not one of ``layout.JOB_ENTRIES``);
  ``--new-run`` moves it aside with the catalogue and the labels (``pipeline/resume.py``).
"""

from __future__ import annotations

import json
import posixpath
import time
import uuid
from dataclasses import dataclass

import pyarrow as pa
import pyarrow.fs as pafs

from mining.catalog.integrity import Damage, cached_sha256, digest
from mining.catalog.layout import EMBEDDING_MARKERS, embedding_dir, embedding_marker
from mining.catalog.store import Store
from mining.errors import InputError

MARKER_VERSION = 1  # the marker's format; a newer one is refused by name
MODEL_KEY_HEX = 16  # ours: hex digits of the model's sha256 in a folder name (64 bits: no two models meet)

EMBEDDING_SCHEMA = pa.schema([
    pa.field("tube_id", pa.string(), False),
    pa.field("dataset", pa.string(), False),
    pa.field("sequence", pa.string(), False),
    pa.field("model", pa.string(), False),  # the ONNX file's name (as given to mine embed --model)
    pa.field("model_sha256", pa.string(), False),  # sha256 of the ONNX file's bytes: the model's version
    pa.field("preset", pa.string(), False),  # the normalisation preset (clip, dino, imagenet)
    pa.field("settings", pa.string(), False),  # hash of everything else that makes the vector (views, margin, input size)
    pa.field("views_key", pa.string(), False),  # hash of the views' frames, boxes and masks: a changed tube re-embeds
    pa.field("n_views", pa.int16(), False),  # how many crops were averaged
    pa.field("view_frames", pa.list_(pa.int32()), False),  # their frames (the source's indices)
    pa.field("dim", pa.int32(), False),  # D, the vector's length
    pa.field("vector", pa.list_(pa.float32()), False),  # the tube's vector, L2 norm 1
    # When it was embedded, UTC, a plain timestamp as the labels' (every reader reads it without a zone library).
    pa.field("embedded_at", pa.timestamp("ms"), False),
])


def model_key(model_sha256: str) -> str:
    """The folder name of a model's files: the first ``MODEL_KEY_HEX`` hex digits of its sha256."""
    return model_sha256[:MODEL_KEY_HEX]


@dataclass
class EmbeddingMarker:
    """The record of one sequence's embedding files of one model."""

    dataset: str
    sequence: str
    model: str
    model_sha256: str
    files: dict[str, dict]  # relative path → {"size", "sha256"}

    @property
    def path(self) -> str:
        return embedding_marker(self.dataset, self.sequence, model_key(self.model_sha256))

    def save(self, store: Store) -> None:
        body = {"version": MARKER_VERSION, "dataset": self.dataset, "sequence": self.sequence, "model": self.model,
                "model_sha256": self.model_sha256, "files": self.files}
        store.write_bytes(self.path, (json.dumps(body, indent=1, sort_keys=True) + "\n").encode())


def load_marker(store: Store, rel: str) -> EmbeddingMarker:
    """The marker at ``rel``; an InputError naming it when it does not read as one."""
    try:
        d = json.loads(store.read_bytes(rel))
    except (ValueError, RecursionError, OSError) as e:
        raise InputError(f"embedding marker does not read: {e}", store.full(rel)) from None
    if not isinstance(d, dict) or not isinstance(d.get("files"), dict):
        raise InputError("embedding marker does not read: not an object with files", store.full(rel))
    if d.get("version") != MARKER_VERSION:
        raise InputError(f"embedding marker of version {d.get('version')!r}; this code reads {MARKER_VERSION}",
                         store.full(rel))
    try:
        marker = EmbeddingMarker(str(d["dataset"]), str(d["sequence"]), str(d["model"]), str(d["model_sha256"]),
                                 {str(k): dict(v) for k, v in d["files"].items()})
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"embedding marker does not read: {e}", store.full(rel)) from None
    if marker.path != rel:  # a marker speaks only for its own folder
        raise InputError(f"embedding marker names {marker.dataset}/{marker.sequence}/{marker.model_sha256[:16]}, "
                         f"not its own place", store.full(rel))
    folder = embedding_dir(marker.dataset, marker.sequence, model_key(marker.model_sha256)) + "/"
    if any(not f.startswith(folder) or "/" in f[len(folder):] for f in marker.files):
        raise InputError("embedding marker records a file outside its folder", store.full(rel))
    return marker


def _check(store: Store, marker: EmbeddingMarker) -> tuple[list[str], list[Damage]]:
    """(files that check out by size and sha256, damaged ones) of one marker."""
    good, bad = [], []
    owner = f"embeddings of {marker.dataset}/{marker.sequence} by {marker.model}"
    for rel in sorted(marker.files):
        want = marker.files[rel]
        info = store.fs.get_file_info(store.full(rel))
        if info.type != pafs.FileType.File:
            bad.append(Damage(rel, "missing", owner))
        elif info.size != want.get("size"):
            bad.append(Damage(rel, f"{info.size} bytes, {want.get('size')} recorded", owner))
        elif cached_sha256(store, rel, info.size, info.mtime_ns) != want.get("sha256"):
            bad.append(Damage(rel, "sha256 does not match its marker's: damaged", owner))
        else:
            good.append(rel)
    return good, bad


def vouched_embeddings(store: Store) -> tuple[list[str], list[Damage]]:
    """(every embedding file a marker vouches for, the damage: files that do not check out and
    markers that do not read), over the whole catalogue."""
    files, damage = [], []
    for rel in store.list(EMBEDDING_MARKERS, ".json"):
        try:
            marker = load_marker(store, rel)
        except InputError as e:
            damage.append(Damage(rel, e.reason, "mine embed"))
            continue
        good, bad = _check(store, marker)
        files += good
        damage += bad
    return sorted(files), damage


KEY_COLUMNS = ["tube_id", "settings", "views_key"]  # what says whether a tube's vector is already stored


def existing(store: Store, dataset: str, sequence: str, model: str,
             model_sha256: str) -> tuple[EmbeddingMarker, pa.Table]:
    """(the marker of one sequence's embeddings by one model, keeping only the files that check
    out; their rows' ``KEY_COLUMNS``). A marker that does not read starts afresh: its files are
    embedded again."""
    rel = embedding_marker(dataset, sequence, model_key(model_sha256))
    marker = EmbeddingMarker(dataset, sequence, model, model_sha256, {})
    if store.exists(rel):
        try:
            marker = load_marker(store, rel)
        except InputError:
            pass
    good, _ = _check(store, marker)
    marker.files = {r: marker.files[r] for r in good}
    keys = pa.schema([EMBEDDING_SCHEMA.field(c) for c in KEY_COLUMNS])
    tables = [store.read_table(r, KEY_COLUMNS).cast(keys) for r in good]
    return marker, pa.concat_tables(tables) if tables else keys.empty_table()


def sweep(store: Store, marker: EmbeddingMarker) -> list[str]:
    """Remove the files in a marker's folder it does not record (a killed write's, a damaged
    one's) and the temporaries a kill left beside them or the marker: under the writer lock, by
    the one process that writes these. The files removed."""
    folder = embedding_dir(marker.dataset, marker.sequence, model_key(marker.model_sha256))
    gone = [r for r in store.list(folder, "") if r not in marker.files and posixpath.dirname(r) == folder]
    beside = (folder, posixpath.dirname(marker.path))
    gone += [r for r in store.temporaries(beside) if posixpath.dirname(r) in beside]
    for r in gone:
        store.remove(r)
    return gone


def append(store: Store, marker: EmbeddingMarker, rows: pa.Table) -> str:
    """Write ``rows`` as a new file of ``marker``'s folder, then record it in the marker; the file."""
    folder = embedding_dir(marker.dataset, marker.sequence, model_key(marker.model_sha256))
    rel = f"{folder}/part-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}-{uuid.uuid4().hex[:12]}.parquet"
    store.write_table(rel, rows.cast(EMBEDDING_SCHEMA))
    marker.files[rel] = digest(store, rel)
    marker.save(store)  # only now is the file read
    return rel
