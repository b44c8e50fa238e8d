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

Categories follow the ``known`` flag: a known tube's COCO class with its COCO annotation id
(``mining/formats/coco.py``); known false → ``unknown`` (id ``UNKNOWN_ID``); no
classifier → ``unclassified`` (``UNCLASSIFIED_ID``), both outside COCO's 1..90. Only the
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

import json
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
from pycocotools import mask as mask_utils

from mining.catalog.rows import mask_rle
from mining.config import JobConfig
from mining.errors import InputError
from mining.export.selection import by_sequence, category_label, export_settings, frame_digits, frames_by_tube, job_source
from mining.formats.coco import CLASS_INDEX, COCO_CATEGORY_IDS
from mining.formats.lvis import synset
from mining.names import inside
from mining.progress import Ticker

UNKNOWN_ID = 1000  # ours: category id of unknown tubes, outside COCO's 1..90
UNCLASSIFIED_ID = 1001  # ours: category id of unclassified tubes
# ours: the synsets of the two own categories; not WordNet names (no sense is known for them)
OWN_SYNSETS = {"unknown": "tube_miner.unknown", "unclassified": "tube_miner.unclassified"}
BOX_DECIMALS = 3  # ours: JSON boxes to 1/1000 px (the catalogue stores float32)
JPEG_QUALITY = 95  # ours: --images JPEG quality
YTVIS_JSON, YTVIS_IMAGES = "instances.json", "JPEGImages"  # the YouTube-VIS 2021 split layout
TAO_JSON, TAO_IMAGES = "tao.json", "frames"
# ours: the results (tracker) file of every video format, in a folder of its own: evaluators
# want one JSON in the ground-truth folder and one in the tracker's
RESULTS_DIR, RESULTS_JSON = "results", "results.json"


def video_name(dataset: str, sequence: str) -> str:
    """``<dataset>_<sequence>``: both are checked names (``selection.by_sequence``), so this is one."""
    return f"{dataset}_{sequence}"


def xywh(bbox) -> list[float]:
    """COCO ``[x, y, width, height]`` of the catalogue's ``x1, y1, x2, y2``."""
    x1, y1, x2, y2 = (float(v) for v in bbox)
    return [round(x1, BOX_DECIMALS), round(y1, BOX_DECIMALS), round(x2 - x1, BOX_DECIMALS), round(y2 - y1, BOX_DECIMALS)]


def category_id(tube: dict) -> int:
    """The COCO id of a known tube's class; UNKNOWN_ID / UNCLASSIFIED_ID otherwise."""
    label = category_label(tube)
    if label == "unknown":
        return UNKNOWN_ID
    if label == "unclassified":
        return UNCLASSIFIED_ID
    if label not in CLASS_INDEX:
        raise InputError(f"tube {tube['tube_id']} is known as {label!r}, which is not a COCO class")
    return COCO_CATEGORY_IDS[CLASS_INDEX[label]]


def categories(used: set[int], tao: bool = False) -> list[dict]:
    """The categories among ``used`` (by id), COCO's first; YouTube-VIS entries carry a
    supercategory ("coco" / "mined"), TAO entries the class's synset."""
    names = {COCO_CATEGORY_IDS[i]: name for name, i in CLASS_INDEX.items()}
    rows = [(c, names[c], "coco") for c in sorted(used) if c in names]
    rows += [(c, n, "mined") for c, n in ((UNKNOWN_ID, "unknown"), (UNCLASSIFIED_ID, "unclassified")) if c in used]
    if tao:
        return [{"id": c, "name": n, "synset": OWN_SYNSETS[n] if g == "mined" else synset(n)} for c, n, g in rows]
    return [{"id": c, "name": n, "supercategory": g} for c, n, g in rows]



class Video:
    """One sequence as a video: its frames (the catalogue's, in frame order), size and tubes."""

    def __init__(self, vid: int, dataset: str, sequence: str, frames: list[int], tubes: list[dict],
                 per_tube: dict[str, list[dict]]):
        self.id, self.dataset, self.sequence, self.tubes = vid, dataset, sequence, tubes
        self.name = video_name(dataset, sequence)
        sizes = {(f["rle_h"], f["rle_w"]) for t in tubes for f in per_tube.get(t["tube_id"], [])}
        if len(sizes) != 1:
            raise InputError(f"{dataset}/{sequence}: the tubes' masks have {len(sizes)} sizes {sorted(sizes)}; "
                             "a video has one")
        self.height, self.width = sizes.pop()
        seen = {f["frame"] for t in tubes for f in per_tube.get(t["tube_id"], [])}
        self.frames = sorted(set(frames) | seen)
        self.digits = frame_digits(self.frames)

    def image_name(self, frame: int) -> str:
        """``<frame, zero-padded>.jpg``."""
        return f"{frame:0{self.digits}d}.jpg"

    def file_name(self, frame: int) -> str:
        return f"{self.name}/{self.image_name(frame)}"


