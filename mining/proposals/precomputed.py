"""Proposals read from files instead of computed: the ``precomputed`` proposers.

Two inputs:

* ``JsonProposals`` — the original 4D-GVT per-frame proposal JSON (one ``NNNNNN.json`` per
  frame, a list of ``{segmentation: {size, counts}, score, category_id, bbox?,
  second_category_id?, second_posterior?}``; shared/data/proposals_4dgvt_format/*/README.md).
  objectness = ``score``; box = ``bbox`` (x, y, w, h) when present, else the mask's box.
  Posterior: ``second_posterior`` is sparse ``{size: 81, values: {"k": p}}`` with key 0 =
  background and keys 1..80 = the COCO classes in contiguous order; key 0 becomes our
  ``UNKNOWN_CLASS`` (the original's 81st class is "background/unknown", REFERENCE "Known and
  unknown"), keys k ≥ 1 become column k − 1, and each row is normalised to sum 1. A file
  without any ``second_posterior`` has no class information: with ``category_ids =
  "agnostic"`` (the README's files: category_id 1 = the single "object" class) the posterior
  is None; with ``"coco"`` the category_id is a COCO id (1..90) and the row puts ``score`` on
  that class and 1 − score on unknown, the same split the original uses for background.
  A file where only some elements carry ``second_posterior`` is rejected.

  Bounded (``JsonProposalsConfig``): a file over ``max_file_bytes`` is refused; its elements
  are parsed one at a time and only the ``max_proposals`` best by score are kept (what the
  ONNX proposer keeps, and what localise.filters ranks by later) — only their masks are
  checked (``mining.masks.rle_problem``, all of a frame's at once) and decoded. A malformed file of any shape is an
  InputError naming the file, the frame and the reason.

* ``KittiDetections`` — KITTI tracking detection files: PointRCNN's comma-separated 15-column
  files (SOURCES.md §1.6) and the 18-column tracking result format (§1.5), read by
  ``mining/formats/kitti_detections.py``. Each detection
  becomes a box-shaped mask (the pixels whose centres lie inside the box clipped to the
  image). The scores are unbounded, so objectness is a logistic map
  1 / (1 + exp(−(score − score_offset) / score_scale)); the defaults are fitted on PointRCNN
  against label_02 (KittiDetectionsConfig). The raw score stays available through
  ``raw_scores(frame)``. Posterior: one-hot on the detector's class mapped to COCO
  (KITTI_TYPE_TO_COCO; "unknown" for a class outside COCO): the class is the detector's
  decision given that the detection exists, and existence is the objectness. 3D: KITTI locations are box *bottom*
  centres in rectified camera 0; position = location − (0, h/2, 0) moved into the image_02
  frame, size = (w, h, l). Detections without 3D (Regionlets' −1/−1000 placeholders) get NaN rows.
"""

from __future__ import annotations

import heapq
import json
import math
import os
import re
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
from pycocotools import mask as mask_utils

from mining.errors import InputError, decode_text
from mining.files import open_regular
from mining.formats.coco import CATEGORY_ID_TO_INDEX, CLASS_INDEX
from mining.formats.kitti_calib import KittiCalib
from mining.formats.kitti_detections import read_kitti_detections
from mining.masks import batch_rle_problems
from mining.proposals.config import JsonProposalsConfig, KittiDetectionsConfig, ProposalConfig
from mining.proposals.registry import Proposer
from mining.types import N_CLASSES, UNKNOWN_CLASS, Proposals

JSON_PROPOSER = "json"
KITTI_PROPOSER = "kitti_detections"

# ours: KITTI object type → COCO class; None = no COCO class (all mass on unknown).
# A Cyclist box holds a person on a bicycle; we name the vehicle, as the brief of this stage asks.
KITTI_TYPE_TO_COCO: dict[str, str | None] = {
    "Car": "car", "Van": "car", "Truck": "truck", "Pedestrian": "person", "Person": "person",
    "Person_sitting": "person", "Cyclist": "bicycle", "Tram": "train", "Misc": None,
}


