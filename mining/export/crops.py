"""`mine export --format crops`: per tube, the left image around its box and its mask, each frame.

Per tube ``<dest>/<tube_id with / → _>/crop_<frame>.png`` (the left image around the box,
with ``--margin`` context: a fraction of the box's width / height on each side) and
``mask_<frame>.png``, frame numbers zero-padded (``crop_000010.png``: the sequence's largest
frame number's digits, at least 6, so names sort in frame order), plus
``<dest>/index.parquet`` and ``index.json``: every ``tubes`` column, the crop folder, and per
frame (``track``) the box as x1, y1, x2, y2 and COCO x, y, w, h, the 3D position in the
camera and the world, the crop and mask file names and the crop's rectangle in the frame.
Images are re-read through the source named in ``OUT/job.json``, each frame once; a mask
that is malformed or of another size than its frame stops the export naming the tube.
"""

from __future__ import annotations

import json
from datetime import datetime
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from mining.catalog.labels import utc_text
from mining.catalog.rows import decode_mask
from mining.config import JobConfig
from mining.errors import InputError
from mining.export.selection import by_sequence, frame_digits, frames_by_tube, job_source
from mining.names import inside, tube_folder
from mining.progress import Ticker

CROP_MARGIN = 0.15  # ours: context around the box, as a fraction of the box's width / height
CROP_MARGIN_MIN_PX = 8  # ours: at least this much context for small boxes


def crop_box(bbox, width: int, height: int, margin: float = CROP_MARGIN) -> tuple[int, int, int, int]:
    """Pixel rectangle [x0, x1) × [y0, y1) around a box, with ``margin`` (a fraction of the
    box's width / height, at least CROP_MARGIN_MIN_PX) on every side, inside the image."""
    x1, y1, x2, y2 = (float(v) for v in bbox)
    mx = max(margin * (x2 - x1), CROP_MARGIN_MIN_PX)
    my = max(margin * (y2 - y1), CROP_MARGIN_MIN_PX)
    x0, x1_ = int(np.floor(max(0.0, x1 - mx))), int(np.ceil(min(float(width), x2 + mx)))
    y0, y1_ = int(np.floor(max(0.0, y1 - my))), int(np.ceil(min(float(height), y2 + my)))
    return x0, max(x1_, x0 + 1), y0, max(y1_, y0 + 1)


def tube_folders(tubes: pa.Table, dest: Path) -> dict[str, Path]:
    """tube id → its crop folder inside DEST; an InputError for an unsafe id or two tubes
    that would share a folder."""
    out: dict[str, Path] = {}
    owner: dict[str, str] = {}
    for tid in tubes.column("tube_id").to_pylist():
        name = tube_folder(tid)
        if owner.setdefault(name, tid) != tid:
            raise InputError(f"tubes {owner[name]!r} and {tid!r} would share the crop folder {name!r}", dest)
        out[tid] = inside(dest, name)
    return out


def _write_png(path: Path, image: np.ndarray) -> None:
    if not cv2.imwrite(str(path), image):
        raise InputError("cannot write PNG", path)


def crop_names(frame: int, digits: int) -> tuple[str, str]:
    """(crop, mask) file names of a tube's crop at ``frame``: ``crop_000010.png``, ``mask_000010.png``."""
    return f"crop_{frame:0{digits}d}.png", f"mask_{frame:0{digits}d}.png"


