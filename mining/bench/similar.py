"""``mine bench similar``: k nearest tubes by cosine distance over 10⁵ and 10⁶ descriptors, and
grouping 10⁵ unknown tubes, on this machine's cores.

The descriptors are realistic, not uniform noise: raw quantities (``discovery/descriptors.py``)
drawn per kind of street object (cars, pedestrians, cyclists, poles, signs, bins, barriers, bushes:
``KINDS``, sizes and speeds from their physics, each with its spread), then normalised by the
descriptor's own fixed transform. Exact search (``similar.py``: NumPy over L2-normalised vectors)
is timed against the same search in DuckDB (``array_cosine_distance``) and, with ``--compare``,
against the libraries that were candidates for the index (faiss flat and HNSW, usearch, hnswlib:
whichever are installed, ``pip install tube-miner[bench]``), with each approximate index's
recall@10 against the exact answer. docs/RESULTS.md "Discovery at scale" holds the numbers.

    mine bench similar [--sizes 100000,1000000] [--queries 50] [--compare] [--group-size 100000]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable

import numpy as np

from mining.checks import count
from mining.discovery.descriptors import CAMERA_HEIGHT_M, DIM, NAMES, normalise
from mining.discovery.similar import ExactIndex

K = 10  # the query: the 10 nearest tubes
MAX_SIZE = 10_000_000  # ours: the largest set the bench builds, 10× the 10⁶ (1.6 GB of descriptors)
SEED = 0
HNSW_M, HNSW_EF_BUILD, HNSW_EF_SEARCH = 16, 100, 64  # ours: the libraries' common defaults for HNSW
# Per kind: (share, size w/h/l in m, speed m/s, moving share, P(unknown)). Ours, from street physics.
KINDS = {
    "car": (0.40, (1.8, 1.5, 4.3), 4.0, 0.5, 0.05),
    "pedestrian": (0.20, (0.6, 1.7, 0.6), 1.2, 0.7, 0.05),
    "cyclist": (0.06, (0.6, 1.7, 1.8), 4.0, 0.9, 0.1),
    "pole": (0.10, (0.3, 4.0, 0.3), 0.0, 0.0, 0.8),
    "sign": (0.06, (0.8, 0.8, 0.1), 0.0, 0.0, 0.7),
    "bin": (0.06, (0.6, 1.0, 0.6), 0.0, 0.0, 0.85),
    "barrier": (0.06, (2.0, 1.0, 0.4), 0.0, 0.0, 0.9),
    "bush": (0.06, (1.5, 1.2, 1.5), 0.0, 0.0, 0.9),
}


def realistic_raw(n: int, seed: int = SEED) -> np.ndarray:
    """(n, DIM) raw descriptor quantities of ``n`` tubes drawn from ``KINDS``."""
    rng = np.random.default_rng(seed)
    shares = np.array([k[0] for k in KINDS.values()])
    kind = rng.choice(len(KINDS), n, p=shares / shares.sum())
    params = list(KINDS.values())
    size = np.array([params[k][1] for k in kind]) * rng.lognormal(0.0, 0.2, (n, 3))
    moving = rng.random(n) < np.array([params[k][3] for k in kind])
    speed = np.where(moving, np.array([params[k][2] for k in kind]) * rng.lognormal(0.0, 0.4, n),
                     np.abs(rng.normal(0.0, 0.1, n)))
    sigma = rng.lognormal(np.log(0.15), 0.5, n)
    frames = np.maximum(2, rng.geometric(1 / 15, n))
    p_unknown = np.clip(np.array([params[k][4] for k in kind]) + rng.normal(0, 0.1, n), 0, 1)
    top_known = (1 - p_unknown) * rng.uniform(0.5, 1.0, n)
    elevation = -CAMERA_HEIGHT_M + np.where(np.array([params[k][1][1] for k in kind]) < 1.0,
                                            rng.uniform(0, 2.0, n), rng.normal(0, 0.1, n))
    cols = {
        "log_width": size[:, 0], "log_height": size[:, 1], "log_length": size[:, 2], "foot_elevation": elevation,
        "log_distance": rng.uniform(4, 45, n), "log_speed": speed, "log_speed_sigma": sigma,
        "moving": moving.astype(float), "log_path": speed * frames / 10, "log_duration": frames,
        "box_aspect": np.log(size[:, 0] / size[:, 1]) + rng.normal(0, 0.1, n), "mask_fill": rng.uniform(0.5, 0.9, n),
        "aspect_spread": rng.gamma(2, 0.05, n), "fill_spread": rng.gamma(2, 0.03, n),
        "area_spread": rng.gamma(2, 0.1, n), "class_entropy": rng.uniform(0.3, 3.0, n), "p_unknown": p_unknown,
        "top_known": top_known, "object_prob": rng.uniform(0.3, 1.0, n)}
    return np.column_stack([cols[name] for name in NAMES])


def realistic_descriptors(n: int, seed: int = SEED) -> np.ndarray:
    return normalise(realistic_raw(n, seed))


def _median_ms(queries: np.ndarray, search: Callable[[np.ndarray], np.ndarray]) -> tuple[float, list[np.ndarray]]:
    search(queries[0])  # warm
    times, found = [], []
    for q in queries:
        t = time.perf_counter()
        found.append(search(q))
        times.append((time.perf_counter() - t) * 1e3)
    return statistics.median(times), found


def recall(found: list[np.ndarray], truth: list[np.ndarray]) -> float:
    """Mean share of the exact k nearest that an approximate search found."""
    return float(np.mean([len(set(f.tolist()) & set(t.tolist())) / len(t) for f, t in zip(found, truth)]))


def _stored_and_read(vectors: np.ndarray) -> tuple[ExactIndex, float]:
    """The exact index as `mine similar` builds it, and its seconds: the descriptors read back from
    a ``tube_descriptors`` file (tube ids included) and normalised."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from mining.catalog.derived import descriptor_schema

    n = len(vectors)
    table = pa.table({"tube_id": [f"bench/0000/{k:07d}.000" for k in range(n)], "dataset": ["bench"] * n,
                      "sequence": ["0000"] * n, "version": ["bench"] * n,
                      "vector": pa.FixedSizeListArray.from_arrays(pa.array(vectors.ravel(), pa.float32()), DIM)},
                     schema=descriptor_schema(DIM))
    with tempfile.TemporaryDirectory(prefix="bench-similar-") as folder:
        path = f"{folder}/descriptors.parquet"
        pq.write_table(table, path, compression="zstd")
        t = time.perf_counter()
        back = pq.read_table(path)
        vec = np.asarray(back.column("vector").combine_chunks().flatten().to_numpy(), np.float32).reshape(-1, DIM)
        back.column("tube_id").to_pylist()  # `mine similar` reads the ids too, to name the tubes it finds
        exact = ExactIndex(vec)
        return exact, time.perf_counter() - t


