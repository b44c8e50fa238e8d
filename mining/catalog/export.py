"""`mine export`: the tubes matching a SQL predicate, in formats other tools read.

* ``kitti`` — KITTI tracking result txt per sequence (``<dest>/<sequence>.txt``, 17 label
  columns + the tube's score; SOURCES.md §1.5), for `mine eval kitti-mot` and TrackEval.
* ``kitti-mots`` — KITTI-MOTS txt per sequence: ``time_frame id class_id img_height
  img_width rle`` with class 1 car, 2 pedestrian, 10 ignore (the MOTS annotation format,
  vision.rwth-aachen.de/page/mots), object id = class_id·1000 + track index. MOTS masks
  may not overlap: within a frame the higher-scoring tube keeps the shared pixels.
* ``crops`` — per tube ``<dest>/<tube_id with / → _>/crop_<frame>.png`` (the left image
  around the box, with ``--margin`` context: a fraction of the box's width / height on each
  side) and ``mask_<frame>.png``, frame numbers zero-padded (``crop_000010.png``: the
  sequence's largest frame number's digits, at least 6, so names sort in frame order), plus
  ``<dest>/index.parquet`` and ``index.json``: every ``tubes`` column, the crop folder, and
  per frame (``track``) the box as x1, y1, x2, y2 and COCO x, y, w, h, the 3D position in
  the camera and the world, the crop and mask file names and the crop's rectangle in the
  frame. Images are re-read through the source named in ``OUT/job.json``, each frame once.
* ``youtube-vis`` and ``tao`` — video instance segmentation / open-world tracking JSON
  (``export_vis.py``).

Boxes: the catalogue keeps x1, y1, x2, y2; COCO-style formats (YouTube-VIS, TAO, the
crops index's ``bbox_xywh``) get x, y, width, height.

DEST: an export refuses a DEST that is not empty, unless ``--overwrite`` and DEST holds
the record (``.mine-export.json``) of an earlier export: then exactly the entries that
record lists are replaced (files, and folders with what is in them; links are removed,
not followed), anything else in DEST is kept, and nothing outside DEST is touched. A
predicate that matches no tube writes and removes nothing and exits 1.

Links: an export never writes a link, so a DEST that holds one (at any depth) holds
something it did not write; it is refused, naming the link, before anything is removed
or written (a link at ``index.json`` or ``JPEGImages`` would send the files elsewhere).
The exporters write into a private folder inside DEST (``mine-export-partial-<random>``,
made by ``mkdir`` under an unpredictable name: no link can be planted in it beforehand);
only when they have all finished are the earlier export's entries removed and the new
ones renamed into DEST (``safe_files.move_in``: never onto an existing entry). So a
failed export (bad data, a full disk) leaves the earlier one as it was. The record is
written first listing the old entries, the new ones and the private folder, so even an
export killed half-way leaves a record that a later ``--overwrite`` cleans up.

Names read from the catalogue are data: the dataset and sequence names and the tube ids
must pass ``mining/names.py`` before a file name is made from them, two tubes may not
share a folder, and every file written must resolve inside DEST.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import cv2
import duckdb
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from pycocotools import mask as mask_utils

from mining.catalog import safe_files
from mining.catalog.layout import JobRecord
from mining.catalog.predicate import tubes_query
from mining.catalog.store import Store
from mining.catalog.views import connect, execute_read_only
from mining.errors import InputError, MiningError, NothingMatched
from mining.formats.kitti_tracking import ResultFrame, ResultTrack, kitti_type, write_tracking_results
from mining.names import check_name, inside, name_problem, tube_folder
from mining.progress import Ticker

FORMATS = ("kitti", "kitti-mots", "crops", "youtube-vis", "tao")
# KITTI-MOTS class ids (MOTS annotation format): car 1, pedestrian 2, ignore region 10.
MOTS_CLASS = {"car": 1, "person": 2}
MOTS_IGNORE = 10
MOTS_IDS_PER_CLASS = 1000  # object id = class_id * 1000 + instance; instance < 1000
CROP_MARGIN = 0.15  # ours: context around the box, as a fraction of the box's width / height
CROP_MARGIN_MIN_PX = 8  # ours: at least this much context for small boxes
MIN_FRAME_DIGITS = 6  # ours: frame numbers in file names are zero-padded to at least this width


def read_job(store: Store) -> dict:
    """The resolved job config recorded in OUT/job.json, or {} when the catalogue has none."""
    record = JobRecord.load(store)
    return {} if record is None else record.config


# What a predicate can cause: unknown names, wrong types, a value that does not convert. The rest
# (a damaged table, a full disk) is the catalogue's, not the predicate's.
PREDICATE_ERRORS = (duckdb.ParserException, duckdb.BinderException, duckdb.CatalogException,
                    duckdb.ConversionException, duckdb.TypeMismatchException, duckdb.OutOfRangeException)


def selected_rows(con: duckdb.DuckDBPyConnection, where: str) -> tuple[pa.Table, pa.Table]:
    """(tubes, tube_frames) of the tubes matching ``where``, frames in (tube, frame) order.

    ``where`` is parsed as one expression (``predicate.tubes_query``) and both queries run
    through the read-only checks on ``con`` (a ``views.connect`` connection)."""
    tubes_sql = tubes_query(where)
    try:
        tubes = execute_read_only(con, f"SELECT * FROM ({tubes_sql}) ORDER BY dataset, sequence, t_start, tube_id")
        frames = execute_read_only(con, f"SELECT f.* FROM tube_frames AS f SEMI JOIN ({tubes_sql}) AS t "
                                        "USING (dataset, sequence, tube_id) ORDER BY f.dataset, f.sequence, f.tube_id, f.frame")
        return tubes.to_arrow_table(), frames.to_arrow_table()
    except PREDICATE_ERRORS as e:
        raise InputError(f"bad --where predicate {where!r}: {e}") from None
    except duckdb.Error as e:  # a damaged or missing file (the message names it), out of memory, …
        raise InputError(f"cannot read the catalogue: {e}") from None


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
    """The tubes per (dataset, sequence), both checked names (they become file names)."""
    out: dict[tuple[str, str], list[dict]] = {}
    checked: set[tuple[str, str]] = set()
    for t in tubes.to_pylist():
        key = (t["dataset"], t["sequence"])
        if key not in checked:
            check_name(key[0], "dataset", "the catalogue")
            check_name(key[1], "sequence", "the catalogue")
            checked.add(key)
        out.setdefault(key, []).append(t)
    return out


def _frames_by_tube(frames: pa.Table) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = {}
    for f in frames.to_pylist():
        out.setdefault(f["tube_id"], []).append(f)
    return out


def _sequence_file(dest: Path, sequence: str) -> Path:
    """``<dest>/<sequence>.txt`` of a checked sequence name, inside DEST."""
    return inside(dest, f"{check_name(sequence, 'sequence', 'the catalogue')}.txt")


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
        n += write_tracking_results(_sequence_file(dest, sequence),
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
        _sequence_file(dest, sequence).write_text("\n".join(lines) + ("\n" if lines else ""))
        n += len(lines)
    return n


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


def frame_digits(frames) -> int:
    """Width of zero-padded frame numbers in file names: the largest frame's digits, at least
    MIN_FRAME_DIGITS (so names sort in frame order)."""
    return max(MIN_FRAME_DIGITS, len(str(max(frames, default=0))))


def crop_names(frame: int, digits: int) -> tuple[str, str]:
    """(crop, mask) file names of a tube's crop at ``frame``: ``crop_000010.png``, ``mask_000010.png``."""
    return f"crop_{frame:0{digits}d}.png", f"mask_{frame:0{digits}d}.png"


