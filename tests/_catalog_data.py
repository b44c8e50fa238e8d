"""A real small catalogue for the catalogue tests: KITTI tracking 0005, frames 0–15.

Tubes come from the detections-only pipeline (real PointRCNN detections, real ORB-SLAM3
egoposes, the project's tube generator, scorer and co-selection), converted into rows of
schema v1 here until the pipeline's own ``mining/catalog/rows.py`` is used instead. The
16 frames are the ones whose images are in shared/data, so crops can be exported.
"""

from __future__ import annotations

import json
from itertools import islice
from pathlib import Path

import numpy as np
import pyarrow as pa

from mining.catalog.schema import SCHEMA_VERSION, SCHEMAS, file_schema
from mining.catalog.store import Store, write_sequence
from mining.config import load_config

REPO = Path(__file__).resolve().parents[1]
DATASET, SEQUENCE, N_FRAMES = "kitti", "0005", 16
RUN_ID = "test-run"


def _nan_none(x: float):
    return None if x is None or not np.isfinite(x) else float(x)


def _counts(rle: dict) -> str:
    c = rle["counts"]
    return c.decode() if isinstance(c, bytes) else c


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
    """(tubes, tube_frames) rows of schema v1 (with partition columns) from mined tubes."""
    tubes, tf = [], []
    for m in mined:
        t, fr0 = m.tube, m.tube.frames[0]
        tube_id = f"{DATASET}/{SEQUENCE}/{fr0.frame}.{fr0.obs_index}"
        obs = [f for f in t.frames if f.observed]
        world = np.array([f.footpoint_world for f in t.frames])
        post = m.category.posterior
        tubes.append({
            "tube_id": tube_id, "dataset": DATASET, "sequence": SEQUENCE,
            "t_start": fr0.t_ns, "t_end": t.frames[-1].t_ns,
            "frame_start": t.first_frame, "frame_end": t.last_frame,
            "n_frames": len(t.frames), "n_observed": len(obs),
            "score": m.score.total, "score_motion": m.score.motion, "score_mask": m.score.mask,
            "score_objectness": m.score.objectness, "selected": m.selected, "known": m.category.known,
            "category": m.category.category, "category_prob": _nan_none(m.category.probability),
            "best_known": m.category.best_known,
            "class_posterior": None if post is None else [float(x) for x in post],
            "segment": t.segment,
            "mean_position": np.mean([f.footpoint_world for f in obs], axis=0).tolist(),
            "size": np.median([f.size for f in obs], axis=0).tolist(),
            "path_length": float(np.linalg.norm(np.diff(world, axis=0), axis=1).sum()),
            "speed": float(np.mean([np.linalg.norm(f.velocity_world) for f in t.frames])),
            "n_windows": 1, "run_id": RUN_ID, "params_hash": params_hash, "schema_version": SCHEMA_VERSION,
        })
        for f in t.frames:
            tf.append({
                "tube_id": tube_id, "dataset": DATASET, "sequence": SEQUENCE, "frame": f.frame, "t_ns": f.t_ns,
                "bbox": [float(x) for x in f.box], "rle_counts": _counts(f.rle),
                "rle_h": int(f.rle["size"][0]), "rle_w": int(f.rle["size"][1]),
                "observed": f.observed, "obs_index": f.obs_index, "objectness": _nan_none(f.objectness),
                "position_cam": f.position_cam.tolist(), "position_world": f.footpoint_world.tolist(),
                "velocity_world": f.velocity_world.tolist(), "size": f.size.tolist(),
                "mask_iou": _nan_none(f.mask_iou), "motion_density": _nan_none(f.motion_density),
            })
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
    return pa.Table.from_pylist([row], schema=file_schema("windows"))


def build_catalogue(out: Path, kitti_tracking_root: Path) -> dict:
    """Write the KITTI 0005 catalogue under ``out``; returns the tables written."""
    frames, mined, cfg = mined_kitti_0005(kitti_tracking_root)
    store = Store(out)
    tubes, tf = tube_rows(mined, cfg.params_hash)
    write_sequence(store, "tubes", DATASET, SEQUENCE, tubes)
    write_sequence(store, "tube_frames", DATASET, SEQUENCE, tf)
    write_sequence(store, "frames", DATASET, SEQUENCE, frame_rows(frames))
    store.write_table(store.manifest_path(DATASET, SEQUENCE, "w00000"), window_rows(cfg.params_hash))
    job = dict(cfg.to_dict(), run_id=RUN_ID, params_hash=cfg.params_hash)
    store.write_bytes("job.json", json.dumps(job, default=str).encode())
    return {"tubes": tubes, "tube_frames": tf, "mined": mined}