def empty_proposals(frame: int, with_classes: bool, with_3d: bool, name: str) -> Proposals:
    return Proposals(
        frame=frame, rles=[], boxes=np.zeros((0, 4), np.float32), objectness=np.zeros(0, np.float32),
        posterior=np.zeros((0, N_CLASSES), np.float32) if with_classes else None, proposer=[],
        position=np.zeros((0, 3), np.float32) if with_3d else None,
        size=np.zeros((0, 3), np.float32) if with_3d else None,
    )


# -- 4D-GVT JSON --------------------------------------------------------------------


class JsonProposals:
    """Per-frame proposals from a folder of 4D-GVT JSON files; ``proposals(frame)`` reads one.

    ``image_size`` (w, h), when given, is checked against every mask's size.
    """

    def __init__(self, folder: str | Path, cfg: JsonProposalsConfig | None = None,
                 image_size: tuple[int, int] | None = None, name: str = JSON_PROPOSER):
        self.cfg = cfg or JsonProposalsConfig()
        if self.cfg.category_ids not in ("agnostic", "coco"):
            raise InputError(f"category_ids must be 'agnostic' or 'coco', got {self.cfg.category_ids!r}", folder)
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise InputError("proposal folder does not exist", self.folder)
        self.image_size = image_size
        self.name = name

    def path(self, frame: int) -> Path:
        return self.folder / f"{frame:0{self.cfg.filename_digits}d}.json"

    def frames(self) -> list[int]:
        """Frame indices that have a file, ascending."""
        pattern = re.compile(rf"(\d{{{self.cfg.filename_digits}}})\.json")
        return sorted(int(m.group(1)) for p in self.folder.iterdir() if (m := pattern.fullmatch(p.name)))

    def __call__(self, frame: int, image: np.ndarray | None = None) -> Proposals:
        """Proposals of ``frame``; ``image`` (optional) only checks the frame size."""
        size = self.image_size if image is None else (image.shape[1], image.shape[0])
        return read_proposal_json(self.path(frame), frame, self.cfg.category_ids, size, self.name,
                                  max_proposals=self.cfg.max_proposals, max_file_bytes=self.cfg.max_file_bytes)


def json_proposer(cfg: ProposalConfig, frame_size: tuple[int, int]) -> Proposer:
    """The registry's factory of ``json``: the files of ``proposals.json.folder``, read by frame index."""
    reader = JsonProposals(cfg.json.folder, cfg.json, image_size=(frame_size[1], frame_size[0]))
    return lambda frame, geometry: reader(frame.index, frame.left)


def read_proposal_json(path: str | Path, frame: int, category_ids: str = "agnostic",
                       image_size: tuple[int, int] | None = None, name: str = JSON_PROPOSER, *,
                       max_proposals: int = JsonProposalsConfig.max_proposals,
                       max_file_bytes: int = JsonProposalsConfig.max_file_bytes) -> Proposals:
    """One 4D-GVT proposal JSON file → Proposals sorted by score (see the module doc).

    Bounded: a file over ``max_file_bytes`` is refused; of more than ``max_proposals``
    proposals the best by score are kept (ties: the earlier in the file), and only those
    have their masks checked and decoded. Any malformed file is an InputError naming it,
    the frame and the reason.
    """
    path = Path(path)
    try:
        return _read_proposal_json(path, frame, category_ids, image_size, name, max_proposals, max_file_bytes)
    except FileNotFoundError:
        raise InputError("proposal file for this frame is missing", path, frame) from None
    except json.JSONDecodeError as e:
        raise InputError(f"not valid JSON at line {e.lineno} column {e.colno}: {e.msg}", path, frame) from None
    except RecursionError:
        raise InputError("nested too deeply to be a list of proposals", path, frame) from None
    except OSError as e:
        raise InputError(f"cannot be read: {e.strerror or e}", path, frame) from None
    except (ValueError, TypeError, KeyError, IndexError) as e:  # a wrongly shaped file a check missed
        raise InputError(f"malformed proposal file ({type(e).__name__}: {e})", path, frame) from None