def export_crops(tubes: pa.Table, frames: pa.Table, job: dict, dest: Path, margin: float = CROP_MARGIN) -> int:
    """Per-tube crop and mask PNGs plus the index; returns the crops written."""
    if not margin >= 0:
        raise InputError(f"--margin must be a fraction ≥ 0 of the box, got {margin}")
    folders = tube_folders(tubes, dest)  # every id checked before anything is written
    by_sequence = _by_sequence(tubes)
    source, src = job_source(job, "crops")
    per_tube = _frames_by_tube(frames)
    files: dict[tuple[str, int], dict] = {}  # (tube, frame) → what the index records of its crop
    n = 0
    for (_, sequence), seq_tubes in by_sequence.items():
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
                                 src.get("root"), frame)
            image = source.read_frame(plan, position[frame]).left
            h, w = image.shape[:2]
            for f in wanted[frame]:
                if (f["rle_h"], f["rle_w"]) != (h, w):
                    raise InputError(f"mask size {f['rle_h']}×{f['rle_w']} of tube {f['tube_id']} differs from "
                                     f"the image's {h}×{w}", src.get("root"), frame)
                x0, x1, y0, y1 = crop_box(f["bbox"], w, h, margin)
                mask = mask_utils.decode({"size": [h, w], "counts": f["rle_counts"].encode()})
                folder = folders.get(f["tube_id"])
                if folder is None:
                    raise InputError(f"tube_frames row of tube {f['tube_id']!r}, which the tubes table lacks",
                                     src.get("root"), frame)
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
        if isinstance(v, float) and not np.isfinite(v):
            return None
        if isinstance(v, list):
            return [clean(x) for x in v]
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        return v

    (dest / "index.json").write_text(json.dumps([clean(r) for r in index.to_pylist()], indent=1) + "\n")


