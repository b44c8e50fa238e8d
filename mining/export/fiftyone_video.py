"""`mine export --format fiftyone`: the tubes as a FiftyOne video dataset on disk, in
FiftyOne's own ``FiftyOneVideoLabelsDataset`` layout (``fiftyone.types``), which
``fo.Dataset.from_dir(DEST, fo.types.FiftyOneVideoLabelsDataset)`` imports:

* ``DEST/manifest.json`` — the index (ETA's ``LabeledDatasetIndex``): one record per
  sequence, ``data`` (its video) and ``labels`` (its labels file), relative to DEST;
* ``DEST/labels/<dataset>_<sequence>.json`` — ETA's ``VideoLabels``: the video's metadata
  (frame size, rate, count), its attributes (``dataset``, ``sequence``), and per video
  frame (1-based) the ``source_frame`` it shows and one ``DetectedObject`` per tube there;
* ``DEST/data/<dataset>_<sequence>.mp4`` — with ``--images``: the rectified left frames,
  re-read through the job's source (H.264 with PyAV, else OpenCV's MPEG-4: ``video.py``).
  Without it no video is written and the manifest still names where it goes: FiftyOne
  reads the labels without the media (an importer opens a video only for its metadata,
  which the labels carry), so an export made where the source frames are not reachable
  stays readable.

The video frames are the ones the catalogue mined (the ``frames`` table), as YouTube-VIS's
and TAO's are. The video has even sides (4:2:0; KITTI's 375 rows → 376, the last black) and
the labels' frame size is the video's, so relative boxes place the masks on the right pixels.

A detection: ``label`` the category by the tube's call (a known tube's COCO
class, ``unknown``, ``clutter``, ``unclassified``), ``confidence`` the tube's ``category_prob`` (none
when unclassified), ``index`` the tube's track id (0, 1, … per sequence in catalogue order:
the KITTI exports' ids), and attributes ``tube_id``, ``score`` (the catalogue's ``score``)
and ``observed``. FiftyOne keeps an instance mask inside its box, so the box is the pixel
grid box that holds both the catalogue's box and every mask pixel, and the mask is the
catalogue's mask cut to it: the same pixels, none lost. With the job's
``export.observed_only`` (the default) frames where a tube is only predicted have no
detection, as in the other tracking exports.

The export writes JSON (ETA's mask encoding: ``np.save`` bytes, zlib, base64) and needs no
FiftyOne; reading it does (``pip install 'tube-miner[fiftyone]'``).
"""

from __future__ import annotations

import base64
import io
import json
import math
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow as pa

from mining.catalog import safe_files
from mining.catalog.rows import decode_mask
from mining.config import JobConfig
from mining.export.selection import Video, category_label, export_settings, frames_by_tube, videos
from mining.export.source_frames import even_size, frame_rate, pad_even, read_frames
from mining.export.video import check_video, open_video
from mining.progress import Ticker

MANIFEST, LABELS, DATA = "manifest.json", "labels", "data"  # REFERENCE: FiftyOneVideoLabelsDataset's layout
DATASET_TYPE = "eta.core.datasets.LabeledVideoDataset"  # REFERENCE: the manifest's "type" FiftyOne's exporter writes
OBJECT_TYPE = "eta.core.objects.DetectedObject"  # REFERENCE: ETA's class names, as its JSON names them
NUMERIC, CATEGORICAL, BOOLEAN = ("eta.core.data.NumericAttribute", "eta.core.data.CategoricalAttribute",
                                 "eta.core.data.BooleanAttribute")
VIDEO_SUFFIX, VIDEO_MIME = ".mp4", "video/mp4"  # ours: `video.py`'s MP4 (H.264 where PyAV is installed)
COORD_DECIMALS = 9  # ours: relative box corners to 1e-9 of the frame (sub-pixel for any real frame)


def _attr(kind: str, name: str, value) -> dict:
    return {"type": kind, "name": name, "value": value}


def eta_mask(mask: np.ndarray) -> str:
    """ETA's serialised array: the ``np.save`` bytes, zlib-compressed, base64 text."""
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(mask), allow_pickle=False)
    return base64.b64encode(zlib.compress(buf.getvalue())).decode("ascii")


def mask_box(mask: np.ndarray, bbox) -> tuple[int, int, int, int]:
    """The pixel grid box (x0, y0, x1, y1; x1, y1 exclusive) holding the catalogue's box
    ``bbox`` (x1, y1, x2, y2, float) and every pixel of ``mask``, inside the frame, at least
    one pixel wide and high."""
    h, w = mask.shape
    x0, y0 = math.floor(float(bbox[0])), math.floor(float(bbox[1]))
    x1, y1 = math.ceil(float(bbox[2])), math.ceil(float(bbox[3]))
    ys, xs = np.nonzero(mask)
    if xs.size:
        x0, y0 = min(x0, int(xs.min())), min(y0, int(ys.min()))
        x1, y1 = max(x1, int(xs.max()) + 1), max(y1, int(ys.max()) + 1)
    x0, y0 = min(max(x0, 0), w - 1), min(max(y0, 0), h - 1)
    return x0, y0, min(max(x1, x0 + 1), w), min(max(y1, y0 + 1), h)


