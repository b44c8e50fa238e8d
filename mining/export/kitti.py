"""`mine export --format kitti | kitti-mots`: the tubes as KITTI tracking results.

* ``kitti`` — KITTI tracking result txt per sequence (``<dest>/<sequence>.txt``, 17 label
  columns + the tube's score; SOURCES.md §1.5), for `mine eval kitti-mot` and TrackEval.
  3D positions go from our left camera to KITTI's rectified camera 0 (on KITTI sources).
* ``kitti-mots`` — KITTI-MOTS txt per sequence: ``time_frame id class_id img_height
  img_width rle`` with class 1 car, 2 pedestrian, 10 ignore (the MOTS annotation format,
  vision.rwth-aachen.de/page/mots), object id = class_id·1000 + track index. MOTS masks
  may not overlap: within a frame the higher-scoring tube keeps the shared pixels.

With the job's ``export.observed_only`` (the default) a frame where a tube is only predicted
(a gap) is left out; ``export.unclassified_as`` is the KITTI type of tubes no classifier
looked at.

Both write ``<dest>/<sequence>.ids.json`` beside each txt: the object/track id of each line →
the catalogue's ``tube_id`` and category, since the formats themselves carry only numbers.
KITTI-MOTS's ``unknown_class`` (``--unknown-class N``) writes unknown tubes as class N
instead of the field's 10 ("ignore"), which MOTS tools drop: the discovered objects are kept.
Hook: ``category_from`` names the tube column the category is read from (``category`` now; a
current-label column once the selection exposes one).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
from pycocotools import mask as mask_utils

from mining.catalog.rows import mask_rle
from mining.config import JobConfig
from mining.errors import InputError
from mining.export.selection import by_sequence, export_settings, frames_by_tube, tube_call
from mining.formats.kitti_tracking import ResultFrame, ResultTrack, kitti_type, write_tracking_results
from mining.names import check_name, inside

# KITTI-MOTS class ids (MOTS annotation format): car 1, pedestrian 2, ignore region 10.
MOTS_CLASS = {"car": 1, "person": 2}
MOTS_IGNORE = 10
MOTS_IDS_PER_CLASS = 1000  # object id = class_id * 1000 + instance; instance < 1000
MOTS_MAX_CLASS = 1000  # ours: a class id beyond this would make object ids past what 32-bit readers expect


def _sequence_file(dest: Path, sequence: str) -> Path:
    """``<dest>/<sequence>.txt`` of a checked sequence name, inside DEST."""
    return inside(dest, f"{check_name(sequence, 'sequence', 'the catalogue')}.txt")


def _cam_to_rect0(job: JobConfig | None, sequence: str):
    """Map from our left camera to KITTI's rectified camera 0 (identity off KITTI)."""
    if job is None or job.source.dataset != "kitti" or not job.source.root:
        return lambda p: p
    return job.source.open().kitti_calib(sequence).cam2_to_rect0


def _id_map_file(dest: Path, sequence: str) -> Path:
    """``<dest>/<sequence>.ids.json``: track id → tube_id and category."""
    return inside(dest, f"{check_name(sequence, 'sequence', 'the catalogue')}.ids.json")


def _write_id_map(dest: Path, sequence: str, ids: dict[int, dict]) -> None:
    _id_map_file(dest, sequence).write_text(json.dumps({str(k): v for k, v in sorted(ids.items())}, indent=1))


def _result_tracks(seq_tubes: list[dict], per_tube: dict[str, list[dict]], unclassified_as: str,
                   category_from: str = "category"):
    """A sequence's tubes as tracking results; track ids 0, 1, … in catalogue order."""
    for track_id, t in enumerate(seq_tubes):
        kind = kitti_type(t[category_from], t["known"], unclassified_as)
        frames = [ResultFrame(f["frame"], f["observed"], f["bbox"], f["size"], f["position_cam"])
                  for f in per_tube.get(t["tube_id"], [])]
        yield ResultTrack(track_id, kind, t["score"], frames)


