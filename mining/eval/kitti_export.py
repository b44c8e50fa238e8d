"""Mined tubes → KITTI tracking result txt (for `mine eval kitti-mot` and TrackEval)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mining.eval.kitti_labels import KittiTrackingRows, write_kitti_tracking

# COCO category → KITTI type; everything else is written as Misc (KITTI MOT ignores it).
KITTI_TYPE = {"car": "Car", "person": "Pedestrian", "bicycle": "Cyclist", "motorcycle": "Cyclist",
              "truck": "Truck", "bus": "Truck", "train": "Tram"}


def tubes_to_kitti_rows(mined, rect0_from_cam2=None, observed_only: bool = True,
                        unclassified_as: str = "Misc") -> KittiTrackingRows:
    """One row per frame of each selected tube; the score column is the tube's score.

    ``rect0_from_cam2`` maps image_02 camera points to KITTI's rectified camera 0 (the
    frame of KITTI's 3D fields); without it the 3D fields are placeholders.
    """
    rows = []
    for m in mined:
        if not m.selected:
            continue
        # A KITTI result names the detector's best class; known-ness is a separate question.
        kind = KITTI_TYPE.get(m.category.best_known, "Misc") if m.category.posterior is not None else unclassified_as
        for f in m.tube.frames:
            if observed_only and not f.observed:
                continue
            size = f.size
            if rect0_from_cam2 is not None and np.isfinite(f.position_cam).all():
                bottom = f.position_cam + np.array([0.0, size[1] / 2, 0.0])
                loc = rect0_from_cam2(bottom[None])[0]
                dims = (size[1], size[0], size[2])
            else:
                loc, dims = (-1000.0, -1000.0, -1000.0), (-1.0, -1.0, -1.0)
            rows.append((f.frame, m.tube.tube_id, kind, f.box, dims, loc, m.score.total))
    rows.sort(key=lambda r: (r[0], r[1]))
    return KittiTrackingRows.results("<tubes>", [r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows],
                                     [r[3] for r in rows], [r[6] for r in rows],
                                     dimensions=[r[4] for r in rows], location=[r[5] for r in rows])


def write_tubes_kitti(path: str | Path, mined, rect0_from_cam2=None, observed_only: bool = True,
                      unclassified_as: str = "Misc") -> int:
    rows = tubes_to_kitti_rows(mined, rect0_from_cam2, observed_only, unclassified_as)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_kitti_tracking(path, rows, with_score=True)
    return len(rows)
