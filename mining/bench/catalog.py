"""Catalogue benchmark: bytes per tube-frame row and the README's example queries.

Builds a catalogue of about ``n_rows`` tube-frame rows over a few sequences with
``write_sequence``. Masks are real: the COCO RLEs of the proposal JSON of KITTI 0005
(shared/data/proposals_4dgvt_format), each tube following one real mask that slides
sideways by a pixel per frame with its outline jittered by a pixel, so every row holds a
distinct, valid compressed RLE of realistic length and entropy (cycling identical
strings would flatter Parquet's dictionary and zstd compression).
The other columns are seeded random values of realistic ranges.

    python -m mining.bench.catalog [--rows N] [--dir DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
from pycocotools import mask as mask_utils

from mining.catalog.integrity import sequence_files
from mining.catalog.records import SequenceMarker
from mining.catalog.schema import SCHEMA_VERSION, THETA_COLUMNS, hive_file_schema
from mining.catalog.store import Store, write_sequence
from mining.catalog.views import connect
from mining.formats.coco import CLASS_INDEX
from mining.masks import rle_counts

DATA = Path(os.environ.get("TUBE_MINER_SHARED", Path(__file__).resolve().parents[3] / "shared")) / "data"
PROPOSALS = DATA / "proposals_4dgvt_format" / "kitti_tracking_0005" / "top20"
N_SEQUENCES = 4  # ours: a few sequences, as a multi-sequence job writes them
SEED = 0

# The README's example queries; {sequence} and {tube_id} are filled in by the bench.
EXAMPLE_QUERIES = {
    "unknown_long_tubes": "SELECT tube_id, n_frames, score FROM unknown_tubes "
                          "WHERE sequence = '{sequence}' AND n_frames > 20 ORDER BY score DESC",
    "tubes_by_category": "SELECT category, count(*) AS tubes FROM selected_tubes GROUP BY category ORDER BY tubes DESC",
    "rerank": "SELECT tube_id, 0.5 * score_motion + 2.0 * score_mask + 1.0 * score_objectness AS rescored "
              "FROM tube_scores WHERE selected ORDER BY rescored DESC LIMIT 100",
    "one_tube_masks": "SELECT frame, bbox, rle_counts, rle_h, rle_w FROM tube_frames "
                      "WHERE tube_id = '{tube_id}' ORDER BY frame",
}


def real_masks(folder: Path = PROPOSALS) -> list[tuple[np.ndarray, int, int]]:
    """(run lengths, height, width) of every proposal mask in the folder's JSON files."""
    out = []
    for path in sorted(folder.glob("*.json")):
        for p in json.loads(path.read_text()):
            seg = p["segmentation"]
            h, w = seg["size"]
            out.append((rle_counts(seg), int(h), int(w)))
    if not out:
        raise FileNotFoundError(f"no proposal JSON under {folder}")
    return out


def _slid(rng: np.random.Generator, counts: np.ndarray, h: int, w: int, n: int) -> list[dict]:
    """The mask over n frames: slid right by 0, 1, 2, … columns (bouncing inside the
    image; in column-major runs one column moves h pixels from the last run to the first),
    its boundary jittered by a pixel per run and frame, as a real mask's outline changes."""
    room = (int(counts[-1]) - 1) // h if counts.size % 2 == 1 else 0  # free columns on the right (jitter takes 1)
    steps = np.arange(n) % (2 * room) if room else np.zeros(n, int)
    steps = np.where(steps > room, 2 * room - steps, steps)
    c = np.repeat(counts[None], n, axis=0)
    d = rng.integers(-1, 2, (n, counts.size - 1)) * ((counts[:-1] >= 3) & (counts[1:] >= 3))
    c[:, :-1] += d
    c[:, 1:] -= d
    c[:, 0] += steps * h
    c[:, -1] -= steps * h
    objs = [{"counts": row, "size": [h, w]} for row in c.tolist()]
    return mask_utils.frPyObjects(objs, h, w)


