"""A real small catalogue for the catalogue tests: KITTI tracking 0005, frames 0–15.

Tubes come from the detections-only pipeline (real PointRCNN detections, real ORB-SLAM3
egoposes, the project's tube generator, scorer and co-selection), converted into rows of
schema v2 by the pipeline's own ``mining/catalog/rows.py``. The 16 frames are the ones whose images are in shared/data, so crops can be exported.
"""

from __future__ import annotations

import json
from itertools import islice
from pathlib import Path

import numpy as np
import pyarrow as pa

from mining.catalog.layout import manifest_path
from mining.catalog.rows import RunInfo, tube_row
from mining.catalog.rows import frame_rows as rows_of_frames
from mining.catalog.schema import SCHEMAS, hive_file_schema
from mining.catalog.store import Store, write_sequence
from mining.config import load_config

from conftest import REPO

DATASET, SEQUENCE, N_FRAMES = "kitti", "0005", 16
RUN_ID = "test-run"


def mined_kitti_0005(kitti_tracking_root: Path):
    """(tracking frames, mined tubes, job config) of KITTI 0005 frames 0–15."""
    from mining.pipeline.detections import detection_frames
    from mining.pipeline.mine import mine_tubes

    train = kitti_tracking_root / "training"
    cfg = load_config(REPO / "jobs" / "kitti-detections.toml")
    cfg.source.dataset, cfg.source.root = DATASET, str(kitti_tracking_root)
    frames = list(islice(detection_frames(kitti_tracking_root, SEQUENCE, train / "det_pointrcnn",
                                          train / "egoposes_orbslam3" / f"{SEQUENCE}.txt", cfg), N_FRAMES))
    return frames, mine_tubes(frames, cfg), cfg


def tube_rows(mined, params_hash: str) -> tuple[pa.Table, pa.Table]:
    """(tubes, tube_frames) rows of schema v2 (with partition columns) from mined tubes."""
    run = RunInfo(DATASET, SEQUENCE, RUN_ID, params_hash)
    tubes, tf = [], []
    for m in mined:
        fr0 = m.tube.frames[0]
        tube_id = f"{DATASET}/{SEQUENCE}/{fr0.frame:07d}.{fr0.obs_index:03d}"
        tubes.append(dict(tube_row(m, tube_id, run), dataset=DATASET, sequence=SEQUENCE))
        tf.extend(dict(r, dataset=DATASET, sequence=SEQUENCE) for r in rows_of_frames(m, tube_id))
    return (pa.Table.from_pylist(tubes, schema=SCHEMAS["tubes"]),
            pa.Table.from_pylist(tf, schema=SCHEMAS["tube_frames"]))


def frame_rows(frames) -> pa.Table:
    rows = [{"dataset": DATASET, "sequence": SEQUENCE, "frame": f.index, "position": k, "t_ns": f.t_ns, "segment": f.segment,
             "pose": [float(x) for x in np.asarray(f.pose).ravel()],
             "egomotion_ok": None if k == 0 else True,  # poses given (ORB-SLAM3), not estimated
             "egomotion_inliers": 0, "egomotion_rmse_px": None, "ground_ok": False, "ground_age": None,
             "n_proposals": len(f.observations), "n_observations": len(f.observations)}
            for k, f in enumerate(frames)]
    return pa.Table.from_pylist(rows, schema=SCHEMAS["frames"])


def window_rows(params_hash: str) -> pa.Table:
    row = {"run_id": RUN_ID, "window": "w00000", "core_start": 0, "core_end": N_FRAMES,
           "context_start": 0, "context_end": N_FRAMES, "status": "done", "attempts": 1,
           "started": None, "finished": None, "seconds_observe": 1.0, "seconds_tubes": 0.5,
           "n_pieces": 0, "error": None, "params_hash": params_hash}
    return pa.Table.from_pylist([row], schema=hive_file_schema("windows"))  # a manifest row: hive folders say D and S


