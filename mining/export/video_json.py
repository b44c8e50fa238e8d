"""`mine export --format youtube-vis | tao`: the tubes as video instance segmentation and
open-world tracking annotations, the JSON that VIS and TAO tools read (BURST: ``burst.py``).

Each format writes both files its evaluation needs: the **dataset** file (the tubes as
ground truth, the format's annotation layout) and, in ``DEST/results/``, the **results**
file (the same tubes as a tracker's output, the format's results layout, with scores). So the
export scored against itself is perfect, and the results file can be scored against a real
dataset's annotations (and the dataset file used to score another tracker).

One video per sequence. Its frames are the ones the catalogue mined (the ``frames`` table,
in plan order); ``file_names`` / ``file_name`` name them ``<video>/<frame, zero-padded>.jpg``
relative to an image folder in DEST, which ``--images`` fills with the rectified left
frames re-read through the job's source (the frames the masks are drawn on). Boxes are COCO
``[x, y, width, height]`` from the catalogue's ``x1, y1, x2, y2``; areas are the masks' pixel
counts. With the job's ``export.observed_only`` (the default) a frame where a tube is only
predicted (a gap) has no annotation (null in YouTube-VIS), as in the KITTI exports.

Categories follow the tube's call (``mining.score.call``): a known tube's COCO class with its
COCO annotation id (``mining/formats/coco.py``); ``unknown``, ``clutter`` and ``unclassified``
their own ids (``json_annotations.OWN_IDS``), outside COCO's 1..90. Only the
categories some exported tube has are listed: an evaluator averages over the categories a
dataset lists, and an empty one would count as a failed class. Every annotation carries the
tube's score (its weighted total, not a probability) and tube id.

* ``youtube-vis`` — ``DEST/instances.json`` in the YouTube-VIS 2021 layout (``videos``:
  id, name, width, height, length, file_names; ``annotations``: id, video_id,
  category_id, segmentations / bboxes / areas with one entry or null per video frame,
  iscrowd 0, score; ``categories``: id, name, supercategory). Its masks are *uncompressed*
  RLE (``counts`` a list of run lengths), as YouTube-VIS's own annotations and its readers
  (``pycocotools.mask.frPyObjects``, TrackEval) take them. ``DEST/results/results.json``: the
  YouTube-VIS results list (video_id, category_id, score, segmentations as compressed RLE,
  ``counts`` a string, or null per frame). Images in ``DEST/JPEGImages/``.
* ``tao`` — ``DEST/tao.json`` in TAO's layout (``videos``, ``images`` (id, video_id,
  file_name, width, height, frame_index), ``tracks`` (id, category_id, video_id),
  ``annotations`` (id, image_id, video_id, track_id, category_id, bbox, area, iscrowd, plus
  the compressed RLE ``segmentation`` and a ``score``), ``categories`` (id, name, synset)).
  ``DEST/results/results.json``: TAO's results list, one detection per tube frame (image_id,
  video_id, track_id, category_id, bbox, score, segmentation). Images in ``DEST/frames/``.
  TAO's categories are LVIS's; ours keep COCO's ids, each with the WordNet synset LVIS names
  the class by (``mining/formats/lvis.py``), so a TAO tool can map them to LVIS; the two own
  categories carry ``OWN_SYNSETS`` (no WordNet sense: a discovered object has none yet).
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
from pycocotools import mask as mask_utils

from mining.catalog.rows import mask_rle
from mining.config import JobConfig
from mining.export.json_annotations import (OWN_IDS, OWN_SYNSETS, RESULTS_DIR, RESULTS_JSON, TAG_SUPERCATEGORY,
                                            TAG_SYNSET, TAO_IMAGES, area, category_id, info, tag_categories,
                                            write_json)
from mining.export.selection import video_tubes, videos
from mining.export.source_frames import ticking, write_images
from mining.formats.coco import CLASS_INDEX, COCO_CATEGORY_IDS
from mining.formats.lvis import synset

BOX_DECIMALS = 3  # ours: JSON boxes to 1/1000 px (the catalogue stores float32)
YTVIS_JSON, YTVIS_IMAGES = "instances.json", "JPEGImages"  # the YouTube-VIS 2021 split layout
TAO_JSON = "tao.json"  # TAO's images folder: json_annotations.TAO_IMAGES


def xywh(bbox) -> list[float]:
    """COCO ``[x, y, width, height]`` of the catalogue's ``x1, y1, x2, y2``."""
    x1, y1, x2, y2 = (float(v) for v in bbox)
    return [round(x1, BOX_DECIMALS), round(y1, BOX_DECIMALS), round(x2 - x1, BOX_DECIMALS), round(y2 - y1, BOX_DECIMALS)]


def categories(used: set[int], tao: bool = False, tags: dict[str, int] | None = None) -> list[dict]:
    """The categories among ``used`` (by id), COCO's first, then the calls', then the tags'
    (``json_annotations.tag_categories``); YouTube-VIS entries carry a supercategory ("coco" /
    "mined" / "tag"), TAO entries the class's synset."""
    names = {COCO_CATEGORY_IDS[i]: name for name, i in CLASS_INDEX.items()}
    rows = [(c, names[c], "coco") for c in sorted(used) if c in names]
    rows += [(c, n, "mined") for n, c in sorted(OWN_IDS.items(), key=lambda kv: kv[1]) if c in used]
    rows += [(c, n, TAG_SUPERCATEGORY) for n, c in sorted((tags or {}).items(), key=lambda kv: kv[1]) if c in used]

    def tao_synset(n: str, g: str) -> str:
        return OWN_SYNSETS[n] if g == "mined" else f"{TAG_SYNSET}:{n}" if g == TAG_SUPERCATEGORY else synset(n)
    if tao:
        return [{"id": c, "name": n, "synset": tao_synset(n, g)} for c, n, g in rows]
    return [{"id": c, "name": n, "supercategory": g} for c, n, g in rows]


