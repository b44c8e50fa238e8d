"""Tables derived from the mined catalogue by discovery (``mining/discovery/``): the tube
descriptors and the groups of the unknown set. Paths, schemas, atomic writes with a marker, and
the files a reader may trust; what the rows hold is ``discovery/``'s.

    discovery/tube_descriptors/D/S/descriptors.parquet   one row per tube of the sequence
    discovery/tube_descriptors/D/S.json                  its marker (DerivedMarker)
    discovery/tube_groups/groups.parquet                 one row per unknown tube grouped
    discovery/tube_groups.json                           its marker

Each data file is written under a temporary name and moved into place (``Store.write_table``),
then its marker: the recipe's ``version``, the ``inputs`` it was computed from (a digest of the
sequence's compacted ``tubes`` and ``tube_frames`` files, or of the descriptors grouped) and the
size and sha256 of the file. A reader serves a file only when its marker records it and its size
and sha256 agree (``vouched``); a writer recomputes a sequence only when the version or the
inputs changed, so re-running over a grown catalogue touches the new sequences alone.

Derived, not mined: a resubmission leaves ``discovery/`` alone (the inputs digests say what is
stale), and ``mine submit --new-run`` moves it aside with the catalogue whose tube ids it names.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import pyarrow as pa
import pyarrow.fs as pafs

from mining.catalog.integrity import cached_sha256, digest
from mining.catalog.layout import DISCOVERY
from mining.catalog.store import Store
from mining.errors import InputError
from mining.names import check_name

DESCRIPTORS = "tube_descriptors"
GROUPS = "tube_groups"
DERIVED_TABLES = (DESCRIPTORS, GROUPS)
NOISE = -1  # HDBSCAN's group of the tubes that belong to none


def descriptor_schema(dim: int) -> pa.Schema:
    """``tube_descriptors``: one fixed-length vector per tube and descriptor version."""
    return pa.schema([
        pa.field("tube_id", pa.string(), False),
        pa.field("dataset", pa.string(), False),
        pa.field("sequence", pa.string(), False),
        pa.field("version", pa.string(), False),  # the descriptor recipe (discovery/descriptors.py DESCRIPTOR_VERSION)
        pa.field("vector", pa.list_(pa.float32(), dim), False),  # the normalised components, in the recipe's order
    ])


GROUP_SCHEMA = pa.schema([
    pa.field("tube_id", pa.string(), False),
    pa.field("dataset", pa.string(), False),
    pa.field("sequence", pa.string(), False),
    pa.field("group", pa.int32(), False),  # HDBSCAN group, −1: noise (in no group)
    pa.field("probability", pa.float32(), False),  # HDBSCAN membership strength in [0, 1] (0 for noise)
    pa.field("group_size", pa.int32(), False),  # tubes in the same group (noise: how many are noise)
    pa.field("centre_distance", pa.float32(), False),  # cosine distance to the group's mean direction (the spread; noise: 0)
    pa.field("version", pa.string(), False),  # the grouping recipe: descriptor version and HDBSCAN settings
])


def descriptors_file(dataset: str, sequence: str) -> str:
    origin = "a path under --out"
    return (f"{DISCOVERY}/{DESCRIPTORS}/{check_name(dataset, 'dataset', origin)}/"
            f"{check_name(sequence, 'sequence', origin)}/descriptors.parquet")


def descriptors_marker(dataset: str, sequence: str) -> str:
    return descriptors_file(dataset, sequence).rsplit("/", 1)[0] + ".json"


GROUPS_FILE = f"{DISCOVERY}/{GROUPS}/groups.parquet"
GROUPS_MARKER = f"{DISCOVERY}/{GROUPS}.json"


@dataclass(frozen=True)
class DerivedMarker:
    """What a derived file was computed from, and its digest."""

    version: str
    inputs: str  # digest of the inputs
    file: str  # relative path of the data file
    size: int
    sha256: str
    rows: int

    def to_json(self) -> bytes:
        return json.dumps(self.__dict__, indent=1, sort_keys=True).encode()


def read_marker(store: Store, rel: str) -> DerivedMarker | None:
    """The marker at ``rel``; None when it is missing or does not read (then nothing is vouched)."""
    try:
        d = json.loads(store.read_bytes(rel))
        return DerivedMarker(str(d["version"]), str(d["inputs"]), str(d["file"]), int(d["size"]), str(d["sha256"]),
                             int(d["rows"]))
    except (InputError, ValueError, KeyError, TypeError):
        return None


def write_derived(store: Store, rel: str, marker_rel: str, table: pa.Table, version: str, inputs: str) -> DerivedMarker:
    """Write ``table`` at ``rel`` atomically, then its marker: a crash between the two leaves a
    file no marker vouches for (recomputed next time), never a marker for a half-written file."""
    store.write_table(rel, table)
    d = digest(store, rel)
    marker = DerivedMarker(version, inputs, rel, d["size"], d["sha256"], table.num_rows)
    store.write_bytes(marker_rel, marker.to_json())
    return marker


def checks_out(store: Store, marker: DerivedMarker) -> str | None:
    """Why the marker's file is not as recorded, or None when its size and sha256 agree."""
    info = store.fs.get_file_info(store.full(marker.file))
    if info.type != pafs.FileType.File:
        return "missing"
    if info.size != marker.size:
        return f"{info.size} bytes, {marker.size} recorded"
    if cached_sha256(store, marker.file, info.size, info.mtime_ns) != marker.sha256:
        return "sha256 differs from its marker's"
    return None


def descriptor_markers(store: Store) -> dict[tuple[str, str], DerivedMarker | None]:
    """(dataset, sequence) → the marker of its stored descriptors (None: unreadable)."""
    out: dict[tuple[str, str], DerivedMarker | None] = {}
    for rel in store.list(f"{DISCOVERY}/{DESCRIPTORS}", ".json"):
        parts = rel.split("/")
        if len(parts) == 4:
            out[(parts[2], parts[3].removesuffix(".json"))] = read_marker(store, rel)
    return out


def vouched(store: Store) -> tuple[dict[str, list[str]], list[tuple[str, str]]]:
    """({table: files whose marker vouches for them}, [(file, why not)] for damaged ones)."""
    files: dict[str, list[str]] = {t: [] for t in DERIVED_TABLES}
    damage: list[tuple[str, str]] = []
    markers = [(DESCRIPTORS, m) for m in descriptor_markers(store).values() if m is not None]
    if (g := read_marker(store, GROUPS_MARKER)) is not None:
        markers.append((GROUPS, g))
    for table, m in markers:
        why = checks_out(store, m)
        if why is None:
            files[table].append(m.file)
        else:
            damage.append((m.file, why))
    return {t: sorted(v) for t, v in files.items()}, damage
