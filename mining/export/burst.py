"""`mine export --format burst`: the tubes in BURST's own annotation layout (the BURST
benchmark's ``ANNOTATION_FORMAT.md``), which its evaluation (TrackEval's ``BURST`` and
``BURST_OW`` readers) reads. Videos, frames, masks, scores and ``export.observed_only`` as in
``video_json.py``.

* ``DEST/burst.json`` — the dataset file: ``split`` (``BURST_SPLIT``), ``categories`` (the
  ones used: id, name, synset) and per sequence ``id``, ``width``, ``height``, ``seq_name``,
  ``dataset``, ``fps`` (the mined frames' rate, rounded as BURST's integer; absent when the
  catalogue has no timestamps or they say under one), ``all_image_paths`` and
  ``annotated_image_paths`` (the video's frames, ``<frame, zero-padded>.jpg``),
  ``neg_category_ids`` and ``not_exhaustive_category_ids`` (empty), ``track_category_ids``
  (track id → category id) and ``segmentations``: per annotated frame, track id →
  ``{"rle": compressed RLE counts, "is_gt": false, "score"}`` (``is_gt`` false: BURST's flag
  for a mask made automatically, ``score`` its confidence: the tube's score). Ours beside
  them: ``track_tube_ids`` (track id → tube id). Track ids are 1, 2, … per sequence, as BURST
  numbers them.
* ``DEST/results/results.json`` — the results file, in the same layout (BURST's evaluation
  takes a tracker's output so: the dataset file with ``track_category_ids`` and
  ``segmentations`` replaced), each mask with its ``score``.
* ``--images``: ``DEST/frames/<split>/<dataset>/<sequence>/<frame>.jpg``, the image layout
  BURST's paths name (``<split>/<dataset>/<seq_name>/<image path>``).

Category ids are TAO's (LVIS v0.5), which BURST uses: TrackEval's BURST readers take TAO's
category list whatever the file lists. A known tube's COCO class → its TAO id
(``mining/formats/lvis.py``). The rest get ids above TAO's (1..1230) and inside BURST-OW's
range (1..1999, where an id that is not one of its 78 COCO ids, "known", or a distractor counts
as "unknown"): hot dog and oven, the COCO classes TAO lacks, ``OUTSIDE_TAO_BASE`` + their
COCO id; unknown tubes ``UNKNOWN_ID``, clutter ``CLUTTER_ID``, unclassified ``UNCLASSIFIED_ID``;
a user's tag that is no COCO class (``--category-from tag``) ``TAG_BASE`` + its rank. So class-guided
BURST scores the known tubes of TAO's classes, and BURST-OW scores every tube, its "known"
subset the COCO classes and its "unknown" subset the others.
"""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa

from mining.config import JobConfig
from mining.export.json_annotations import (OWN_SYNSETS, RESULTS_DIR, RESULTS_JSON, TAG_SYNSET, TAO_IMAGES, area,
                                            category_id, info, tag_categories, write_json)
from mining.export.selection import Video, category_label, video_tubes, videos
from mining.export.source_frames import ticking, write_images
from mining.formats.lvis import TAO_MAX_ID, synset, tao_category

BURST_JSON = "burst.json"  # ours (BURST's own files are named by task: all_classes.json, …)
BURST_SPLIT = "val"  # REFERENCE: BURST's splits are train / val / test; its evaluation scores val and test
OUTSIDE_TAO_BASE = 1900  # ours: + COCO id (1..90) for the COCO classes TAO lacks
UNKNOWN_ID = 1998  # ours: unknown tubes (above TAO's 1..1230, inside BURST-OW's 1..1999)
UNCLASSIFIED_ID = 1999  # ours: unclassified tubes
CLUTTER_ID = 1997  # ours: tubes called clutter (unknown wins, the object gate says not an object)
OWN_IDS = {"unknown": UNKNOWN_ID, "unclassified": UNCLASSIFIED_ID, "clutter": CLUTTER_ID}  # by the tube's call
BURST_OW_MAX_ID = 1999  # REFERENCE: TrackEval's BURST-OW: ids 1..1999 are known, unknown or distractor
# ours: a user's tag that is no COCO class: TAG_BASE + its rank, between TAO's ids and
# OUTSIDE_TAO_BASE, so BURST-OW scores it as "unknown" (TAG_LIMIT such tags in one export)
TAG_BASE, TAG_LIMIT = 1300, 600