def _sequence_tables(rng: np.random.Generator, masks, dataset: str, sequence: str, n_rows: int,
                     first_mask: int) -> tuple[pa.Table, pa.Table, pa.Table, int]:
    names = list(CLASS_INDEX)
    tube_ids, tf_cols = [], {k: [] for k in ("tube_id", "frame", "bbox", "rle_counts", "rle_h", "rle_w")}
    starts, lengths = [], []
    n, k, frame0 = 0, first_mask, 0
    while n < n_rows:
        length = int(min(rng.integers(3, 60), n_rows - n))
        counts, h, w = masks[k % len(masks)]
        k += 1
        tid = f"{dataset}/{sequence}/{frame0}.{len(tube_ids) % 20}"
        tube_ids.append(tid)
        starts.append(frame0)
        lengths.append(length)
        rles = _slid(rng, counts, h, w, length)
        boxes = mask_utils.toBbox(rles)  # x, y, w, h
        tf_cols["tube_id"] += [tid] * length
        tf_cols["frame"] += list(range(frame0, frame0 + length))
        tf_cols["bbox"] += np.c_[boxes[:, :2], boxes[:, :2] + boxes[:, 2:]].tolist()
        tf_cols["rle_counts"] += [r["counts"].decode() for r in rles]
        tf_cols["rle_h"] += [h] * length
        tf_cols["rle_w"] += [w] * length
        n += length
        frame0 += int(rng.integers(0, 3))  # a few tubes start per frame
    m, t = len(tube_ids), n
    observed = rng.random(t) > 0.1
    f32 = lambda *shape: rng.normal(size=shape).astype(np.float32)  # noqa: E731
    vec = lambda a: pa.FixedSizeListArray.from_arrays(pa.array(a.ravel()), 3)  # noqa: E731
    tf = pa.table({
        "tube_id": pa.array(tf_cols["tube_id"]), "frame": pa.array(tf_cols["frame"], pa.int32()),
        "t_ns": pa.array(np.asarray(tf_cols["frame"], np.int64) * 100_000_000),
        "bbox": pa.FixedSizeListArray.from_arrays(pa.array(np.asarray(tf_cols["bbox"], np.float32).ravel()), 4),
        "rle_counts": pa.array(tf_cols["rle_counts"]), "rle_h": pa.array(tf_cols["rle_h"], pa.int32()),
        "rle_w": pa.array(tf_cols["rle_w"], pa.int32()), "observed": pa.array(observed),
        "obs_index": pa.array(np.where(observed, rng.integers(0, 30, t), -1).astype(np.int32)),
        "objectness": pa.array(rng.random(t).astype(np.float32), mask=~observed),
        "position_cam": vec(f32(t, 3) * 10), "position_world": vec(f32(t, 3) * 50),
        "velocity_world": vec(f32(t, 3)), "size": vec(np.abs(f32(t, 3)) + 1),
        "mask_iou": pa.array(rng.random(t).astype(np.float32), mask=~observed),
        "motion_density": pa.array(rng.random(t).astype(np.float32), mask=~observed),
    })
    known = rng.random(m) > 0.3
    best = rng.choice(names[:10], m)
    post = rng.dirichlet(np.ones(81) * 0.1, m).astype(np.float32)
    starts_a, lengths_a = np.asarray(starts), np.asarray(lengths)
    motion, mask, objn = rng.normal(20, 10, m), rng.normal(30, 15, m), rng.normal(10, 5, m)
    tubes = pa.table({
        "tube_id": pa.array(tube_ids), "t_start": pa.array(starts_a * 100_000_000),
        "t_end": pa.array((starts_a + lengths_a - 1) * 100_000_000),
        "frame_start": pa.array(starts_a, pa.int32()), "frame_end": pa.array(starts_a + lengths_a - 1, pa.int32()),
        "n_frames": pa.array(lengths_a, pa.int32()), "n_observed": pa.array(lengths_a, pa.int32()),
        "score": pa.array(0.4 * motion + mask + objn), "score_model": pa.array(["reference"] * m),
        "score_version": pa.nulls(m, pa.string()),  # synthetic scores: no parameters to hash
        **{c: pa.nulls(m, pa.float64()) for c in THETA_COLUMNS}, "score_motion": pa.array(motion),
        "score_mask": pa.array(mask), "score_objectness": pa.array(objn),
        "selected": pa.array(rng.random(m) > 0.5), "call": pa.array(np.where(known, "known", "unknown")),
        "object_prob": pa.array(np.where(known, np.nan, rng.random(m)), pa.float32(), mask=np.asarray(known, bool)),
        "known": pa.array(known),
        "category": pa.array(np.where(known, best, "unknown")), "category_prob": pa.array(rng.random(m), pa.float32()),
        "best_known": pa.array(best), "class_posterior": pa.array(list(post), pa.list_(pa.float32())),
        "classified_frames": pa.array(lengths_a, pa.int32()), "class_evidence": pa.array(lengths_a, pa.float32()),
        "segment": pa.array(np.zeros(m, np.int32)), "mean_position": vec(f32(m, 3) * 50),
        "size": vec(np.abs(f32(m, 3)) + 1), "path_length": pa.array(np.abs(f32(m)) * 20),
        "speed": pa.array(np.abs(f32(m)) * 5), "speed_sigma_mps": pa.array(np.full(m, 0.5, np.float32)),
        "path_sigma_m": pa.array(np.full(m, 1.0, np.float32)),
        "moving_speed_mps": pa.array(np.where(np.arange(m) % 3 == 0, np.abs(f32(m)) * 5, np.nan), pa.float32(),
                                     mask=np.arange(m) % 3 != 0), "n_windows": pa.array(np.ones(m, np.int16)),
        "run_id": pa.array(["bench"] * m), "params_hash": pa.array(["0" * 16] * m),
        "schema_version": pa.array(np.full(m, SCHEMA_VERSION, np.int16)),
    })
    n_fr = int(frame0 + 60)
    frames = pa.table({
        "frame": pa.array(np.arange(n_fr, dtype=np.int32)), "position": pa.array(np.arange(n_fr, dtype=np.int32)),
        "t_ns": pa.array(np.arange(n_fr, dtype=np.int64) * 100_000_000),
        "segment": pa.array(np.zeros(n_fr, np.int32)),
        "pose": pa.FixedSizeListArray.from_arrays(pa.array(np.tile(np.eye(4).ravel(), n_fr)), 16),
        "egomotion_ok": pa.array(np.ones(n_fr, bool)), "egomotion_inliers": pa.array(np.full(n_fr, 300, np.int32)),
        "egomotion_rmse_px": pa.array(np.full(n_fr, 0.5, np.float32)), "ground_ok": pa.array(np.ones(n_fr, bool)),
        "ground_age": pa.array(np.zeros(n_fr, np.int32)), "n_proposals": pa.array(np.full(n_fr, 20, np.int32)),
        "n_observations": pa.array(np.full(n_fr, 15, np.int32)),
    })
    for name, tab in (("tubes", tubes), ("tube_frames", tf), ("frames", frames)):
        assert tab.schema.names == hive_file_schema(name).names, name  # write_sequence adds dataset / sequence
    return tubes, tf, frames, k