def _read_proposal_json(path: Path, frame: int, category_ids: str, image_size: tuple[int, int] | None, name: str,
                        max_proposals: int, max_file_bytes: int) -> Proposals:
    kept, n_items, all_post = _best_elements(_bounded_text(path, frame, max_file_bytes), path, frame, max_proposals)
    if not n_items:  # an empty posterior array fits files with and without classes alike
        return empty_proposals(frame, True, False, name)
    in_file_order = sorted(kept, key=lambda e: e[0])  # so that the first bad element is the one named
    problems = _rle_problems([it for _, it in in_file_order])  # every mask at once: the cost at 500 a frame
    for j, (i, it) in enumerate(in_file_order):
        _check_element(i, it, in_file_order[0] if j else None, image_size, path, frame, problems[j])
    n = len(kept)
    rles, boxes, scores = [], np.zeros((n, 4)), np.zeros(n)
    posterior = np.zeros((n, N_CLASSES)) if (all_post or category_ids == "coco") else None
    for row, (i, it) in enumerate(kept):
        def bad(reason: str) -> InputError:
            return InputError(f"element {i}: {reason}", path, frame)

        seg = it["segmentation"]
        rles.append({"size": list(seg["size"]), "counts": seg["counts"].encode("ascii")})
        scores[row] = it["score"]
        bbox = it.get("bbox")
        boxes[row] = bbox if bbox is not None else mask_utils.toBbox(rles[-1])
        if posterior is not None and all_post:
            problem = _fill_second_posterior(it["second_posterior"], posterior[row])
            if problem:
                _check_mass(posterior[:row], kept, path, frame)  # an earlier element's error comes first
                raise bad(problem)
        elif posterior is not None:
            posterior[row] = _coco_one_hot(it.get("category_id"), it["score"], bad)
    if posterior is not None and all_post:
        posterior /= _check_mass(posterior, kept, path, frame)[:, None]  # each row normalised to sum 1
    boxes[:, 2:] += boxes[:, :2]
    return Proposals(
        frame=frame, rles=rles, boxes=boxes.astype(np.float32), objectness=scores.astype(np.float32),
        posterior=None if posterior is None else posterior.astype(np.float32), proposer=[name] * n,
    )


def _bounded_text(path: Path, frame: int, max_file_bytes: int) -> str:
    """The file's text, refused above ``max_file_bytes`` before it is read."""
    with open_regular(path, frame) as f:  # a FIFO at the frame's name is refused, never waited on
        size = os.fstat(f.fileno()).st_size
        if size > max_file_bytes:
            raise InputError(f"{size} bytes, over proposals.json.max_file_bytes = {max_file_bytes}", path, frame)
        data = f.read(max_file_bytes + 1)  # a file that grows, or is not a regular file, stops here too
    if len(data) > max_file_bytes:
        raise InputError(f"over proposals.json.max_file_bytes = {max_file_bytes}", path, frame)
    return decode_text(data, path, "proposal file", frame)


def _best_elements(text: str, path: Path, frame: int, max_proposals: int) -> tuple[list[tuple[int, dict]], int, bool]:
    """(the ``max_proposals`` best elements of the list ``text`` as (index, element), best
    score first, ties in file order; the number of elements; whether they carry
    ``second_posterior``). Each element is parsed on its own and only its score (which ranks
    it) is checked here, so memory is the text and the kept elements."""
    heap: list[tuple[float, int, dict]] = []  # (score, −index, element): the worst kept one on top
    first_with = first_without = None  # elements with and without second_posterior
    n = 0
    for i, it in enumerate(_list_elements(text, path, frame)):
        n = i + 1
        if not isinstance(it, dict):
            raise InputError(f"element {i}: expected an object, got {type(it).__name__}", path, frame)
        if "second_posterior" in it:
            first_with = i if first_with is None else first_with
        elif first_without is None:
            first_without = i
        if first_with is not None and first_without is not None:
            raise InputError(f"element {first_without}: no second_posterior where other elements have one",
                             path, frame)
        score = it.get("score")
        if score.__class__ not in (int, float) or not 0.0 <= score <= 1.0:
            raise InputError(f"element {i}: score must be a number in [0, 1], got {score!r}", path, frame)
        if len(heap) < max_proposals:
            heapq.heappush(heap, (score, -i, it))
        elif (score, -i) > heap[0][:2]:
            heapq.heapreplace(heap, (score, -i, it))
    kept = [(-neg_i, it) for _, neg_i, it in sorted(heap, key=lambda e: e[:2], reverse=True)]
    return kept, n, first_with is not None