def _export_youtube_vis(*args, **kwargs) -> int:
    from mining.catalog.export_vis import export_youtube_vis

    return export_youtube_vis(*args, **kwargs)


def _export_tao(*args, **kwargs) -> int:
    from mining.catalog.export_vis import export_tao

    return export_tao(*args, **kwargs)


EXPORTERS = {"kitti": export_kitti, "kitti-mots": export_kitti_mots, "crops": export_crops,
             "youtube-vis": _export_youtube_vis, "tao": _export_tao}
VIDEO_FORMATS = ("youtube-vis", "tao")  # one video per sequence: they take the catalogue's frames and --images
ITEMS = {"kitti": "rows", "kitti-mots": "masks", "crops": "crops", "youtube-vis": "tube annotations",
         "tao": "frame annotations"}
RECORD = ".mine-export.json"  # in DEST: what the export wrote there, so --overwrite replaces exactly that
STAGING_PREFIX = "mine-export-partial-"  # the exporters' private folder in DEST (a safe name: a record may list it)


def _entries(dest: Path) -> list[str]:
    return sorted(p.name for p in dest.iterdir()) if dest.is_dir() else []


def _recorded(dest: Path) -> list[str]:
    """The top-level names in ``dest`` an earlier export recorded (RECORD), checked to be
    plain names inside ``dest``."""
    try:
        names = json.loads((dest / RECORD).read_text())["written"]
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise TypeError("'written' is not a list of names")
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InputError(f"not a record of an earlier export ({e}); remove DEST's contents yourself or choose "
                         "another folder", dest / RECORD) from None
    bad = [n for n in names if n == RECORD or name_problem(n) is not None]
    if bad:
        raise InputError(f"the record names {bad!r}, which are not entries of DEST; remove DEST's contents yourself",
                         dest / RECORD)
    return names


def check_dest(dest: Path, overwrite: bool) -> list[str]:
    """Refuse a DEST that is not an empty or absent folder, unless ``overwrite`` and DEST
    holds an earlier export's RECORD and no link; returns the entries that replacing will
    remove."""
    if dest.exists() and not dest.is_dir():
        raise InputError("DEST is not a folder", dest)
    present = _entries(dest)
    if not present:
        return []
    if not overwrite:
        raise InputError(f"DEST is not empty ({len(present)} entries: {', '.join(present[:5])}"
                         f"{', …' if len(present) > 5 else ''}); choose an empty folder, or pass --overwrite to replace "
                         "an earlier export there", dest)
    links = safe_files.links_under(dest)
    if links:
        raise InputError(f"DEST holds links, which no export writes: {safe_files.describe_links(links, dest)}; an "
                         "export never writes through a link (the files would land elsewhere) and nothing was "
                         "removed: remove the links yourself or choose another folder", dest)
    if RECORD not in present:
        raise InputError(f"--overwrite replaces only what an earlier `mine export` recorded in {RECORD}, and DEST "
                         f"has none ({len(present)} other entries): remove them yourself or choose another folder", dest)
    return [n for n in _recorded(dest) if n in present]


def _remove(dest: Path, names: list[str]) -> None:
    """Delete the entries ``names`` of ``dest`` (links themselves, never what they point to)."""
    for name in names:
        safe_files.remove_tree(dest / name)


