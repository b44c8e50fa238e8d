"""``mine describe``: a descriptor for every tube, stored per sequence beside the catalogue
(``catalog/derived.py``), recomputed only where it is stale.

A sequence's descriptors are stale when its marker is missing or unreadable, records another
``DESCRIPTOR_VERSION``, or was computed from other inputs: the inputs are the sha256 of the
sequence's compacted ``tubes`` and ``tube_frames`` files (as the sequence's finished marker
records them, or hashed here for a catalogue no job wrote). So describing a catalogue that grew
by a few sequences computes those alone, and a re-stitched sequence is described again.
Descriptors of a sequence the catalogue no longer holds are removed.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from mining.catalog import derived
from mining.catalog.integrity import cached_sha256, vouched_files
from mining.catalog.records import SequenceMarker
from mining.catalog.schema import SCHEMAS
from mining.catalog.store import Store
from mining.discovery.descriptors import DESCRIPTOR_VERSION, DIM, FRAME_COLUMNS, TUBE_COLUMNS, descriptors
from mining.errors import InputError


@dataclass(frozen=True)
class Described:
    """What one ``describe`` did."""

    computed: list[tuple[str, str, int]]  # (dataset, sequence, tubes) described now
    kept: list[tuple[str, str, int]]  # up to date already
    removed: list[tuple[str, str]]  # of sequences no longer in the catalogue


def _sequence_of(rel: str) -> tuple[str, str]:
    """(dataset, sequence) of a compacted file ``catalog/<table>/D/S/…`` (either layout)."""
    p = rel.split("/")
    return p[2].removeprefix("dataset="), p[3].removeprefix("sequence=")


def catalogue_sequences(store: Store) -> dict[tuple[str, str], dict[str, list[str]]]:
    """(dataset, sequence) → {"tubes": files, "tube_frames": files}: the vouched compacted files.
    InputError when a table is damaged (``mine status`` names the files)."""
    v = vouched_files(store)
    if v.damage.get("tubes") or v.damage.get("tube_frames"):
        bad = (v.damage.get("tubes") or v.damage["tube_frames"])[0]
        raise InputError(f"the catalogue is damaged ({bad.reason}): `mine status` lists all; resubmitting recomputes it",
                         store.full(bad.path))
    out: dict[tuple[str, str], dict[str, list[str]]] = {}
    for table in ("tubes", "tube_frames"):
        for rel in v.files[table]:
            out.setdefault(_sequence_of(rel), {"tubes": [], "tube_frames": []})[table].append(rel)
    return {k: s for k, s in out.items() if s["tubes"]}


def inputs_digest(store: Store, dataset: str, sequence: str, files: dict[str, list[str]]) -> str:
    """A digest of the sequence's compacted tubes and tube_frames files (their sha256)."""
    marker = SequenceMarker.load(store, dataset, sequence)
    recorded = marker.files if isinstance(marker, SequenceMarker) and marker.files else {}
    items = []
    for rel in sorted(files["tubes"] + files["tube_frames"]):
        sha = (recorded.get(rel) or {}).get("sha256")
        if sha is None:
            info = store.fs.get_file_info(store.full(rel))
            sha = cached_sha256(store, rel, info.size, info.mtime_ns)
        items.append((rel, sha))
    return hashlib.sha256(json.dumps(items).encode()).hexdigest()


def _read(store: Store, files: list[str], table: str, columns: list[str]) -> pa.Table:
    """``columns`` of the files of ``table``, a column a file lacks (written before it was added:
    ``schema.ADDED_COLUMNS``) as nulls of its type."""
    types = {f.name: f.type for f in SCHEMAS[table]}
    parts = []
    for rel in files:
        t = store.read_table(rel)
        cols = {c: t.column(c) if c in t.column_names else pa.nulls(len(t), types[c]) for c in columns}
        parts.append(pa.table(cols))
    return pa.concat_tables(parts, promote_options="permissive")


def describe_sequence(store: Store, dataset: str, sequence: str, files: dict[str, list[str]]) -> pa.Table:
    """The ``tube_descriptors`` rows of one sequence."""
    tubes = _read(store, files["tubes"], "tubes", [c for c in TUBE_COLUMNS if c not in ("dataset", "sequence")])
    frames = _read(store, files["tube_frames"], "tube_frames", FRAME_COLUMNS)
    vec = descriptors(tubes, frames)
    n = len(tubes)
    return pa.table({
        "tube_id": tubes.column("tube_id").cast(pa.string()), "dataset": pa.array([dataset] * n, pa.string()),
        "sequence": pa.array([sequence] * n, pa.string()), "version": pa.array([DESCRIPTOR_VERSION] * n, pa.string()),
        "vector": pa.FixedSizeListArray.from_arrays(pa.array(vec.ravel(), pa.float32()), DIM),
    }, schema=derived.descriptor_schema(DIM)).sort_by("tube_id")


def describe(store: Store, force: bool = False) -> Described:
    """Describe every stale sequence of the catalogue (every one with ``force``)."""
    sequences = catalogue_sequences(store)
    markers = derived.descriptor_markers(store)
    computed, kept = [], []
    for (dataset, sequence), files in sorted(sequences.items()):
        key = inputs_digest(store, dataset, sequence, files)
        m = markers.get((dataset, sequence))
        if (not force and m is not None and m.version == DESCRIPTOR_VERSION and m.inputs == key
                and derived.checks_out(store, m) is None):
            kept.append((dataset, sequence, m.rows))
            continue
        rows = describe_sequence(store, dataset, sequence, files)
        derived.write_derived(store, derived.descriptors_file(dataset, sequence),
                              derived.descriptors_marker(dataset, sequence), rows, DESCRIPTOR_VERSION, key)
        computed.append((dataset, sequence, rows.num_rows))
    removed = []
    for dataset, sequence in sorted(set(markers) - set(sequences)):
        store.remove(derived.descriptors_marker(dataset, sequence))  # the marker first: its file is then unvouched
        store.remove(derived.descriptors_file(dataset, sequence))
        removed.append((dataset, sequence))
    return Described(computed, kept, removed)


def load_descriptors(store: Store) -> tuple[pa.Table, np.ndarray]:
    """(tube_id, dataset, sequence of every described tube; their (n, DIM) vectors), in id order,
    from the files the markers vouch for at the current ``DESCRIPTOR_VERSION``."""
    files, damage = derived.vouched(store)
    bad = [(f, why) for f, why in damage if f.split("/")[1] == derived.DESCRIPTORS]
    if bad:
        raise InputError(f"stored descriptors are damaged ({bad[0][1]}): `mine describe` recomputes them",
                         store.full(bad[0][0]))
    parts = [store.read_table(f) for f in files[derived.DESCRIPTORS]]
    parts = [p for p in parts if len(p) and p.column("version")[0].as_py() == DESCRIPTOR_VERSION]
    if not parts:
        return derived.descriptor_schema(DIM).empty_table().select(["tube_id", "dataset", "sequence"]), \
            np.zeros((0, DIM), np.float32)
    table = pa.concat_tables(parts).sort_by("tube_id")
    vec = np.asarray(table.column("vector").combine_chunks().flatten().to_numpy(), np.float32).reshape(-1, DIM)
    return table.select(["tube_id", "dataset", "sequence"]), vec