assert TAO_MAX_ID < TAG_BASE and TAG_BASE + TAG_LIMIT <= OUTSIDE_TAO_BASE
assert TAO_MAX_ID < OUTSIDE_TAO_BASE and OUTSIDE_TAO_BASE + 90 < CLUTTER_ID < UNKNOWN_ID < UNCLASSIFIED_ID <= BURST_OW_MAX_ID


def burst_category(tube: dict, tags: dict[str, int] | None = None) -> tuple[int, str, str]:
    """(id, name, synset) of a tube's BURST category (``json_annotations.category_id`` checks the
    class); ``tags``: the export's own categories for tags that are no COCO class."""
    label = category_label(tube)
    if label in OWN_IDS:
        return OWN_IDS[label], label, OWN_SYNSETS[label]
    if tags is not None and label in tags:
        return tags[label], label, f"{TAG_SYNSET}:{label}"
    coco_id = category_id(tube)  # raises naming a class that is not COCO's
    tao = tao_category(label)
    if tao is None:
        return OUTSIDE_TAO_BASE + coco_id, label, synset(label)
    return tao[0], tao[1], synset(label)


def image_path(v: Video, frame: int) -> str:
    """``<split>/<dataset>/<sequence>/<frame>.jpg``: where BURST's paths put a frame."""
    return f"{BURST_SPLIT}/{v.dataset}/{v.sequence}/{v.image_name(frame)}"


def export_burst(tubes: pa.Table, frames: pa.Table, job: JobConfig | None, dest: Path,
                 video_frames: dict[tuple[str, str], list[int]] | None = None, images: bool = False,
                 video_rates: dict[tuple[str, str], float] | None = None) -> int:
    """``DEST/burst.json``, ``DEST/results/results.json`` (and ``DEST/frames/`` with
    ``images``); returns the masks (tube frames) written. ``video_rates``: frames per second
    per (dataset, sequence), BURST's ``fps`` (left out where unknown)."""
    vids = videos(tubes, frames, video_frames or {})
    rates = video_rates or {}

    def fps(v: Video) -> dict:
        rate = rates.get((v.dataset, v.sequence))
        return {} if rate is None or round(rate) < 1 else {"fps": round(rate)}

    seqs = {v.id: {"id": v.id, "width": v.width, "height": v.height, "seq_name": v.sequence, "dataset": v.dataset,
                   **fps(v), "all_image_paths": [v.image_name(f) for f in v.frames],
                   "annotated_image_paths": [v.image_name(f) for f in v.frames],
                   "neg_category_ids": [], "not_exhaustive_category_ids": [],
                   "track_category_ids": {}, "track_tube_ids": {},
                   "segmentations": [{} for _ in v.frames]} for v in vids}
    results = {vid: {**s, "track_category_ids": {}, "segmentations": [{} for _ in s["segmentations"]]}
               for vid, s in seqs.items()}
    used: dict[int, tuple[str, str]] = {}
    n = 0
    tags = tag_categories(tubes.to_pylist(), TAG_BASE, TAG_LIMIT)
    for v, t, at in video_tubes(vids, frames, job):
        cid, name, syn = burst_category(t, tags)
        used[cid] = (name, syn)
        seq, res = seqs[v.id], results[v.id]
        track = str(len(seq["track_category_ids"]) + 1)
        seq["track_category_ids"][track] = res["track_category_ids"][track] = cid
        seq["track_tube_ids"][track] = t["tube_id"]
        score = float(t["score"])
        for k, frame in enumerate(v.frames):
            if frame in at:
                area(at[frame])  # checks the mask before it is copied
                counts = at[frame]["rle_counts"]
                seq["segmentations"][k][track] = {"rle": counts, "is_gt": False, "score": score}
                res["segmentations"][k][track] = {"rle": counts, "score": score}
                n += 1
    categories = [{"id": c, "name": name, "synset": syn} for c, (name, syn) in sorted(used.items())]
    head = {"info": info(job, "burst"), "split": BURST_SPLIT, "categories": categories}
    write_json(dest / BURST_JSON, {**head, "sequences": list(seqs.values())})
    write_json(dest / RESULTS_DIR / RESULTS_JSON, {**head, "sequences": list(results.values())})
    if images:
        write_images(job, vids, dest / TAO_IMAGES, ticking("burst images"), image_path)
    return n