def build_catalogue(out: str | Path, n_rows: int = 1_000_000, n_sequences: int = N_SEQUENCES) -> dict:
    """Write the bench catalogue; returns its row counts and the sequences written."""
    rng = np.random.default_rng(SEED)
    masks = real_masks()
    store = Store(out)
    k, n_tubes = 0, 0
    sequences = [f"{i:04d}" for i in range(n_sequences)]
    for i, seq in enumerate(sequences):
        rows = n_rows // n_sequences + (1 if i < n_rows % n_sequences else 0)
        tubes, tf, frames, k = _sequence_tables(rng, masks, "bench", seq, rows, k)
        written = (write_sequence(store, "tubes", "bench", seq, tubes)
                   + write_sequence(store, "tube_frames", "bench", seq, tf)
                   + write_sequence(store, "frames", "bench", seq, frames))
        # A finished marker with every file's size and sha256, as a mining job's stitch leaves
        # it: readers then serve only these files and check their checksums (integrity on).
        SequenceMarker("bench", seq, (), files=sequence_files(store, written)).save(store)
        n_tubes += tubes.num_rows
    return {"tube_frames": n_rows, "tubes": n_tubes, "sequences": sequences, "masks": len(masks)}


def _bytes(store: Store, prefix: str) -> int:
    return sum(store.fs.get_file_info(store.full(p)).size for p in store.list(prefix))