def _well_shaped(seg: object) -> bool:
    """Whether ``seg`` has the shape of a compressed COCO RLE {size: [h, w], counts: str}."""
    if not isinstance(seg, dict):
        return False
    size = seg.get("size")  # the two sides written out: this runs twice for each of 500 elements a frame
    return (isinstance(seg.get("counts"), str) and isinstance(size, list) and len(size) == 2
            and isinstance(size[0], int) and size[0] > 0 and isinstance(size[1], int) and size[1] > 0)


def _rle_problems(elements: list[dict]) -> list[str | None]:
    """``mining.masks.rle_problem`` of each element's segmentation, all in one pass
    (``batch_rle_problems``); None for an element whose segmentation is not even shaped as one."""
    shaped = [k for k, it in enumerate(elements) if _well_shaped(it.get("segmentation"))]
    found = batch_rle_problems([tuple(elements[k]["segmentation"]["size"]) for k in shaped],
                               [elements[k]["segmentation"]["counts"] for k in shaped])
    problems: list[str | None] = [None] * len(elements)
    for k, problem in zip(shaped, found):
        problems[k] = problem
    return problems


def _check_element(i: int, it: dict, first: tuple[int, dict] | None, image_size: tuple[int, int] | None,
                   path: Path, frame: int, problem: str | None) -> None:
    """Check a kept element before its mask is decoded: its RLE (``problem``, from
    ``mining.masks.rle_problem`` of its segmentation), its size against the image and against
    ``first`` (the first kept element), its bbox."""
    def bad(reason: str) -> InputError:
        return InputError(f"element {i}: {reason}", path, frame)

    seg = it.get("segmentation")
    if not _well_shaped(seg):
        raise bad("segmentation must be a compressed COCO RLE {size: [h, w], counts: str}")
    hw = tuple(seg["size"])
    if first is None and image_size is not None and hw != (image_size[1], image_size[0]):
        raise bad(f"mask size {hw[1]}×{hw[0]} differs from the image size {image_size[0]}×{image_size[1]}")
    if first is not None and hw != tuple(first[1]["segmentation"]["size"]):
        raise bad(f"mask size {hw} differs from element {first[0]}'s {tuple(first[1]['segmentation']['size'])}")
    if problem is not None:
        raise bad(f"malformed segmentation ({problem})")
    bbox = it.get("bbox")
    if bbox is not None and (not (isinstance(bbox, list) and len(bbox) == 4 and _finite(bbox[0]) and _finite(bbox[1])
                                  and _finite(bbox[2]) and _finite(bbox[3])) or min(bbox[2:]) < 0):
        raise bad(f"bbox must be [x, y, w, h] with w, h ≥ 0, got {bbox!r}")


_SPACE = re.compile(r"[ \t\n\r]*")  # JSON's whitespace
_NEXT = re.compile(r"[ \t\n\r]*([,\]])[ \t\n\r]*")  # what follows a list element


def _list_elements(text: str, path: Path, frame: int) -> Iterator:
    """The elements of the JSON list ``text``, parsed one at a time by the standard library,
    so that a file of many proposals never exists as one Python list."""
    decoder = json.JSONDecoder()
    i = _SPACE.match(text).end()
    if not text.startswith("[", i):
        value, _ = decoder.raw_decode(text, i)  # the JSONDecodeError of a file that is not JSON at all
        raise InputError(f"expected a JSON list of proposals, got {type(value).__name__}", path, frame)
    i = _SPACE.match(text, i + 1).end()
    if text.startswith("]", i):
        i += 1
    else:
        while True:
            item, i = decoder.raw_decode(text, i)
            yield item
            sep = _NEXT.match(text, i)
            if sep is None:
                raise json.JSONDecodeError("Expecting ',' delimiter", text, _SPACE.match(text, i).end())
            if sep.group(1) == "]":
                i = sep.start(1) + 1
                break
            i = sep.end()
    i = _SPACE.match(text, i).end()
    if i != len(text):
        raise json.JSONDecodeError("Extra data", text, i)


def _finite(v) -> bool:
    if v.__class__ is float or v.__class__ is int:  # what JSON numbers are: the common case first
        return math.isfinite(v)
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


# The file's index keys written plainly ("0".."80") → our columns; other spellings ("07") take the long check.
_POSTERIOR_COLUMN = {str(k): UNKNOWN_CLASS if k == 0 else k - 1 for k in range(N_CLASSES)}


