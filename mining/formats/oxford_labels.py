"""Reader of the 4D-GVT "oxford-unknown" RobotCar labels (shared/data/SOURCES.md §4).

Layout: ``<root>/<traversal>_sub_<NNNN>/postproc_<frame>.json``, each a JSON list of
``{"category": car|person|bike|bus|other, "extreme_points": [[x, y] × 4], "mask": null,
"pos3d": [x, y, z] (or three nulls), "track_id": int}``. Extreme points are in 1280×960 "postproc" image
pixels in no fixed order; the box is their min/max (as the original evaluation takes it).
Known = the four COCO-covered categories; "other" holds the unknown objects (signs, poles,
cones, bins, …), the split of the original proposal-recall evaluation.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mining.errors import InputError
from mining.files import read_text

OXFORD_KNOWN = frozenset({"car", "person", "bike", "bus"})  # REFERENCE (original eval): known categories
OXFORD_UNKNOWN = frozenset({"other"})  # REFERENCE (original eval): the "others" curve
_FOLDER = re.compile(r"(.+)_sub_(\d+)")
_FILE = re.compile(r"postproc_(\d+)\.json")


@dataclass
class LabelledFrame:
    """The labelled objects of one RobotCar frame (N objects)."""

    traversal: str  # e.g. "2015-05-29-09-36-29"
    sub: int  # sub-sequence number of the folder name
    frame: int  # frame index from the file name
    path: Path
    boxes: np.ndarray  # (N, 4) float64 x1, y1, x2, y2 pixels, from the extreme points
    known: np.ndarray  # (N,) bool
    categories: list[str]
    track_ids: np.ndarray  # (N,) int64
    positions: np.ndarray  # (N, 3) float64 pos3d, camera metres; NaN rows where the file has nulls

    def __len__(self) -> int:
        return len(self.categories)


def read_oxford_labels(root: str | Path) -> list[LabelledFrame]:
    """Every label file under ``root`` (the ``labels_4dgvt`` folder or its parent), sorted."""
    root = Path(root)
    if (root / "labels_4dgvt").is_dir():
        root = root / "labels_4dgvt"
    if not root.is_dir():
        raise InputError("Oxford label folder does not exist", root)
    out = []
    for folder in sorted(p for p in root.iterdir() if p.is_dir()):
        m = _FOLDER.fullmatch(folder.name)
        if not m:
            raise InputError("folder name is not <traversal>_sub_<NNNN>", folder)
        for path in sorted(folder.iterdir()):
            f = _FILE.fullmatch(path.name)
            if not f:
                raise InputError("file name is not postproc_<frame>.json", path)
            out.append(read_oxford_label_file(path, m.group(1), int(m.group(2)), int(f.group(1))))
    return out


def read_oxford_label_file(path: Path, traversal: str, sub: int, frame: int) -> LabelledFrame:
    try:
        items = json.loads(read_text(path, "label file", frame))
    except json.JSONDecodeError as e:
        raise InputError(f"not valid JSON at line {e.lineno} column {e.colno}: {e.msg}", path, frame) from None
    except OSError as e:
        raise InputError(f"cannot read label file: {e.strerror or e}", path, frame) from None
    if not isinstance(items, list):
        raise InputError("expected a JSON list of objects", path, frame)
    n = len(items)
    boxes, pos, ids, cats = np.zeros((n, 4)), np.zeros((n, 3)), np.zeros(n, np.int64), []
    for i, it in enumerate(items):
        def bad(reason: str) -> InputError:
            return InputError(f"object {i}: {reason}", path, frame)

        if not isinstance(it, dict):
            raise bad("expected an object")
        cat = it.get("category")
        if cat not in OXFORD_KNOWN | OXFORD_UNKNOWN:
            raise bad(f"category {cat!r} is not one of {sorted(OXFORD_KNOWN | OXFORD_UNKNOWN)}")
        pts = it.get("extreme_points")
        if not (isinstance(pts, list) and len(pts) == 4
                and all(isinstance(p, list) and len(p) == 2 and all(_finite(v) for v in p) for p in pts)):
            raise bad("extreme_points must be four finite [x, y] pairs")
        xy = np.asarray(pts, np.float64)
        boxes[i] = [*xy.min(axis=0), *xy.max(axis=0)]
        p3 = it.get("pos3d")
        if p3 == [None, None, None]:  # the label has no 3D position (31 objects in the shared files)
            pos[i] = np.nan
        elif isinstance(p3, list) and len(p3) == 3 and all(_finite(v) for v in p3):
            pos[i] = p3
        else:
            raise bad(f"pos3d must be three finite numbers or three nulls, got {p3!r}")
        tid = it.get("track_id")
        if isinstance(tid, bool) or not isinstance(tid, int):
            raise bad(f"track_id {tid!r} is not an integer")
        ids[i] = tid
        cats.append(cat)
    known = np.array([c in OXFORD_KNOWN for c in cats], bool)
    return LabelledFrame(traversal, sub, frame, Path(path), boxes, known, cats, ids, pos)


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