def rle(f: dict) -> dict:
    """The row's compressed RLE as the JSON carries it (counts a string); ``area`` has checked it."""
    return {"size": [f["rle_h"], f["rle_w"]], "counts": f["rle_counts"]}


def uncompressed_rle(f: dict) -> dict:
    """The row's mask as uncompressed RLE: ``counts`` the run lengths of the column-major
    pixels, zeros first (COCO's RLE before compression)."""
    pixels = mask_utils.decode(mask_rle(f)).ravel(order="F")
    edges = np.flatnonzero(pixels[1:] != pixels[:-1]) + 1
    runs = np.diff(np.concatenate(([0], edges, [pixels.size])))
    if pixels.size and pixels[0]:
        runs = np.concatenate(([0], runs))
    return {"size": [f["rle_h"], f["rle_w"]], "counts": [int(r) for r in runs]}


def export_youtube_vis(tubes: pa.Table, frames: pa.Table, job: JobConfig | None, dest: Path,
                       video_frames: dict[tuple[str, str], list[int]] | None = None, images: bool = False) -> int:
    """``DEST/instances.json``, ``DEST/results/results.json`` (and ``DEST/JPEGImages/`` with
    ``images``); returns the annotations (tubes) written."""
    vids = videos(tubes, frames, video_frames or {})
    out_videos = [{"id": v.id, "name": v.name, "width": v.width, "height": v.height, "length": len(v.frames),
                   "file_names": [v.file_name(f) for f in v.frames]} for v in vids]
    anns, results, used = [], [], set()
    tags = tag_categories(tubes.to_pylist())
    for v, t, at in video_tubes(vids, frames, job):
        cid = category_id(t, tags)
        used.add(cid)
        areas = [area(at[f]) if f in at else None for f in v.frames]  # checks every mask before it is copied
        anns.append({"id": len(anns) + 1, "video_id": v.id, "category_id": cid, "iscrowd": 0,
                     "width": v.width, "height": v.height, "length": 1,
                     "segmentations": [uncompressed_rle(at[f]) if f in at else None for f in v.frames],
                     "bboxes": [xywh(at[f]["bbox"]) if f in at else None for f in v.frames],
                     "areas": areas, "score": float(t["score"]), "tube_id": t["tube_id"]})
        results.append({"video_id": v.id, "category_id": cid, "score": float(t["score"]),
                        "segmentations": [rle(at[f]) if f in at else None for f in v.frames],
                        "tube_id": t["tube_id"]})
    doc = {"info": info(job, "youtube-vis"), "licenses": [], "videos": out_videos, "annotations": anns,
           "categories": categories(used, tags=tags)}
    write_json(dest / YTVIS_JSON, doc)
    write_json(dest / RESULTS_DIR / RESULTS_JSON, results)
    if images:
        write_images(job, vids, dest / YTVIS_IMAGES, ticking("youtube-vis images"))
    return len(anns)


def export_tao(tubes: pa.Table, frames: pa.Table, job: JobConfig | None, dest: Path,
               video_frames: dict[tuple[str, str], list[int]] | None = None, images: bool = False) -> int:
    """``DEST/tao.json``, ``DEST/results/results.json`` (and ``DEST/frames/`` with ``images``);
    returns the annotations (tube frames) written."""
    vids = videos(tubes, frames, video_frames or {})
    out_videos, out_images, image_id = [], [], {}
    for v in vids:
        out_videos.append({"id": v.id, "name": v.name, "width": v.width, "height": v.height,
                           "neg_category_ids": [], "not_exhaustive_category_ids": [],
                           "metadata": {"dataset": v.dataset, "sequence": v.sequence}})
        for k, f in enumerate(v.frames):
            image_id[v.id, f] = len(out_images) + 1
            out_images.append({"id": image_id[v.id, f], "video_id": v.id, "file_name": v.file_name(f),
                               "width": v.width, "height": v.height, "frame_index": k, "frame": f})
    tracks, anns, results, used = [], [], [], set()
    tags = tag_categories(tubes.to_pylist())
    for v, t, at in video_tubes(vids, frames, job):
        cid = category_id(t, tags)
        used.add(cid)
        track_id = len(tracks) + 1
        score = float(t["score"])
        tracks.append({"id": track_id, "category_id": cid, "video_id": v.id, "score": score, "tube_id": t["tube_id"]})
        for frame, f in sorted(at.items()):
            box, a = xywh(f["bbox"]), area(f)
            anns.append({"id": len(anns) + 1, "image_id": image_id[v.id, frame], "video_id": v.id,
                         "track_id": track_id, "category_id": cid, "bbox": box, "area": a, "iscrowd": 0,
                         "segmentation": rle(f), "score": score})
            results.append({"image_id": image_id[v.id, frame], "video_id": v.id, "track_id": track_id,
                            "category_id": cid, "bbox": box, "score": score, "segmentation": rle(f)})
    doc = {"info": info(job, "tao"), "licenses": [], "videos": out_videos, "images": out_images, "tracks": tracks,
           "annotations": anns, "categories": categories(used, tao=True, tags=tags)}
    write_json(dest / TAO_JSON, doc)
    write_json(dest / RESULTS_DIR / RESULTS_JSON, results)
    if images:
        write_images(job, vids, dest / TAO_IMAGES, ticking("tao images"))
    return len(anns)