def _fill_second_posterior(sp, row: np.ndarray) -> str | None:
    """Write sparse ``{size: 81, values: {"k": p}}`` (0 = background, 1..80 = classes) into ``row``
    (zeros, our 81 layout), unnormalised (``_check_mass`` normalises a frame's rows at once); what is
    wrong with it, or None."""
    if not (isinstance(sp, dict) and sp.get("size") == N_CLASSES and isinstance(sp.get("values"), dict)):
        return f"second_posterior must be {{size: {N_CLASSES}, values: {{index: p}}}}"
    for key, p in sp["values"].items():
        col = _POSTERIOR_COLUMN.get(key) if key.__class__ is str else None
        if col is None:
            if not (key.isdigit() and int(key) < N_CLASSES):
                return f"second_posterior entry {key!r}: {p!r} is not an index 0..80 with a probability ≥ 0"
            col = UNKNOWN_CLASS if int(key) == 0 else int(key) - 1
        if not _finite(p) or p < 0:
            return f"second_posterior entry {key!r}: {p!r} is not an index 0..80 with a probability ≥ 0"
        row[col] = p
    return None


def _check_mass(rows: np.ndarray, kept: list[tuple[int, dict]], path: Path, frame: int) -> np.ndarray:
    """Each row's total (rows of ``kept``'s elements, in order); the first without mass is an InputError."""
    total = rows.sum(axis=1)
    empty = np.flatnonzero(~(total > 0))
    if empty.size:
        raise InputError(f"element {kept[int(empty[0])][0]}: second_posterior has no mass", path, frame)
    return total


def _coco_one_hot(category_id, score: float, bad) -> np.ndarray:
    if isinstance(category_id, bool) or category_id not in CATEGORY_ID_TO_INDEX:
        raise bad(f"category_id {category_id!r} is not a COCO category id")
    row = np.zeros(N_CLASSES)
    row[CATEGORY_ID_TO_INDEX[category_id]] = score
    row[UNKNOWN_CLASS] += 1.0 - score
    return row


# -- KITTI detection files ----------------------------------------------------------