def build_catalogue(out: Path, kitti_tracking_root: Path) -> dict:
    """Write the KITTI 0005 catalogue under ``out``; returns the tables written."""
    frames, mined, cfg = mined_kitti_0005(kitti_tracking_root)
    store = Store(out)
    tubes, tf = tube_rows(mined, cfg.params_hash)
    write_sequence(store, "tubes", DATASET, SEQUENCE, tubes)
    write_sequence(store, "tube_frames", DATASET, SEQUENCE, tf)
    write_sequence(store, "frames", DATASET, SEQUENCE, frame_rows(frames))
    store.write_table(manifest_path(DATASET, SEQUENCE, "w00000"), window_rows(cfg.params_hash))
    job = {"run_id": RUN_ID, "params_hash": cfg.params_hash, "config": cfg.to_dict(), "windows": []}
    store.write_bytes("job.json", json.dumps(job, default=str).encode())
    return {"tubes": tubes, "tube_frames": tf, "mined": mined}


# ── every call in one catalogue (the viewer's tests) ─────────────────────────────────
# The four tubes of the catalogue above each get a call, and three more, copies of them under new ids,
# are rows written before the `call` column (call null: read from `known`, as export/selection.py
# tube_call reads them); a last copy is a selected unclassified tube. Posteriors and P(object) agree
# with each call (mining/score/call.py at margin 0 and unknown_min_object 0.5).
COCO_CAR = 2  # the index of "car" among the 80 COCO classes (formats/coco.py)
UNKNOWN_INDEX = 80


def _posterior(p_car: float, p_unknown: float) -> list[float]:
    rest = (1.0 - p_car - p_unknown) / 79
    post = [rest] * 81
    post[COCO_CAR], post[UNKNOWN_INDEX] = p_car, p_unknown
    return post


_UNKNOWN = dict(known=False, category="unknown", category_prob=0.8, best_known="car",
                class_posterior=_posterior(0.15, 0.8))
_CLUTTER = dict(known=False, category="unknown", category_prob=0.9, best_known="car",
                class_posterior=_posterior(0.06, 0.9))
_UNCLASSIFIED = dict(known=None, category=None, category_prob=None, best_known=None, class_posterior=None,
                     classified_frames=0, class_evidence=0.0, object_prob=None)
# (the source tube's position in tube-id order, the new id's observation index or None, changes, its call)
EVERY_CALL = [
    (0, None, dict(call="known"), "known"),
    (1, None, dict(_UNKNOWN, call="unknown", object_prob=0.72), "unknown"),
    (2, None, dict(_CLUTTER, call="clutter", object_prob=0.31), "clutter"),
    (3, None, dict(_UNCLASSIFIED, call="unclassified"), "unclassified"),  # a candidate, not selected
    (0, 100, dict(call=None, object_prob=None), "known"),  # written before the call column
    (1, 101, dict(_UNKNOWN, call=None, object_prob=None), "unknown"),
    # before the call column, an older rule called a tube unclassified on low classifier evidence too
    (2, 102, dict(_UNCLASSIFIED, call=None, classified_frames=3, class_evidence=0.4), "unclassified"),
    (3, 103, dict(_UNCLASSIFIED, call="unclassified", selected=True), "unclassified"),
]


def every_call_catalogue(out: Path, tables: dict, dest: Path) -> dict[str, str]:
    """A copy at ``dest`` of the catalogue ``out`` with the ``tables`` of ``build_catalogue``, whose
    tubes carry every call, some as rows written before the call column (``EVERY_CALL``); tube id →
    its call."""
    import shutil

    shutil.copytree(out, dest)
    tubes = sorted(tables["tubes"].to_pylist(), key=lambda t: t["tube_id"])
    assert len(tubes) == 4, "EVERY_CALL is written for the four tubes of KITTI 0005 frames 0–15"
    rows, frames, calls = [], [], {}
    for k, obs, changes, call in EVERY_CALL:
        src = tubes[k]
        tube_id = src["tube_id"] if obs is None else f"{src['tube_id'].rsplit('.', 1)[0]}.{obs:03d}"
        rows.append(dict(src, **changes, tube_id=tube_id))
        frames += [dict(f, tube_id=tube_id) for f in tables["tube_frames"].to_pylist() if f["tube_id"] == src["tube_id"]]
        calls[tube_id] = call
    store = Store(dest)
    write_sequence(store, "tubes", DATASET, SEQUENCE, pa.Table.from_pylist(rows, schema=tables["tubes"].schema))
    write_sequence(store, "tube_frames", DATASET, SEQUENCE,
                   pa.Table.from_pylist(frames, schema=tables["tube_frames"].schema))
    return calls