def export_crops(tubes: pa.Table, frames: pa.Table, job: JobConfig | None, dest: Path,
                 margin: float = CROP_MARGIN) -> int:
    """Per-tube crop and mask PNGs plus the index; returns the crops written."""
    if not margin >= 0:
        raise InputError(f"--margin must be a fraction ≥ 0 of the box, got {margin}")
    folders = tube_folders(tubes, dest)  # every id checked before anything is written
    sequences = by_sequence(tubes)
    source = job_source(job, "crops")
    root = job.source.root
    per_tube = frames_by_tube(frames)
    files: dict[tuple[str, int], dict] = {}  # (tube, frame) → what the index records of its crop
    n = 0
    for (_, sequence), seq_tubes in sequences.items():
        plan = source.plan(sequence)
        position = {f: p for p, f in enumerate(plan.frames)}
        digits = frame_digits(plan.frames)
        wanted: dict[int, list[dict]] = {}  # frame → the tube frames that need it
        for t in seq_tubes:
            folders[t["tube_id"]].mkdir(parents=True, exist_ok=True)
            for f in per_tube.get(t["tube_id"], []):
                wanted.setdefault(f["frame"], []).append(f)
        ticker = Ticker(f"crops of {sequence}", len(wanted))
        for k, frame in enumerate(sorted(wanted)):
            ticker.tick(k)
            if frame not in position:
                raise InputError(f"frame {frame} of the catalogue is not in the source's sequence {sequence!r}",
                                 root, frame)
            image = source.read_frame(plan, position[frame]).left
            h, w = image.shape[:2]
            for f in wanted[frame]:
                mask = decode_mask(f, (h, w), root)
                x0, x1, y0, y1 = crop_box(f["bbox"], w, h, margin)
                folder = folders.get(f["tube_id"])
                if folder is None:
                    raise InputError(f"tube_frames row of tube {f['tube_id']!r}, which the tubes table lacks",
                                     root, frame)
                crop_name, mask_name = crop_names(frame, digits)
                _write_png(folder / crop_name, cv2.cvtColor(image[y0:y1, x0:x1], cv2.COLOR_RGB2BGR))
                _write_png(folder / mask_name, mask[y0:y1, x0:x1] * np.uint8(255))
                files[(f["tube_id"], frame)] = {"crop": crop_name, "mask": mask_name, "crop_box": [x0, y0, x1, y1]}
                n += 1
        ticker.close()
    write_index(tubes, per_tube, dest, files)
    return n


_TRACK_TYPE = pa.list_(pa.struct([
    ("frame", pa.int32()), ("t_ns", pa.int64()), ("observed", pa.bool_()),
    ("bbox", pa.list_(pa.float32(), 4)),  # x1, y1, x2, y2 pixels (the catalogue's convention)
    ("bbox_xywh", pa.list_(pa.float32(), 4)),  # COCO x, y, width, height
    ("position_cam", pa.list_(pa.float32(), 3)),  # camera metres of this frame (x right, y down, z forward)
    ("position_world", pa.list_(pa.float32(), 3)),  # world metres of the tube's segment
    ("crop", pa.string()), ("mask", pa.string()),  # file names in the tube's folder
    ("crop_box", pa.list_(pa.int32(), 4)),  # the crop's pixels in the frame: x0, y0, x1, y1 (exclusive)
]))


def write_index(tubes: pa.Table, per_tube: dict[str, list[dict]], dest: Path,
                files: dict[tuple[str, int], dict] | None = None) -> None:
    """index.parquet and index.json: the tubes' columns, crop folder and per frame the box,
    3D position and crop files (``track``)."""
    files = files or {}

    def entry(f: dict) -> dict:
        x1, y1, x2, y2 = (float(v) for v in f["bbox"])
        crop = files.get((f["tube_id"], f["frame"]), {})
        return {"frame": f["frame"], "t_ns": f["t_ns"], "observed": f["observed"], "bbox": [x1, y1, x2, y2],
                "bbox_xywh": [x1, y1, x2 - x1, y2 - y1], "position_cam": f["position_cam"],
                "position_world": f["position_world"], "crop": crop.get("crop"), "mask": crop.get("mask"),
                "crop_box": crop.get("crop_box")}

    tracks = [[entry(f) for f in per_tube.get(tid, [])] for tid in tubes.column("tube_id").to_pylist()]
    index = tubes.append_column("folder", pa.array([tube_folder(t) for t in tubes.column("tube_id").to_pylist()],
                                                   pa.string()))
    index = index.append_column("track", pa.array(tracks, _TRACK_TYPE))
    pq.write_table(index, dest / "index.parquet", compression="zstd")

    def clean(v):
        if isinstance(v, datetime):  # a label time (labelled_at): UTC text, as tube_labels.json writes it
            return utc_text(v)
        if isinstance(v, float) and not np.isfinite(v):
            return None
        if isinstance(v, list):
            return [clean(x) for x in v]
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        return v

    (dest / "index.json").write_text(json.dumps([clean(r) for r in index.to_pylist()], indent=1) + "\n")
