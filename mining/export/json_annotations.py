"""What the JSON annotation formats share (YouTube-VIS and TAO: ``video_json.py``; BURST:
``burst.py``): the own categories beside COCO's (``category_id``), the results file's
place, the ``info`` block, the checked mask area and the writing of one JSON document.

Each of these formats writes a **dataset** file and, in ``DEST/results/``, a **results**
file (the same tubes as a tracker's output): ``RESULTS_DIR`` / ``RESULTS_JSON``.
"""

from __future__ import annotations

import json
from pathlib import Path

from pycocotools import mask as mask_utils

from mining.catalog.rows import mask_rle
from mining.config import JobConfig
from mining.errors import InputError
from mining.export.selection import category_label
from mining.formats.coco import CLASS_INDEX, COCO_CATEGORY_IDS

UNKNOWN_ID = 1000  # ours: category id of unknown tubes, outside COCO's 1..90
UNCLASSIFIED_ID = 1001  # ours: category id of unclassified tubes
CLUTTER_ID = 1002  # ours: category id of tubes called clutter (unknown wins, the object gate says not an object)
# ours: the synsets of the own categories; not WordNet names (no sense is known for them)
OWN_SYNSETS = {"unknown": "tube_miner.unknown", "unclassified": "tube_miner.unclassified", "clutter": "tube_miner.clutter"}
TAO_IMAGES = "frames"  # TAO's image folder; BURST's --images uses it too
# ours: the results (tracker) file of every video format, in a folder of its own: evaluators
# want one JSON in the ground-truth folder and one in the tracker's
RESULTS_DIR, RESULTS_JSON = "results", "results.json"


OWN_IDS = {"unknown": UNKNOWN_ID, "unclassified": UNCLASSIFIED_ID, "clutter": CLUTTER_ID}  # by the tube's call
# ours: a user's tag that is no COCO class (``--category-from tag``) is a category of its own,
# TAG_BASE + its rank among the export's such tags in sorted order (above COCO's and OWN_IDS)
TAG_BASE = 2000
TAG_SUPERCATEGORY = "tag"  # ours: YouTube-VIS's supercategory of those categories
TAG_SYNSET = "tube_miner.tag"  # ours: TAO's synset of each, followed by ":" and the tag


def tag_categories(tubes: list[dict], base: int = TAG_BASE, limit: int | None = None) -> dict[str, int]:
    """The export's own categories for labels that are neither a COCO class nor a call (a user's
    tag taken as the category): tag → ``base`` + its rank in sorted order, so one export's ids
    do not depend on the tubes' order. ``limit``: the most a format's id range holds."""
    tags = sorted({label for t in tubes if (label := category_label(t)) not in OWN_IDS and label not in CLASS_INDEX})
    if limit is not None and len(tags) > limit:
        raise InputError(f"{len(tags)} tags that are not COCO classes; this format's id range holds {limit}")
    return {tag: base + i for i, tag in enumerate(tags)}


def category_id(tube: dict, tags: dict[str, int] | None = None) -> int:
    """The COCO id of a known tube's class; OWN_IDS's by its call; ``tags``'s (``tag_categories``)
    for a tag that is no COCO class."""
    label = category_label(tube)
    if label in OWN_IDS:
        return OWN_IDS[label]
    if label in CLASS_INDEX:
        return COCO_CATEGORY_IDS[CLASS_INDEX[label]]
    if tags is not None and label in tags:
        return tags[label]
    raise InputError(f"tube {tube['tube_id']} is known as {label!r}, which is not a COCO class")


def area(f: dict) -> float:
    """The pixel count of the row's mask, checked (``rows.mask_rle``): a malformed one stops the export."""
    return float(mask_utils.area(mask_rle(f)))


def write_json(path: Path, doc) -> None:
    """One JSON document and a newline (``path`` lies in the writer's private folder)."""
    path.parent.mkdir(exist_ok=True)
    path.write_text(json.dumps(doc) + "\n")


def info(job: JobConfig | None, fmt: str) -> dict:
    """The ``info`` block of a dataset file: the format and the job's dataset."""
    # "run_id" has always been null: it was read from job.json's config, which does not hold it
    # (the record does, beside the config); kept so that exports stay as they were.
    return {"description": f"Tube Miner tubes ({fmt} export)", "run_id": None,
            "source": None if job is None else job.source.dataset}