def _duckdb(vectors: np.ndarray) -> tuple[float, Callable[[np.ndarray], np.ndarray]]:
    import duckdb
    import pyarrow as pa

    t = time.perf_counter()
    con = duckdb.connect(":memory:")
    flat = pa.FixedSizeListArray.from_arrays(pa.array(vectors.ravel(), pa.float32()), DIM)
    con.register("v_arrow", pa.table({"i": np.arange(len(vectors)), "v": flat}))
    con.execute("CREATE TABLE v AS SELECT * FROM v_arrow")
    build = time.perf_counter() - t
    sql = f"SELECT i FROM v ORDER BY array_cosine_distance(v, ?::FLOAT[{DIM}]) LIMIT {K}"
    return build, lambda q: np.array([r[0] for r in con.execute(sql, [q.tolist()]).fetchall()])


def _candidates(vectors: np.ndarray) -> dict[str, Callable[[], tuple[float, Callable[[np.ndarray], np.ndarray]]]]:
    """name → a builder returning (build s, search): the libraries installed."""
    out: dict[str, Callable] = {}
    unit = vectors / np.maximum(np.linalg.norm(vectors, axis=1, keepdims=True), 1e-12)
    try:
        import faiss

        def faiss_build(kind: str):
            t = time.perf_counter()
            index = faiss.IndexFlatIP(DIM) if kind == "flat" else faiss.IndexHNSWFlat(DIM, HNSW_M, faiss.METRIC_INNER_PRODUCT)
            if kind == "hnsw":
                index.hnsw.efConstruction, index.hnsw.efSearch = HNSW_EF_BUILD, HNSW_EF_SEARCH
            index.add(unit)
            return time.perf_counter() - t, lambda q: index.search(q[None] / np.linalg.norm(q), K)[1][0]
        out["faiss flat (exact)"] = lambda: faiss_build("flat")
        out["faiss HNSW"] = lambda: faiss_build("hnsw")
    except ImportError:
        pass
    try:
        from usearch.index import Index

        def usearch_build():
            t = time.perf_counter()
            index = Index(ndim=DIM, metric="cos", dtype="f32", connectivity=HNSW_M, expansion_add=HNSW_EF_BUILD,
                          expansion_search=HNSW_EF_SEARCH)
            index.add(np.arange(len(unit)), unit)
            return time.perf_counter() - t, lambda q: index.search(q, K).keys
        out["usearch HNSW"] = usearch_build
    except ImportError:
        pass
    try:
        import hnswlib

        def hnswlib_build():
            t = time.perf_counter()
            index = hnswlib.Index(space="cosine", dim=DIM)
            index.init_index(max_elements=len(unit), ef_construction=HNSW_EF_BUILD, M=HNSW_M)
            index.add_items(unit, np.arange(len(unit)))
            index.set_ef(HNSW_EF_SEARCH)
            return time.perf_counter() - t, lambda q: index.knn_query(q, K)[0][0]
        out["hnswlib HNSW"] = hnswlib_build
    except ImportError:
        pass
    return out


