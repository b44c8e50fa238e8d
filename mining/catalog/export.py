"""`mine export`: the tubes matching a SQL predicate, in formats other tools read.

* ``kitti`` — KITTI tracking result txt per sequence (``<dest>/<sequence>.txt``, 17 label
  columns + the tube's score; SOURCES.md §1.5), for `mine eval kitti-mot` and TrackEval.
* ``kitti-mots`` — KITTI-MOTS txt per sequence: ``time_frame id class_id img_height
  img_width rle`` with class 1 car, 2 pedestrian, 10 ignore (the MOTS annotation format,
  vision.rwth-aachen.de/page/mots), object id = class_id·1000 + track index. MOTS masks
  may not overlap: within a frame the higher-scoring tube keeps the shared pixels.
* ``crops`` — per tube ``<dest>/<tube_id with / → _>/frame_<k>.png`` (left image around
  the box) and ``mask_<k>.png``, plus ``<dest>/index.parquet`` and ``index.json``: every
  ``tubes`` column, the crop folder, and the 3D track (frame, t_ns, position_world).
  Images are re-read through the source named in ``OUT/job.json``, each frame once.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import duckdb
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from pycocotools import mask as mask_utils

from mining.catalog.layout import JobRecord
from mining.catalog.store import Store
from mining.catalog.views import connect, execute_read_only
from mining.errors import InputError, MiningError
from mining.formats.kitti_tracking import ResultFrame, ResultTrack, kitti_type, write_tracking_results

FORMATS = ("kitti", "kitti-mots", "crops")
# KITTI-MOTS class ids (MOTS annotation format): car 1, pedestrian 2, ignore region 10.
MOTS_CLASS = {"car": 1, "person": 2}
MOTS_IGNORE = 10
MOTS_IDS_PER_CLASS = 1000  # object id = class_id * 1000 + instance; instance < 1000
CROP_MARGIN = 0.15  # ours: context around the box, as a fraction of the box's width / height
CROP_MARGIN_MIN_PX = 8  # ours: at least this much context for small boxes


def read_job(store: Store) -> dict:
    """The resolved job config recorded in OUT/job.json, or {} when the catalogue has none."""
    record = JobRecord.load(store)
    return {} if record is None else record.config


def selected_rows(con: duckdb.DuckDBPyConnection, where: str) -> tuple[pa.Table, pa.Table]:
    """(tubes, tube_frames) of the tubes matching ``where``, frames in (tube, frame) order."""
    tubes_sql = f"SELECT * FROM tubes WHERE ({where})"
    try:
        if len(duckdb.extract_statements(tubes_sql)) != 1:
            raise InputError(f"--where must be one SQL predicate, got {where!r}")
        tubes = execute_read_only(con, tubes_sql + " ORDER BY dataset, sequence, t_start, tube_id").to_arrow_table()
    except duckdb.Error as e:
        raise InputError(f"bad --where predicate {where!r}: {e}") from None
    frames = con.sql(f"SELECT f.* FROM tube_frames AS f SEMI JOIN ({tubes_sql}) AS t USING (dataset, sequence, tube_id) "
                     "ORDER BY f.dataset, f.sequence, f.tube_id, f.frame").to_arrow_table()
    return tubes, frames


def job_source(job: dict, what: str):
    """(source adapter, job.json's ``source`` table) of the job that made a catalogue:
    images are re-read through it."""
    from mining.sources import open_source

    src = job.get("source")
    if not src or not src.get("dataset"):
        raise InputError(f"{what} needs the source named in job.json (source.dataset, source.root)")
    return open_source(src["dataset"], src.get("root") or None, **src.get("options", {})), src


def category_label(tube: dict) -> str:
    """A tube's category by the rule of its ``known`` flag: a known tube's COCO class,
    ``unknown`` when classified as none of them, ``unclassified`` when no classifier looked."""
    if tube["known"] is None:
        return "unclassified"
    return tube["category"] if tube["known"] else "unknown"


def _by_sequence(tubes: pa.Table) -> dict[tuple[str, str], list[dict]]:
    out: dict[tuple[str, str], list[dict]] = {}
    for t in tubes.to_pylist():
        out.setdefault((t["dataset"], t["sequence"]), []).append(t)
    return out


def _frames_by_tube(frames: pa.Table) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = {}
    for f in frames.to_pylist():
        out.setdefault(f["tube_id"], []).append(f)
    return out


def _file_name(sequence: str) -> str:
    return sequence.replace("/", "_")


def _cam_to_rect0(job: dict, sequence: str):
    """Map from our left camera to KITTI's rectified camera 0 (identity off KITTI)."""
    src = job.get("source", {})
    if src.get("dataset") != "kitti" or not src.get("root"):
        return lambda p: p
    from mining.sources.kitti import KittiTrackingSource

    return KittiTrackingSource(src["root"], **src.get("options", {})).kitti_calib(sequence).cam2_to_rect0


def _export_settings(job: dict) -> tuple[bool, str]:
    """The job's ``[export]`` settings, with ExportConfig's defaults."""
    from mining.config import ExportConfig

    exp, default = job.get("export", {}), ExportConfig()
    return exp.get("observed_only", default.observed_only), exp.get("unclassified_as", default.unclassified_as)


def _result_tracks(seq_tubes: list[dict], per_tube: dict[str, list[dict]], unclassified_as: str):
    """A sequence's tubes as tracking results; track ids 0, 1, … in catalogue order."""
    for track_id, t in enumerate(seq_tubes):
        kind = kitti_type(t["category"], t["known"], unclassified_as)
        frames = [ResultFrame(f["frame"], f["observed"], f["bbox"], f["size"], f["position_cam"])
                  for f in per_tube.get(t["tube_id"], [])]
        yield ResultTrack(track_id, kind, t["score"], frames)


def export_kitti(tubes: pa.Table, frames: pa.Table, job: dict, dest: Path) -> int:
    """KITTI tracking result txt per sequence; returns the rows written."""
    observed_only, unclassified_as = _export_settings(job)
    per_tube = _frames_by_tube(frames)
    n = 0
    for (_, sequence), seq_tubes in _by_sequence(tubes).items():
        n += write_tracking_results(dest / f"{_file_name(sequence)}.txt",
                                    _result_tracks(seq_tubes, per_tube, unclassified_as),
                                    _cam_to_rect0(job, sequence), observed_only)
    return n


def _mots_class(tube: dict, unclassified_as: str) -> int:
    """The MOTS class by the same rule as ``known``: a known tube's category, an unknown one ignored."""
    if tube["known"] is None:
        return {"Car": 1, "Pedestrian": 2}.get(unclassified_as, MOTS_IGNORE)
    return MOTS_CLASS.get(tube["category"], MOTS_IGNORE) if tube["known"] else MOTS_IGNORE


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


def export_kitti_mots(tubes: pa.Table, frames: pa.Table, job: dict, dest: Path) -> int:
    """KITTI-MOTS txt per sequence; returns the lines written."""
    observed_only, unclassified_as = _export_settings(job)
    per_tube = _frames_by_tube(frames)
    n = 0
    for (dataset, sequence), seq_tubes in _by_sequence(tubes).items():
        by_frame: dict[int, list[tuple[int, float, dict]]] = {}
        next_instance: dict[int, int] = {}
        for t in seq_tubes:
            cls = _mots_class(t, unclassified_as)
            instance = next_instance.get(cls, 0)
            if instance >= MOTS_IDS_PER_CLASS:
                raise InputError(f"KITTI-MOTS ids hold at most {MOTS_IDS_PER_CLASS} tracks per class; "
                                 f"{dataset}/{sequence} has more of class {cls}: narrow --where")
            next_instance[cls] = instance + 1
            obj_id = cls * MOTS_IDS_PER_CLASS + instance
            for f in per_tube.get(t["tube_id"], []):
                if observed_only and not f["observed"]:
                    continue
                rle = {"size": [f["rle_h"], f["rle_w"]], "counts": f["rle_counts"].encode()}
                by_frame.setdefault(f["frame"], []).append((obj_id, t["score"], rle))
        lines = []
        for frame in sorted(by_frame):
            items = by_frame[frame]
            masks = disjoint_masks([r for _, _, r in items], [s for _, s, _ in items])
            for (obj_id, _, _), m in sorted(zip(items, masks), key=lambda x: x[0][0]):
                if m is not None:
                    lines.append(f"{frame} {obj_id} {obj_id // MOTS_IDS_PER_CLASS} {m['size'][0]} {m['size'][1]} "
                                 f"{m['counts']}")
        (dest / f"{_file_name(sequence)}.txt").write_text("\n".join(lines) + ("\n" if lines else ""))
        n += len(lines)
    return n


def crop_box(bbox, width: int, height: int) -> tuple[int, int, int, int]:
    """Pixel rectangle [x0, x1) × [y0, y1) around a box, with margin, inside the image."""
    x1, y1, x2, y2 = (float(v) for v in bbox)
    mx = max(CROP_MARGIN * (x2 - x1), CROP_MARGIN_MIN_PX)
    my = max(CROP_MARGIN * (y2 - y1), CROP_MARGIN_MIN_PX)
    x0, x1_ = int(np.floor(max(0.0, x1 - mx))), int(np.ceil(min(float(width), x2 + mx)))
    y0, y1_ = int(np.floor(max(0.0, y1 - my))), int(np.ceil(min(float(height), y2 + my)))
    return x0, max(x1_, x0 + 1), y0, max(y1_, y0 + 1)


def tube_folder(tube_id: str) -> str:
    return tube_id.replace("/", "_")


def _write_png(path: Path, image: np.ndarray) -> None:
    if not cv2.imwrite(str(path), image):
        raise InputError("cannot write PNG", path)


def export_crops(tubes: pa.Table, frames: pa.Table, job: dict, dest: Path) -> int:
    """Per-tube crop and mask PNGs plus the index; returns the crops written."""
    source, src = job_source(job, "crops")
    per_tube = _frames_by_tube(frames)
    n = 0
    for (_, sequence), seq_tubes in _by_sequence(tubes).items():
        plan = source.plan(sequence)
        position = {f: p for p, f in enumerate(plan.frames)}
        wanted: dict[int, list[dict]] = {}  # frame → the tube frames that need it
        for t in seq_tubes:
            (dest / tube_folder(t["tube_id"])).mkdir(parents=True, exist_ok=True)
            for f in per_tube.get(t["tube_id"], []):
                wanted.setdefault(f["frame"], []).append(f)
        for frame in sorted(wanted):
            if frame not in position:
                raise InputError(f"frame {frame} of the catalogue is not in the source's sequence {sequence!r}",
                                 src.get("root"), frame)
            image = source.read_frame(plan, position[frame]).left
            h, w = image.shape[:2]
            for f in wanted[frame]:
                if (f["rle_h"], f["rle_w"]) != (h, w):
                    raise InputError(f"mask size {f['rle_h']}×{f['rle_w']} of tube {f['tube_id']} differs from "
                                     f"the image's {h}×{w}", src.get("root"), frame)
                x0, x1, y0, y1 = crop_box(f["bbox"], w, h)
                mask = mask_utils.decode({"size": [h, w], "counts": f["rle_counts"].encode()})
                folder = dest / tube_folder(f["tube_id"])
                _write_png(folder / f"frame_{frame}.png", cv2.cvtColor(image[y0:y1, x0:x1], cv2.COLOR_RGB2BGR))
                _write_png(folder / f"mask_{frame}.png", mask[y0:y1, x0:x1] * np.uint8(255))
                n += 1
    write_index(tubes, per_tube, dest)
    return n


def write_index(tubes: pa.Table, per_tube: dict[str, list[dict]], dest: Path) -> None:
    """index.parquet and index.json: the tubes' columns, crop folder and 3D track."""
    track_type = pa.list_(pa.struct([("frame", pa.int32()), ("t_ns", pa.int64()),
                                     ("position_world", pa.list_(pa.float32(), 3))]))
    tracks = [[{"frame": f["frame"], "t_ns": f["t_ns"], "position_world": f["position_world"]}
               for f in per_tube.get(tid, [])] for tid in tubes.column("tube_id").to_pylist()]
    index = tubes.append_column("folder", pa.array([tube_folder(t) for t in tubes.column("tube_id").to_pylist()],
                                                   pa.string()))
    index = index.append_column("track", pa.array(tracks, track_type))
    pq.write_table(index, dest / "index.parquet", compression="zstd")

    def clean(v):
        if isinstance(v, float) and not np.isfinite(v):
            return None
        if isinstance(v, list):
            return [clean(x) for x in v]
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        return v

    (dest / "index.json").write_text(json.dumps([clean(r) for r in index.to_pylist()], indent=1) + "\n")


EXPORTERS = {"kitti": export_kitti, "kitti-mots": export_kitti_mots, "crops": export_crops}


def export(out: str | Path, where: str, fmt: str, dest: str | Path) -> tuple[int, int]:
    """Export the tubes of catalogue ``out`` matching ``where``; (tubes, items written)."""
    if fmt not in EXPORTERS:
        raise InputError(f"unknown export format {fmt!r}; one of {', '.join(FORMATS)}")
    con = connect(out)
    try:
        tubes, frames = selected_rows(con, where)
    finally:
        con.close()
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    return tubes.num_rows, EXPORTERS[fmt](tubes, frames, read_job(Store(out)), dest)


def run_export(out: str | Path, where: str, fmt: str, dest: str | Path) -> int:
    """`mine export`: 0 on success; 2 with a message on standard error otherwise."""
    try:
        n_tubes, n_items = export(out, where, fmt, dest)
    except (MiningError, duckdb.Error) as e:
        print(f"mine export: {e}", file=sys.stderr)
        return 2
    what = {"kitti": "rows", "kitti-mots": "masks", "crops": "crops"}[fmt]
    print(f"mine export: {n_tubes} tubes, {n_items} {what} → {dest}")
    return 0