def export_kitti(tubes: pa.Table, frames: pa.Table, job: JobConfig | None, dest: Path,
                 category_from: str = "category") -> int:
    """KITTI tracking result txt per sequence (and its id map); returns the rows written."""
    settings = export_settings(job)
    per_tube = frames_by_tube(frames)
    n = 0
    for (_, sequence), seq_tubes in by_sequence(tubes).items():
        n += write_tracking_results(_sequence_file(dest, sequence),
                                    _result_tracks(seq_tubes, per_tube, settings.unclassified_as, category_from),
                                    _cam_to_rect0(job, sequence), settings.observed_only)
        _write_id_map(dest, sequence, {i: {"tube_id": t["tube_id"], "category": t[category_from],
                                           "known": t["known"], "call": tube_call(t)} for i, t in enumerate(seq_tubes)})
    return n


def _mots_class(tube: dict, unclassified_as: str, unknown_class: int = MOTS_IGNORE,
                category_from: str = "category") -> int:
    """The MOTS class by the same rule as ``known``: a known tube's category, an unknown one
    ``unknown_class`` (the field's 10, ignore, by default)."""
    if tube["known"] is None:
        return {"Car": 1, "Pedestrian": 2}.get(unclassified_as, unknown_class)
    return MOTS_CLASS.get(tube[category_from], unknown_class) if tube["known"] else unknown_class


def disjoint_masks(rles: list[dict], scores: list[float]) -> list[dict | None]:
    """Masks of one frame made disjoint: a higher score keeps the pixels it shares with a
    lower one. None where nothing of a mask is left."""
    out: list[dict | None] = [None] * len(rles)
    taken = None
    for i in sorted(range(len(rles)), key=lambda i: -scores[i]):
        m = mask_utils.decode(rles[i])
        if taken is None:
            taken = np.zeros_like(m)
        m = m & (1 - taken)
        taken |= m
        if m.any():
            enc = mask_utils.encode(np.asfortranarray(m))
            out[i] = {"size": enc["size"], "counts": enc["counts"].decode()}
    return out


def export_kitti_mots(tubes: pa.Table, frames: pa.Table, job: JobConfig | None, dest: Path,
                      unknown_class: int | None = None, category_from: str = "category") -> int:
    """KITTI-MOTS txt per sequence (and its id map); returns the lines written."""
    unknown_class = MOTS_IGNORE if unknown_class is None else unknown_class
    if unknown_class in MOTS_CLASS.values() or not 0 < unknown_class < MOTS_MAX_CLASS:
        raise InputError(f"--unknown-class {unknown_class}: must be 1..{MOTS_MAX_CLASS - 1} and not car 1 / "
                         "pedestrian 2")
    settings = export_settings(job)
    per_tube = frames_by_tube(frames)
    n = 0
    for (dataset, sequence), seq_tubes in by_sequence(tubes).items():
        by_frame: dict[int, list[tuple[int, float, dict]]] = {}
        next_instance: dict[int, int] = {}
        ids: dict[int, dict] = {}
        for t in seq_tubes:
            cls = _mots_class(t, settings.unclassified_as, unknown_class, category_from)
            instance = next_instance.get(cls, 0)
            if instance >= MOTS_IDS_PER_CLASS:
                raise InputError(f"KITTI-MOTS ids hold at most {MOTS_IDS_PER_CLASS} tracks per class; "
                                 f"{dataset}/{sequence} has more of class {cls}: narrow --where")
            next_instance[cls] = instance + 1
            obj_id = cls * MOTS_IDS_PER_CLASS + instance
            ids[obj_id] = {"tube_id": t["tube_id"], "category": t[category_from], "known": t["known"],
                           "call": tube_call(t), "class_id": cls}
            for f in per_tube.get(t["tube_id"], []):
                if settings.observed_only and not f["observed"]:
                    continue
                by_frame.setdefault(f["frame"], []).append((obj_id, t["score"], mask_rle(f)))
        lines = []
        for frame in sorted(by_frame):
            items = by_frame[frame]
            masks = disjoint_masks([r for _, _, r in items], [s for _, s, _ in items])
            for (obj_id, _, _), m in sorted(zip(items, masks), key=lambda x: x[0][0]):
                if m is not None:
                    lines.append(f"{frame} {obj_id} {obj_id // MOTS_IDS_PER_CLASS} {m['size'][0]} {m['size'][1]} "
                                 f"{m['counts']}")
        _sequence_file(dest, sequence).write_text("\n".join(lines) + ("\n" if lines else ""))
        _write_id_map(dest, sequence, ids)
        n += len(lines)
    return n