def videos(tubes: pa.Table, frames: pa.Table, video_frames: dict[tuple[str, str], list[int]]) -> list[Video]:
    """One Video per sequence of ``tubes``, numbered from 1; a sequence the ``frames`` table
    lacks spans its tubes' frames."""
    per_tube = frames_by_tube(frames)
    out = []
    for vid, ((dataset, sequence), seq_tubes) in enumerate(by_sequence(tubes).items(), start=1):
        out.append(Video(vid, dataset, sequence, video_frames.get((dataset, sequence), []), seq_tubes, per_tube))
    return out


def annotated(frames: list[dict], observed_only: bool) -> dict[int, dict]:
    """A tube's rows by frame, the frames it is annotated on (observed ones, or all)."""
    return {f["frame"]: f for f in frames if f["observed"] or not observed_only}


def video_tubes(vids: list[Video], frames: pa.Table, job: JobConfig | None) -> Iterator[tuple[Video, dict, dict[int, dict]]]:
    """(video, tube, its annotated rows by frame) of every tube, video by video."""
    observed_only = export_settings(job).observed_only
    per_tube = frames_by_tube(frames)
    for v in vids:
        for t in v.tubes:
            yield v, t, annotated(per_tube.get(t["tube_id"], []), observed_only)


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


def area(f: dict) -> float:
    """The pixel count of the row's mask, checked (``rows.mask_rle``): a malformed one stops the export."""
    return float(mask_utils.area(mask_rle(f)))


def write_json(path: Path, doc) -> None:
    """One JSON document and a newline (``path`` lies in the writer's private folder)."""
    path.parent.mkdir(exist_ok=True)
    path.write_text(json.dumps(doc) + "\n")


def ticking(label: str) -> Callable[[int, int], None]:
    """A ``write_images`` progress hook on a ``Ticker`` made at the first call (the total known then)."""
    state: dict = {}

    def hook(done: int, total: int) -> None:
        t = state.setdefault("t", Ticker(label, total))
        t.tick(done)
        if done >= total:
            t.close()
    return hook


def write_images(job: JobConfig | None, vids: list[Video], folder: Path,
                 progress: Callable[[int, int], None] | None = None,
                 path_of: Callable[[Video, int], str] = Video.file_name) -> int:
    """The rectified left frame of every video frame as ``folder/<path_of(video, frame)>``
    (``<file_name>`` by default); the count."""
    source = job_source(job, "--images")
    root = job.source.root
    total, done = sum(len(v.frames) for v in vids), 0
    for v in vids:
        survey = source.survey(v.sequence)
        position = {f: p for p, f in enumerate(survey.frames)}
        missing = [f for f in v.frames if f not in position]
        if missing:
            raise InputError(f"frame {missing[0]} of the catalogue is not in the source's sequence {v.sequence!r}",
                             root, missing[0])
        # only the video's frames need to read (problems elsewhere in the sequence do not matter)
        plan = source.plan(v.sequence, min(position[f] for f in v.frames), max(position[f] for f in v.frames) + 1)
        for frame in v.frames:
            image = source.read_frame(plan, position[frame]).left
            if image.shape[:2] != (v.height, v.width):
                raise InputError(f"image of {image.shape[1]}×{image.shape[0]}, masks of {v.width}×{v.height}",
                                 root, frame)
            path = inside(folder, path_of(v, frame))
            path.parent.mkdir(parents=True, exist_ok=True)
            if not cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]):
                raise InputError("cannot write JPEG", path)
            done += 1
            if progress is not None:
                progress(done, total)
    return done


def info(job: JobConfig | None, fmt: str) -> dict:
    # "run_id" has always been null: it was read from job.json's config, which does not hold it
    # (the record does, beside the config); kept so that exports stay as they were.
    return {"description": f"Tube Miner tubes ({fmt} export)", "run_id": None,
            "source": None if job is None else job.source.dataset}


def export_youtube_vis(tubes: pa.Table, frames: pa.Table, job: JobConfig | None, dest: Path,
                       video_frames: dict[tuple[str, str], list[int]] | None = None, images: bool = False) -> int:
    """``DEST/instances.json``, ``DEST/results/results.json`` (and ``DEST/JPEGImages/`` with
    ``images``); returns the annotations (tubes) written."""
    vids = videos(tubes, frames, video_frames or {})
    out_videos = [{"id": v.id, "name": v.name, "width": v.width, "height": v.height, "length": len(v.frames),
                   "file_names": [v.file_name(f) for f in v.frames]} for v in vids]
    anns, results, used = [], [], set()
    for v, t, at in video_tubes(vids, frames, job):
        cid = category_id(t)
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
           "categories": categories(used)}
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
    for v, t, at in video_tubes(vids, frames, job):
        cid = category_id(t)
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
           "annotations": anns, "categories": categories(used, tao=True)}
    write_json(dest / TAO_JSON, doc)
    write_json(dest / RESULTS_DIR / RESULTS_JSON, results)
    if images:
        write_images(job, vids, dest / TAO_IMAGES, ticking("tao images"))
    return len(anns)
