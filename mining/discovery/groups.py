"""Group the unknown set: density-based clusters of the unknown tubes' descriptors (HDBSCAN,
scikit-learn), so a researcher looks at one tile per group instead of one tube at a time.

HDBSCAN (Campello et al. 2013) finds groups of any shape and size and leaves what belongs to
none as noise (group −1), with no number of groups to choose. The descriptors are L2-normalised
first: Euclidean distance between unit vectors is a monotone function of cosine distance
(‖a − b‖² = 2 · (1 − cos)), so the groups are those of cosine similarity while the search for
neighbours are found by faiss's exact flat index (HDBSCAN's cosine metric would need the full
n × n distances, and scikit-learn's minimum spanning tree over all pairs is O(n²): 74 s for 10⁵
tubes on two cores, where the k-nearest-neighbour graph takes about 20 s).

Selection: "leaf" by default, HDBSCAN's finest stable groups (each homogeneous, so one tile
stands for the group); "eom" (excess of mass, HDBSCAN's default) tends to keep a handful of huge
groups when the set is one smeared density, as a drive's unknown set is. The smallest group
grows with the set (``default_min_size``), so the gallery holds at most MAX_GROUPS tiles.

The unknown set is views.sql's ``unknown_tubes`` (selected, call unknown). The grouping is stored
as ``tube_groups`` (``catalog/derived.py``) with the digest of what it grouped: running ``mine
group`` again over an unchanged unknown set reads it back; a grown one is grouped again whole
(HDBSCAN has no incremental form in scikit-learn; 10⁵ tubes take well under a minute on two
cores: docs/RESULTS.md "Discovery at scale"), so group numbers are stable only between runs over
the same inputs.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass
from pathlib import Path

import duckdb
import numpy as np
import pyarrow as pa

from mining.catalog import derived
from mining.catalog.store import Store
from mining.catalog.views import connect
from mining.discovery.describe import load_descriptors
from mining.discovery.descriptors import DESCRIPTOR_VERSION
from mining.discovery.similar import MIN_NORM
from mining.errors import InputError

MIN_GROUP_SIZE = 10  # ours: a group worth a tile holds at least ten tubes (`mine group --min-size`)
MAX_GROUPS = 400  # ours: a gallery of group tiles a person scans in a sitting; the smallest group grows with the set
MIN_SAMPLES = 5  # ours: a tube is in a dense region when 5 neighbours are near (HDBSCAN min_samples)
NEIGHBOURS = 15  # ours: edges per tube of the k-nearest-neighbour graph HDBSCAN runs on (≥ 2 × MIN_SAMPLES)
SELECTION = "leaf"  # ours: HDBSCAN's finest stable groups; "eom" (its default) keeps few huge ones on a smeared set
SELECTIONS = ("leaf", "eom")
TIE_DISTANCE = 1e-9  # ours: a duplicate's distance (0) would read as "no edge" in a sparse matrix
FAR = 2.0  # the largest Euclidean distance of two unit vectors: joins the graph's components at the top only


def default_min_size(n: int) -> int:
    """The smallest group for ``n`` tubes: MIN_GROUP_SIZE, or enough that at most MAX_GROUPS fit."""
    return max(MIN_GROUP_SIZE, -(-n // MAX_GROUPS))


def neighbour_graph(unit: np.ndarray, k: int) -> "scipy.sparse.csr_matrix":  # noqa: F821
    """The symmetric k-nearest-neighbour graph of unit vectors (Euclidean distances; exact, faiss
    flat), its connected components joined by edges of length ``FAR``: HDBSCAN's input."""
    import faiss
    import scipy.sparse as sp
    from scipy.sparse import csgraph

    n = len(unit)
    k = min(k, n - 1)
    index = faiss.IndexFlatL2(unit.shape[1])
    index.add(np.ascontiguousarray(unit, np.float32))
    d2, nb = index.search(np.ascontiguousarray(unit, np.float32), k + 1)
    rows = np.repeat(np.arange(n), k + 1)
    keep = (nb.ravel() >= 0) & (nb.ravel() != rows)
    dist = np.maximum(np.sqrt(np.maximum(d2.ravel()[keep], 0.0)), TIE_DISTANCE)
    g = sp.csr_matrix((dist, (rows[keep], nb.ravel()[keep])), shape=(n, n))
    g = g.maximum(g.T).tocsr()
    n_parts, part = csgraph.connected_components(g, directed=False)
    if n_parts > 1:
        first = np.unique(part, return_index=True)[1]
        bridge = sp.csr_matrix((np.full(n_parts - 1, FAR), (first[:-1], first[1:])), shape=(n, n))
        g = (g + bridge + bridge.T).tocsr()
    return g