def _write_record(dest: Path, record: dict) -> None:
    """DEST's RECORD, written atomically and never through a link (``safe_files``)."""
    safe_files.write_atomic(dest, RECORD, (json.dumps(record, indent=1) + "\n").encode())


def _video_frames(con: duckdb.DuckDBPyConnection, tubes: pa.Table) -> dict[tuple[str, str], list[int]]:
    """The frames the catalogue mined, per (dataset, sequence) of ``tubes``, in frame order."""
    seqs = {(d, s) for d, s in zip(tubes.column("dataset").to_pylist(), tubes.column("sequence").to_pylist())}
    out: dict[tuple[str, str], list[int]] = {}
    for d, s, f in con.execute("SELECT dataset, sequence, frame FROM frames ORDER BY dataset, sequence, frame").fetchall():
        if (d, s) in seqs:
            out.setdefault((d, s), []).append(f)
    return out


def export(out: str | Path, where: str, fmt: str, dest: str | Path, margin: float | None = None,
           images: bool = False, overwrite: bool = False) -> tuple[int, int]:
    """Export the tubes of catalogue ``out`` matching ``where``; (tubes, items written).

    DEST must be empty (or absent); with ``overwrite`` the entries an earlier export
    recorded in DEST's RECORD are replaced (nothing else in DEST, nothing outside it), once
    the new export is complete in a private folder (module docstring). NothingMatched,
    before anything is written or removed, when no tube matches."""
    if fmt not in EXPORTERS:
        raise InputError(f"unknown export format {fmt!r}; one of {', '.join(EXPORTERS)}")
    options: dict = {}
    if margin is not None:
        if fmt != "crops":
            raise InputError("--margin applies to --format crops only")
        options["margin"] = margin
    if images:
        if fmt not in VIDEO_FORMATS:
            raise InputError(f"--images applies to --format {' and '.join(VIDEO_FORMATS)} only")
        options["images"] = True
    dest = Path(dest)
    replaced = check_dest(dest, overwrite)
    job = read_job(Store(out))
    con = connect(out)
    try:
        tubes, frames = selected_rows(con, where)
        if fmt in VIDEO_FORMATS:
            options["video_frames"] = _video_frames(con, tubes)
    finally:
        con.close()
    if not tubes.num_rows:
        raise NothingMatched(f"no tube matches --where {where!r}; nothing written")
    dest.mkdir(parents=True, exist_ok=True)
    staging = safe_files.private_dir(dest, STAGING_PREFIX)
    try:
        n = EXPORTERS[fmt](tubes, frames, job, staging, **options)
        written = sorted(os.listdir(staging))
        kept = set(_entries(dest)) - set(replaced) - {staging.name}
        clash = sorted(set(written) & (kept | {RECORD}))
        if clash:
            raise InputError(f"this export writes {', '.join(clash)}, which DEST holds and no earlier export recorded; "
                             "nothing was removed or written: move them away or choose another folder", dest)
        record = {"format": fmt, "catalogue": str(out), "where": where, "tubes": tubes.num_rows, "items": n,
                  "options": {k: v for k, v in options.items() if k != "video_frames"}}
        # Until the new entries are in, the record names old, new and partial alike: an export
        # killed in between leaves nothing that a later --overwrite would not remove.
        _write_record(dest, record | {"written": sorted(set(replaced) | set(written) | {staging.name})})
        _remove(dest, replaced)
        for name in written:
            safe_files.move_in(staging, name, dest)
        _write_record(dest, record | {"written": written})
    finally:
        safe_files.remove_tree(staging)
    return tubes.num_rows, n


def run_export(out: str | Path, where: str, fmt: str, dest: str | Path, margin: float | None = None,
               images: bool = False, overwrite: bool = False) -> int:
    """`mine export`: 0 on success; NothingMatched (``cli.main``: exit 1) when no tube matches; 2 with a
    message on standard error otherwise."""
    try:
        n_tubes, n_items = export(out, where, fmt, dest, margin, images, overwrite)
    except (MiningError, duckdb.Error) as e:
        print(f"mine export: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # a writer that raised the system's error (a full disk…): one line naming the file
        print(f"mine export: {safe_files.write_error(e, e.filename or dest)}", file=sys.stderr)
        return 2
    print(f"mine export: {n_tubes} tubes, {n_items} {ITEMS[fmt]} → {dest}")
    return 0