class KittiDetections:
    """All detections of one KITTI tracking sequence, parsed once, served per frame.

    ``source``: a file, a list of files, or a folder holding ``<sequence>.txt`` (result
    format) or ``<Class>/<sequence>.txt`` sub-folders (PointRCNN). Each file is recognised by
    its first line: commas → PointRCNN, else the 18-column result format. ``calib`` moves the
    3D boxes from rectified camera 0 into the image_02 frame; ``image_size`` is (w, h).
    """

    def __init__(self, source: str | Path | Sequence[str | Path], sequence: str, calib: KittiCalib,
                 image_size: tuple[int, int], cfg: KittiDetectionsConfig | None = None, name: str = KITTI_PROPOSER):
        self.cfg = cfg or KittiDetectionsConfig()
        if not self.cfg.score_scale > 0:
            raise InputError(f"score_scale must be positive, got {self.cfg.score_scale}")
        self.sequence = sequence
        self.width, self.height = int(image_size[0]), int(image_size[1])
        self.name = name
        self.files = _detection_files(source, sequence)
        parts = [_read_detection_file(f) for f in self.files]
        frame = np.concatenate([p[0] for p in parts])
        cls = np.concatenate([p[1] for p in parts])
        num = np.concatenate([p[2] for p in parts])  # x1 y1 x2 y2 score h w l x y z
        # One sort: by frame, best score first within a frame; frames index into it.
        order = np.lexsort((-num[:, 4], frame))
        self._frame, self._cls, num = frame[order], cls[order], num[order]
        self._box = np.clip(num[:, :4], 0, [self.width, self.height, self.width, self.height])
        self._raw = num[:, 4]
        self._objectness = objectness_from_score(self._raw, self.cfg)
        h, w, l = num[:, 5], num[:, 6], num[:, 7]
        bottom = num[:, 8:11]
        has_3d = (h > 0) & (w > 0) & (l > 0) & (bottom[:, 2] > 0)  # Regionlets write −1 / −1000
        centre = bottom - np.column_stack([np.zeros_like(h), h / 2, np.zeros_like(h)])
        self._position = np.where(has_3d[:, None], calib.rect0_to_cam2(centre), np.nan)
        self._size = np.where(has_3d[:, None], np.column_stack([w, h, l]), np.nan)
        # Boxes that clip to nothing (entirely outside the image) have no pixels to localise.
        self._visible = (self._box[:, 2] > self._box[:, 0]) & (self._box[:, 3] > self._box[:, 1])

    def _rows(self, frame: int) -> np.ndarray:
        if frame < 0:
            raise InputError(f"negative frame index {frame}", self.files[0], frame)
        lo, hi = np.searchsorted(self._frame, [frame, frame + 1])
        idx = np.arange(lo, hi)
        return idx[self._visible[idx]]

    def frames(self) -> list[int]:
        """Frames with at least one detection."""
        return np.unique(self._frame).tolist()

    def raw_scores(self, frame: int) -> np.ndarray:
        """The detector's unbounded scores, row for row with ``self(frame)``."""
        return self._raw[self._rows(frame)].copy()

    def __call__(self, frame: int, image: np.ndarray | None = None) -> Proposals:
        if image is not None and image.shape[:2] != (self.height, self.width):
            raise InputError(f"image is {image.shape[1]}×{image.shape[0]}, detections were set up for "
                             f"{self.width}×{self.height}", self.files[0], frame)
        idx = self._rows(frame)
        if idx.size == 0:
            return empty_proposals(frame, True, True, self.name)
        box = self._box[idx]
        xywh = np.column_stack([box[:, :2], box[:, 2:] - box[:, :2]])
        rles = mask_utils.frPyObjects(xywh, self.height, self.width)
        obj = self._objectness[idx]
        # The class is the detector's own decision (given that the detection exists, which is
        # what objectness says): one-hot on it; a class outside COCO is unknown.
        posterior = np.zeros((idx.size, N_CLASSES))
        cls = self._cls[idx]
        known = cls >= 0
        posterior[known, cls[known]] = 1.0
        posterior[~known, UNKNOWN_CLASS] = 1.0
        return Proposals(
            frame=frame, rles=rles, boxes=box.astype(np.float32), objectness=obj.astype(np.float32),
            posterior=posterior.astype(np.float32), proposer=[self.name] * idx.size,
            position=self._position[idx].astype(np.float32), size=self._size[idx].astype(np.float32),
        )


def objectness_from_score(score: np.ndarray, cfg: KittiDetectionsConfig) -> np.ndarray:
    """Unbounded detector score → objectness in (0, 1), logistic (see KittiDetectionsConfig)."""
    z = (np.asarray(score, np.float64) - cfg.score_offset) / cfg.score_scale
    return 0.5 * (1.0 + np.tanh(0.5 * z))  # = 1 / (1 + e^−z) without overflow


def _detection_files(source, sequence: str) -> list[Path]:
    if isinstance(source, (str, Path)):
        p = Path(source)
        if p.is_file():
            return [p]
        if not p.is_dir():
            raise InputError("detections path does not exist", p)
        if (p / f"{sequence}.txt").is_file():
            return [p / f"{sequence}.txt"]
        found = sorted(d / f"{sequence}.txt" for d in p.iterdir() if (d / f"{sequence}.txt").is_file())
        if not found:
            raise InputError(f"no {sequence}.txt in the folder or its sub-folders", p)
        return found
    files = [Path(f) for f in source]
    for f in files:
        if not f.is_file():
            raise InputError("detections file does not exist", f)
    if not files:
        raise InputError("no detection files given")
    return files


def _read_detection_file(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(frame, COCO class index or −1, [x1 y1 x2 y2 score h w l x y z]) of one file."""
    rows = read_kitti_detections(path)
    keep = rows.type != "DontCare"
    cls = np.full(len(rows), -1, np.int64)
    for t in np.unique(rows.type[keep]):
        if t not in KITTI_TYPE_TO_COCO:
            i = int(np.flatnonzero(rows.type == t)[0])
            raise InputError(f"unknown KITTI object type {t!r}", path, int(rows.frame[i]))
        coco = KITTI_TYPE_TO_COCO[t]
        cls[rows.type == t] = -1 if coco is None else CLASS_INDEX[coco]
    num = np.column_stack([rows.box, rows.score, rows.dimensions, rows.location])
    return rows.frame[keep], cls[keep], num[keep]