def group_vectors(vectors: np.ndarray, min_group_size: int | None = None, min_samples: int = MIN_SAMPLES,
                  selection: str = SELECTION) -> tuple[np.ndarray, np.ndarray]:
    """(group per row, −1 noise; membership probability per row) of HDBSCAN over the rows'
    directions, on their k-nearest-neighbour graph (``neighbour_graph``: exact neighbours, so the
    O(n²) minimum spanning tree of all pairs becomes one of n·k edges). ``min_group_size`` None:
    ``default_min_size``. Fewer rows than that: every row is noise."""
    from sklearn.cluster import HDBSCAN  # here: scikit-learn takes a second to load

    v = np.asarray(vectors, np.float64)
    n = len(v)
    size = default_min_size(n) if min_group_size is None else min_group_size
    if selection not in SELECTIONS:
        raise InputError(f"group selection {selection!r}: one of {', '.join(SELECTIONS)}")
    if n < max(3, size):
        return np.full(n, -1, np.int64), np.zeros(n, np.float64)
    unit = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), MIN_NORM)
    samples = min(min_samples, n - 1)
    graph = neighbour_graph(unit, max(NEIGHBOURS, 2 * samples))
    model = HDBSCAN(min_cluster_size=size, min_samples=samples, metric="precomputed",
                    cluster_selection_method=selection, copy=True)
    labels = model.fit_predict(graph)
    return labels.astype(np.int64), np.asarray(model.probabilities_, np.float64)


def centre_distances(vectors: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Each row's cosine distance to its group's mean direction (0 for noise): a group's spread."""
    unit = np.asarray(vectors, np.float64)
    unit = unit / np.maximum(np.linalg.norm(unit, axis=1, keepdims=True), MIN_NORM)
    out = np.zeros(len(unit))
    for g in np.unique(labels[labels >= 0]):
        rows = labels == g
        centre = unit[rows].mean(axis=0)
        out[rows] = np.maximum(1.0 - unit[rows] @ (centre / max(float(np.linalg.norm(centre)), MIN_NORM)), 0.0)
    return out


GROUPING_RECIPE = 1  # ours: bump when the code changes how the unknown set is grouped


def grouping_version(min_group_size: int | None, min_samples: int, selection: str) -> str:
    """The recipe of a grouping: its descriptors', HDBSCAN's settings."""
    size = "auto" if min_group_size is None else min_group_size
    return f"g{GROUPING_RECIPE}-{DESCRIPTOR_VERSION}-min{size}-samples{min_samples}-{selection}-k{NEIGHBOURS}"


@dataclass(frozen=True)
class Grouped:
    """What one ``group_unknown`` did."""

    tubes: int  # unknown tubes with a descriptor, grouped
    groups: int  # groups found (noise not counted)
    noise: int  # tubes in no group
    undescribed: int  # unknown tubes without a descriptor (run `mine describe`)
    recomputed: bool  # False: the stored grouping was already of these inputs
    seconds: float


def unknown_set(out: str | Path) -> list[tuple[str, str, str]]:
    """(dataset, sequence, tube_id) of the unknown set (views.sql ``unknown_tubes``), in id order."""
    con = connect(out)
    try:
        return [tuple(r) for r in con.execute(
            "SELECT dataset, sequence, tube_id FROM unknown_tubes ORDER BY tube_id").fetchall()]
    except duckdb.Error as e:  # a damaged catalogue: the message names the file
        raise InputError(str(e).removeprefix("Invalid Input Error: ")) from None
    finally:
        con.close()


def group_unknown(store: Store, min_group_size: int | None = None, min_samples: int = MIN_SAMPLES,
                  selection: str = SELECTION, force: bool = False) -> Grouped:
    """Group the unknown set's descriptors into ``tube_groups`` (``derived.GROUPS_FILE``); nothing
    is recomputed when the unknown set, its descriptors and the settings are those stored."""
    t0 = time.perf_counter()
    ids, vectors = load_descriptors(store)
    row = {t: k for k, t in enumerate(ids.column("tube_id").to_pylist())}
    unknown = unknown_set(store.uri)
    have = [u for u in unknown if u[2] in row]
    rows = np.array([row[u[2]] for u in have], np.int64)
    version = grouping_version(min_group_size, min_samples, selection)
    v = vectors[rows] if len(rows) else np.zeros((0, vectors.shape[1]), np.float32)
    key = hashlib.sha256(json.dumps([version, [u[2] for u in have]]).encode() + v.tobytes()).hexdigest()
    stored = derived.read_marker(store, derived.GROUPS_MARKER)
    if not force and stored is not None and stored.version == version and stored.inputs == key \
            and derived.checks_out(store, stored) is None:
        table = store.read_table(stored.file, ["group"])
        labels = np.asarray(table.column("group").to_numpy(), np.int64)
        return Grouped(len(have), len(set(labels[labels >= 0].tolist())), int((labels < 0).sum()),
                       len(unknown) - len(have), False, time.perf_counter() - t0)
    labels, prob = group_vectors(v, min_group_size, min_samples, selection)
    sizes = np.bincount(labels + 1, minlength=1)[labels + 1] if len(labels) else np.zeros(0, np.int64)
    table = pa.table({
        "centre_distance": pa.array(centre_distances(v, labels), pa.float32()),
        "tube_id": [u[2] for u in have], "dataset": [u[0] for u in have], "sequence": [u[1] for u in have],
        "group": pa.array(labels, pa.int32()), "probability": pa.array(prob, pa.float32()),
        "group_size": pa.array(sizes, pa.int32()), "version": [version] * len(have)}).select(derived.GROUP_SCHEMA.names)
    table = table.cast(derived.GROUP_SCHEMA)
    derived.write_derived(store, derived.GROUPS_FILE, derived.GROUPS_MARKER, table, version, key)
    return Grouped(len(have), int(labels.max() + 1) if len(labels) else 0, int((labels < 0).sum()),
                   len(unknown) - len(have), True, time.perf_counter() - t0)