def bench_size(n: int, n_queries: int, compare: bool) -> list[tuple[str, int, float, float, float]]:
    """(method, n, build s, median query ms, recall@10) for ``n`` realistic descriptors."""
    vectors = realistic_descriptors(n)
    queries = vectors[np.random.default_rng(SEED + 1).choice(n, n_queries, replace=False)]
    exact, build = _stored_and_read(vectors)
    ms, truth = _median_ms(queries, lambda q: exact.search(q, K)[0])
    rows = [("numpy exact (chosen; build: read from Parquet)", n, build, ms, 1.0)]
    builders = {"duckdb array_cosine_distance": lambda: _duckdb(vectors)}
    if compare:
        builders |= _candidates(vectors)
    for name, build_fn in builders.items():
        build, search = build_fn()
        ms, found = _median_ms(queries, search)
        rows.append((name, n, build, ms, recall(found, truth)))
        del search
    return rows


def bench_grouping(n: int) -> tuple[float, int, float]:
    """(seconds, groups, noise share) of grouping ``n`` realistic unknown-set descriptors."""
    from mining.discovery.groups import group_vectors

    vectors = realistic_descriptors(n, SEED + 2)
    t = time.perf_counter()
    labels, _ = group_vectors(vectors)
    return time.perf_counter() - t, int(labels.max() + 1), float((labels < 0).mean())


def _sizes(text: str) -> list[int]:
    """``--sizes``: comma-separated tube counts, each a checked count (``checks.count``: no nan, inf or 1e308)."""
    each = count(K + 1, MAX_SIZE, "tubes to index")
    sizes = [each(s.strip()) for s in text.split(",") if s.strip()]
    if not sizes:
        raise argparse.ArgumentTypeError(f"{text!r}: comma-separated tube counts, e.g. 100000,1000000")
    return sizes


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sizes", type=_sizes, default=[100_000, 1_000_000], help="tube counts (default 100000,1000000)")
    p.add_argument("--queries", type=count(1, 10_000), default=50, help="queries per size; the median is reported")
    p.add_argument("--compare", action="store_true",
                   help="also time the candidate index libraries that are installed (faiss, usearch, hnswlib)")
    p.add_argument("--group-size", type=count(0, MAX_SIZE), default=100_000, help="unknown tubes to group (0: skip)")


def run(args: argparse.Namespace) -> int:
    print(f"{'method':48s} {'tubes':>9s} {'build s':>8s} {'query ms':>9s} {'recall@10':>9s}")
    for n in args.sizes:
        for name, size, build, ms, rec in bench_size(n, args.queries, args.compare):
            print(f"{name:48s} {size:9d} {build:8.2f} {ms:9.2f} {rec:9.3f}", flush=True)
    if args.group_size > 0:
        s, groups, noise = bench_grouping(args.group_size)
        print(f"grouping {args.group_size} unknown tubes (HDBSCAN): {s:.1f} s, {groups} groups, {noise:.0%} noise")
    return 0