def bench_catalog(tmpdir: str | Path, n_rows: int = 1_000_000, repeats: int = 3) -> dict:
    """Build the catalogue under ``tmpdir``, then measure storage and the example queries
    (wall seconds, best of ``repeats``, result fetched). ``connect_s`` is the first connect
    of the process: it checks every file's size and sha256 against its marker."""
    out = Path(tmpdir) / "bench_catalog"
    t0 = time.perf_counter()
    built = build_catalogue(out, n_rows)
    build_s = time.perf_counter() - t0
    store = Store(out)
    tf_bytes, all_bytes = _bytes(store, "catalog/tube_frames"), _bytes(store, "catalog")
    t0 = time.perf_counter()
    con = connect(out)
    connect_s = time.perf_counter() - t0
    seq = built["sequences"][1]
    tube_id = con.sql(f"SELECT tube_id FROM tubes WHERE sequence = '{seq}' ORDER BY n_frames DESC, tube_id "
                      "LIMIT 1").fetchone()[0]
    times, rows = {}, {}
    for name, sql in EXAMPLE_QUERIES.items():
        q = sql.format(sequence=seq, tube_id=tube_id)
        best = float("inf")
        for _ in range(repeats):
            t0 = time.perf_counter()
            result = con.sql(q).fetchall()
            best = min(best, time.perf_counter() - t0)
        times[name], rows[name] = best, len(result)
    con.close()
    return {
        "tube_frame_rows": built["tube_frames"], "tubes": built["tubes"], "sequences": len(built["sequences"]),
        "distinct_source_masks": built["masks"],
        "bytes_per_tube_frame": tf_bytes / built["tube_frames"],
        "catalog_bytes_per_tube_frame": all_bytes / built["tube_frames"],
        "build_s": build_s, "connect_s": connect_s, "query_s": times, "query_rows": rows,
        "queries": {k: v.format(sequence=seq, tube_id=tube_id) for k, v in EXAMPLE_QUERIES.items()},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=1_000_000, help="tube-frame rows")
    ap.add_argument("--dir", help="where to build (default: a temporary folder, removed after)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        r = bench_catalog(args.dir or tmp, args.rows)
    print(f"catalogue: {r['tube_frame_rows']:,} tube-frame rows, {r['tubes']:,} tubes, {r['sequences']} sequences "
          f"(built in {r['build_s']:.1f} s)")
    print(f"bytes per tube-frame row: {r['bytes_per_tube_frame']:.1f} (tube_frames), "
          f"{r['catalog_bytes_per_tube_frame']:.1f} (whole catalogue)")
    print(f"connect: {r['connect_s'] * 1000:.1f} ms")
    for name, s in r["query_s"].items():
        flag = "ok" if s <= 1.0 else "OVER 1 s"
        print(f"  {name:20s} {s * 1000:8.1f} ms  {r['query_rows'][name]:6d} rows  {flag}")


if __name__ == "__main__":
    main()