def detected_object(tube: dict, track: int, row: dict, frame_number: int, size: tuple[int, int]) -> dict:
    """One tube in one video frame as an ETA ``DetectedObject`` (``size``: the video's width, height)."""
    mask = decode_mask(row).astype(bool)
    x0, y0, x1, y1 = mask_box(mask, row["bbox"])
    vw, vh = size
    prob = tube["category_prob"]
    return {"type": OBJECT_TYPE, "label": category_label(tube),
            "bounding_box": {"top_left": {"x": round(x0 / vw, COORD_DECIMALS), "y": round(y0 / vh, COORD_DECIMALS)},
                             "bottom_right": {"x": round(x1 / vw, COORD_DECIMALS), "y": round(y1 / vh, COORD_DECIMALS)}},
            "mask": eta_mask(mask[y0:y1, x0:x1]),
            **({"confidence": float(prob)} if prob is not None else {}),
            "index": track, "frame_number": frame_number,
            "attrs": {"attrs": [_attr(CATEGORICAL, "tube_id", tube["tube_id"]),
                                _attr(NUMERIC, "score", float(tube["score"])),
                                _attr(BOOLEAN, "observed", bool(row["observed"]))]}}


def video_labels(v: Video, per_tube: dict[str, list[dict]], observed_only: bool, fps: float) -> dict:
    """ETA ``VideoLabels`` of one sequence: metadata, attributes, and every video frame."""
    size = even_size(v.width, v.height)
    number = {f: k + 1 for k, f in enumerate(v.frames)}  # ETA numbers video frames from 1
    objects: dict[int, list[dict]] = {}
    for track, t in enumerate(v.tubes):
        for row in per_tube.get(t["tube_id"], []):
            if row["observed"] or not observed_only:
                n = number[row["frame"]]
                objects.setdefault(n, []).append(detected_object(t, track, row, n, size))
    frames = {}
    for f, n in number.items():
        frames[str(n)] = {"frame_number": n, "attrs": {"attrs": [_attr(NUMERIC, "source_frame", f)]}}
        if n in objects:
            frames[str(n)]["objects"] = {"objects": objects[n]}
    return {"metadata": {"frame_size": list(size), "frame_rate": fps, "total_frame_count": len(v.frames),
                         "mime_type": VIDEO_MIME},
            "attrs": {"attrs": [_attr(CATEGORICAL, "dataset", v.dataset), _attr(CATEGORICAL, "sequence", v.sequence)]},
            "frames": frames}


def write_video(job: JobConfig | None, v: Video, dest: Path, fps: float, tick: Callable[[], None]) -> None:
    """``dest/data/<video>.mp4``: the video's frames re-read through the job's source, padded
    to even sides; written in a private folder (the encoder opens it by path), read back,
    then moved in."""
    _, pairs = read_frames(job, v.sequence, v.frames, (v.height, v.width), "--images")
    safe_files.make_folder(dest, DATA)
    work = safe_files.private_dir(dest, ".video-")
    try:
        name = v.name + VIDEO_SUFFIX
        size = even_size(v.width, v.height)
        writer = open_video(work / name, fps, size)
        try:
            for pair in pairs:
                writer.write(np.ascontiguousarray(pad_even(pair.left)[:, :, ::-1]))  # RGB → BGR
                tick()
        finally:
            writer.close()
        check_video(work / name, len(v.frames), size)
        safe_files.move_in(work, name, dest / DATA)
    finally:
        safe_files.remove_tree(work)


def export_fiftyone(tubes: pa.Table, frames: pa.Table, job: JobConfig | None, dest: Path,
                    video_frames: dict[tuple[str, str], list[int]] | None = None, images: bool = False) -> int:
    """``DEST/manifest.json`` and ``DEST/labels/`` (and ``DEST/data/`` with ``images``);
    returns the videos (sequences) written."""
    observed_only = export_settings(job).observed_only
    per_tube = frames_by_tube(frames)
    vids = videos(tubes, frames, video_frames or {})
    ticker = Ticker("fiftyone videos", sum(len(v.frames) for v in vids)) if images else None
    done = [0]

    def tick() -> None:
        done[0] += 1
        ticker.tick(done[0])
    index = []
    for v in vids:
        times = {f["frame"]: f["t_ns"] for t in v.tubes for f in per_tube.get(t["tube_id"], [])}
        fps = frame_rate(times)
        labels = f"{LABELS}/{v.name}.json"
        safe_files.write_atomic(dest, labels, (json.dumps(video_labels(v, per_tube, observed_only, fps)) + "\n").encode())
        if images:
            write_video(job, v, dest, fps, tick)
        index.append({"data": f"{DATA}/{v.name}{VIDEO_SUFFIX}", "labels": labels})
    if ticker is not None:
        ticker.close()
    manifest = {"type": DATASET_TYPE, "description": "Tube Miner tubes (fiftyone export)", "index": index}
    safe_files.write_atomic(dest, MANIFEST, (json.dumps(manifest, indent=1) + "\n").encode())
    return len(vids)
