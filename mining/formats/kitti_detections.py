"""KITTI tracking detection files: PointRCNN's comma-separated files and the result format.

* PointRCNN (shared/data/SOURCES.md §1.6): one detection per line, 15 comma-separated
  columns ``frame, type, x1, y1, x2, y2, score, h, w, l, x, y, z, rotation_y, alpha`` with
  type codes 1 Pedestrian, 2 Car, 3 Cyclist.
* The 18-column KITTI tracking result format (§1.5), read by ``kitti_tracking``.

A file is recognised by its first non-blank line: commas → PointRCNN. Both come back as
``KittiTrackingRows``; PointRCNN rows carry track id −1 (untracked) and −1 truncation and
occlusion (the file has none).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from mining.errors import InputError
from mining.files import read_text
from mining.formats.kitti_tracking import KittiTrackingRows, read_kitti_tracking

POINTRCNN_TYPES = {1: "Pedestrian", 2: "Car", 3: "Cyclist"}  # SOURCES.md §1.6 type codes
POINTRCNN_COLUMNS = 15  # frame, type, x1 y1 x2 y2, score, h w l, x y z, rot_y, alpha


def read_kitti_detections(path: str | Path) -> KittiTrackingRows:
    """The detections of one file, in either format (see the module docstring)."""
    path = Path(path)
    try:
        text = read_text(path, "detections file")
    except OSError as e:
        raise InputError(f"cannot read detections: {e.strerror or e}", path) from None
    first = next((line for line in text.splitlines() if line.strip()), "")
    if "," in first:
        return read_pointrcnn(path, text)
    return read_kitti_tracking(path, require_score=True)


def read_pointrcnn(path: Path, text: str) -> KittiTrackingRows:
    """PointRCNN rows from the text of ``path``."""
    lines = [(no, line) for no, line in enumerate(text.splitlines(), 1) if line.strip()]
    for no, line in lines:
        if line.count(",") != POINTRCNN_COLUMNS - 1:
            raise InputError(f"line {no}: expected {POINTRCNN_COLUMNS} comma-separated columns, "
                             f"got {line.count(',') + 1}", path, _leading_int(line))
    if not lines:
        table = np.zeros((0, POINTRCNN_COLUMNS))
    else:
        try:
            table = np.array(",".join(line for _, line in lines).split(","), dtype=np.float64)
        except ValueError:  # find the culprit only on failure; parsing stays vectorised
            for no, line in lines:
                try:
                    [float(v) for v in line.split(",")]
                except ValueError:
                    raise InputError(f"line {no}: a column is not a number", path, _leading_int(line)) from None
            raise
        table = table.reshape(-1, POINTRCNN_COLUMNS)
    frame, code = table[:, 0], table[:, 1]
    bad = ~((frame >= 0) & (frame == np.round(frame)) & np.isin(code, list(POINTRCNN_TYPES)))
    bad |= ~np.isfinite(table[:, 2:7]).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(f"line {lines[i][0]}: frame must be a non-negative integer, type one of "
                         f"{sorted(POINTRCNN_TYPES)}, box and score finite", path, _leading_int(lines[i][1]))
    names = np.array([POINTRCNN_TYPES.get(c, "") for c in range(max(POINTRCNN_TYPES) + 1)], dtype=str)
    n = len(table)
    return KittiTrackingRows(
        path=path,
        frame=frame.astype(np.int64),
        track_id=np.full(n, -1, np.int64),
        type=names[code.astype(np.int64)],
        truncated=np.full(n, -1.0),
        occluded=np.full(n, -1.0),
        alpha=table[:, 14],
        box=table[:, 2:6],
        dimensions=table[:, 7:10],
        location=table[:, 10:13],
        rotation_y=table[:, 13],
        score=table[:, 6],
    )


def _leading_int(line: str) -> int | None:
    head = re.split(r"[,\s]", line.strip(), maxsplit=1)[0]
    return int(head) if head.isdigit() else None
