"""The baseline the tube stage must beat: a plain frame-to-frame 2D-IoU Hungarian tracker.

Each frame, detections (above a score threshold) are matched to the tracks of the
previous frame by Hungarian assignment on box IoU; a match needs IoU ≥ ``min_iou``.
Unmatched detections start tracks; a track not matched in a frame ends. No motion model,
no 3D, no gaps bridged.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from mining.boxes import box_iou
from mining.formats.kitti_tracking import KittiTrackingRows, write_kitti_tracking
from mining.proposals.precomputed import KittiDetections

KITTI_TYPE_OF_CLASS = {0: "Pedestrian", 1: "Cyclist", 2: "Car"}  # COCO person, bicycle, car


def iou_track(dets: KittiDetections, n_frames: int, min_objectness: float = 0.5, min_iou: float = 0.3) -> KittiTrackingRows:
    """Track one sequence's detections; returns KITTI tracking rows."""
    next_id = 0
    prev_boxes = np.zeros((0, 4))
    prev_ids = np.zeros(0, np.int64)
    prev_cls = np.zeros(0, np.int64)
    out = []
    for frame in range(n_frames):
        p = dets(frame)
        keep = p.objectness >= min_objectness
        boxes = p.boxes[keep].astype(np.float64)
        cls = np.argmax(p.posterior[keep, :80], axis=1) if len(boxes) else np.zeros(0, np.int64)
        score = p.objectness[keep]
        ids = np.full(len(boxes), -1, np.int64)
        if len(boxes) and len(prev_boxes):
            iou = box_iou(prev_boxes, boxes)
            iou[prev_cls[:, None] != cls[None, :]] = 0.0  # never link across classes
            r, c = linear_sum_assignment(-iou)
            ok = iou[r, c] >= min_iou
            ids[c[ok]] = prev_ids[r[ok]]
        for k in np.flatnonzero(ids < 0):
            ids[k] = next_id
            next_id += 1
        for b, i, c, s in zip(boxes, ids, cls, score):
            out.append((frame, i, KITTI_TYPE_OF_CLASS.get(int(c), "Misc"), b, s))
        prev_boxes, prev_ids, prev_cls = boxes, ids, cls
    return KittiTrackingRows.results("<iou-tracker>", [o[0] for o in out], [o[1] for o in out],
                                     [o[2] for o in out], [o[3] for o in out], [o[4] for o in out])


def write_iou_tracks(path: str | Path, rows: KittiTrackingRows) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_kitti_tracking(path, rows, with_score=True)
