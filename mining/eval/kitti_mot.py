"""KITTI MOT evaluation (2D boxes): HOTA, CLEAR MOT and identity metrics for Car and Pedestrian.

Follows the KITTI tracking devkit as TrackEval's ``Kitti2DBox`` dataset implements it, so the
numbers agree with TrackEval's. The rules, per sequence, per evaluated class, per frame:

1. **Classes.** Car and Pedestrian are evaluated separately. Ground truth of the class and of
   its neighbour (distractor) class takes part: Van for Car, Person (person sitting) for
   Pedestrian. Tracker rows take part only if their type is the class itself. Types are
   compared case-insensitively and must be KITTI types (an unknown type is an error, as in
   TrackEval).
2. **Distractors.** Tracker and gt boxes of the frame are matched one-to-one (Hungarian,
   maximal total IoU over pairs with IoU ≥ 0.5). A tracker box matched to a neighbour-class
   gt box, or to a gt box that is occluded more than level 2 (level 3 = unknown) or
   truncated more than level 0, is removed: neither TP nor FP.
3. **DontCare and small boxes.** A tracker box left unmatched in step 2 is removed if its
   height is ≤ 25 px, or if more than half of its area lies inside one DontCare region
   (intersection / tracker-box area > 0.5).
4. **Ignored gt.** Ground truth of the neighbour class and gt occluded > 2 or truncated > 0
   is dropped after step 2: never a FN.

What remains is scored with box IoU as similarity by ``hota.py``, ``clear.py`` and ``identity.py``
(a CLEAR/ID match needs IoU ≥ 0.5). Counts add up over sequences; see those modules.

Input. Ground truth in the label_02 layout (``<gt_dir>/<seq>.txt``, 17 columns), results as
KITTI tracking txt (``<result_dir>/<seq>.txt``, 18 columns with the score; 17 are accepted
since no metric here uses the score). Result track ids must be ≥ 0 (TrackEval drops negative
ids silently; we refuse them, as they mean untracked detections). A track id may appear
only once per frame and class. Frame counts come from a seqmap (4th column = number of
frames) or else from the largest frame index seen in the gt or the results.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from mining.boxes import box_ioa, box_iou
from mining.checks import count, input_file, input_folder
from mining.errors import InputError
from mining.files import read_text
from mining.eval.clear import clear_metrics, clear_sums, combine_clear_sums
from mining.eval.hota import combine_hota_sums, hota_metrics, hota_sums
from mining.eval.identity import combine_identity_sums, identity_metrics, identity_sums
from mining.formats.kitti_tracking import KittiTrackingRows, read_kitti_tracking, read_seqmap

# KITTI object types (devkit readme); DontCare marks regions that were not labelled.
KITTI_TYPES = ("car", "van", "truck", "pedestrian", "person", "cyclist", "tram", "misc", "dontcare")
NEIGHBOUR_CLASS = {"car": "van", "pedestrian": "person"}  # REFERENCE (KITTI MOT): neighbour classes
_EPS = np.finfo(float).eps


@dataclass(frozen=True)
class KittiMotProtocol:
    """The constants of the KITTI tracking benchmark (devkit ``evaluate_tracking.py``, TrackEval)."""

    match_iou: float = 0.5  # REFERENCE (KITTI MOT): a match needs box IoU ≥ 0.5
    max_occlusion: int = 2  # REFERENCE (KITTI devkit): gt occluded more than this is ignored
    max_truncation: int = 0  # REFERENCE (KITTI devkit): gt truncated more than this is ignored
    min_height_px: float = 25.0  # REFERENCE (KITTI devkit): unmatched tracker boxes this short or shorter are ignored
    dontcare_ioa: float = 0.5  # REFERENCE (KITTI devkit): unmatched tracker boxes more than this inside DontCare are ignored


class KittiMotResults(dict):
    """Combined metrics, ``results[class][metric]``, plus ``per_sequence[seq][class][metric]``.

    ``sums[seq][class]`` keeps each sequence's summable counts, so that any subset of the
    sequences can be combined later (``combine_kitti_mot``) without evaluating again.
    """

    def __init__(self, combined: dict, per_sequence: dict, seconds: float, sums: dict | None = None):
        super().__init__(combined)
        self.per_sequence = per_sequence
        self.seconds = seconds  # wall time of the evaluation
        self.sums = sums or {}


@dataclass
class ClassSequence:
    """One class of one sequence after the KITTI preprocessing: what the metrics score."""

    gt_ids: list[np.ndarray]  # per frame, contiguous 0-based gt ids
    tracker_ids: list[np.ndarray]  # per frame, contiguous 0-based tracker ids
    similarity: list[np.ndarray]  # per frame, (len(gt_ids[t]), len(tracker_ids[t])) box IoU


def _check_types(rows: KittiTrackingRows) -> np.ndarray:
    kinds = np.char.lower(rows.type)
    unknown = ~np.isin(kinds, KITTI_TYPES)
    if unknown.any():
        i = int(np.flatnonzero(unknown)[0])
        raise InputError(f"unknown object type {rows.type[i]!r}; KITTI types are {KITTI_TYPES}", rows.path,
                         int(rows.frame[i]))
    return kinds


def _check_frames(rows: KittiTrackingRows, n_frames: int) -> None:
    late = rows.frame >= n_frames
    if late.any():
        frame = int(rows.frame[late][0])
        raise InputError(f"frame {frame} beyond the sequence's {n_frames} frames", rows.path, frame)


def _check_unique_ids(rows: KittiTrackingRows, mask: np.ndarray, what: str) -> None:
    pairs = np.stack([rows.frame[mask], rows.track_id[mask]], axis=1)
    uniq, counts = np.unique(pairs, axis=0, return_counts=True)
    if (counts > 1).any():
        frame, tid = uniq[counts > 1][0]
        raise InputError(f"{what} id {tid} appears {counts[counts > 1][0]} times in one frame", rows.path, int(frame))


def _relabel(ids: list[np.ndarray]) -> list[np.ndarray]:
    """Map ids to 0 … n−1 (sorted order), so that the metrics can index arrays with them."""
    unique = np.unique(np.concatenate(ids)) if ids else np.empty(0, np.int64)
    return [np.searchsorted(unique, x) for x in ids]


def preprocess_class(gt: KittiTrackingRows, res: KittiTrackingRows, cls: str, n_frames: int,
                     protocol: KittiMotProtocol = KittiMotProtocol()) -> ClassSequence:
    """Apply the KITTI rules (module docstring) for class ``cls`` ('car' or 'pedestrian')."""
    cls = cls.lower()
    neighbour = NEIGHBOUR_CLASS[cls]
    gt_kind, res_kind = _check_types(gt), _check_types(res)
    _check_frames(gt, n_frames)
    _check_frames(res, n_frames)

    gt_take = np.isin(gt_kind, (cls, neighbour))
    res_take = res_kind == cls
    _check_unique_ids(gt, gt_take, "ground-truth")
    _check_unique_ids(res, res_take, "track")
    # Levels are integers in KITTI; a fractional value is cut as TrackEval does (int()).
    occluded = gt.occluded.astype(int)
    truncated = gt.truncated.astype(int)
    gt_ignored = (gt_kind == neighbour) | (occluded > protocol.max_occlusion) | (truncated > protocol.max_truncation)
    dontcare = gt_kind == "dontcare"

    gt_rows = _rows_by_frame(gt.frame, gt_take, n_frames)
    res_rows = _rows_by_frame(res.frame, res_take, n_frames)
    dc_rows = _rows_by_frame(gt.frame, dontcare, n_frames)
    out = ClassSequence([], [], [])
    for t in range(n_frames):
        g, r = gt_rows[t], res_rows[t]
        iou = box_iou(gt.box[g], res.box[r], min_area=_EPS)
        removed = np.zeros(len(r), bool)
        matched = np.zeros(len(r), bool)
        if len(g) and len(r):
            # Step 2: the distractor matching (IoU below the threshold counts as no overlap).
            score = np.where(iou >= protocol.match_iou - _EPS, iou, 0.0)
            rows, cols = linear_sum_assignment(score, maximize=True)
            ok = score[rows, cols] > _EPS
            rows, cols = rows[ok], cols[ok]
            matched[cols] = True
            removed[cols[gt_ignored[g[rows]]]] = True
        # Step 3: unmatched boxes that are too small or inside a DontCare region.
        boxes = res.box[r]
        too_small = boxes[:, 3] - boxes[:, 1] <= protocol.min_height_px + _EPS
        in_dontcare = (box_ioa(boxes, gt.box[dc_rows[t]], min_area=_EPS) > protocol.dontcare_ioa + _EPS).any(axis=1)
        removed |= ~matched & (too_small | in_dontcare)
        # Step 4: keep only gt that counts.
        keep_gt = ~gt_ignored[g]
        out.gt_ids.append(gt.track_id[g[keep_gt]])
        out.tracker_ids.append(res.track_id[r[~removed]])
        out.similarity.append(iou[keep_gt][:, ~removed])
    out.gt_ids = _relabel(out.gt_ids)
    out.tracker_ids = _relabel(out.tracker_ids)
    return out


def _rows_by_frame(frame: np.ndarray, mask: np.ndarray, n_frames: int) -> list[np.ndarray]:
    """Row indices of each frame, in file order (matching ties are resolved by this order)."""
    idx = np.flatnonzero(mask)
    idx = idx[np.argsort(frame[idx], kind="stable")]
    bounds = np.searchsorted(frame[idx], np.arange(n_frames + 1))
    return [idx[bounds[t]:bounds[t + 1]] for t in range(n_frames)]


def _metrics(hota: dict, clear: dict, ident: dict, counts: dict) -> dict[str, float]:
    return {**hota_metrics(hota), **clear_metrics(clear), **identity_metrics(ident), **counts}


def evaluate_kitti_mot(gt_dir_or_files: str | Path | Mapping[str, str | Path], result_dir: str | Path,
                       sequences: Sequence[str] | None = None, classes: Sequence[str] = ("Car", "Pedestrian"),
                       seqmap: str | Path | None = None,
                       protocol: KittiMotProtocol = KittiMotProtocol()) -> KittiMotResults:
    """Evaluate tracking results against KITTI ground truth.

    ``gt_dir_or_files``: a label_02 folder (``<dir>/<seq>.txt``) or a mapping seq → gt file.
    ``result_dir``: folder with ``<seq>.txt`` results. ``sequences``: which to evaluate
    (default: all of the seqmap). Returns combined metrics per class, with
    ``.per_sequence[seq][class]`` holding each sequence's own.
    """
    start = time.perf_counter()
    frame_counts = read_seqmap(seqmap) if seqmap is not None else None
    if sequences is None:
        if frame_counts is None:
            raise InputError("no sequences given and no seqmap to take them from")
        sequences = list(frame_counts)
    for cls in classes:
        if cls.lower() not in NEIGHBOUR_CLASS:
            raise InputError(f"class {cls!r} cannot be evaluated; KITTI MOT evaluates {tuple(NEIGHBOUR_CLASS)}")

    sums: dict[str, dict[str, dict]] = {}
    per_sequence: dict[str, dict[str, dict[str, float]]] = {}
    for seq in sequences:
        if isinstance(gt_dir_or_files, Mapping):
            if seq not in gt_dir_or_files:
                raise InputError(f"no ground-truth file given for sequence {seq}")
            gt_path = Path(gt_dir_or_files[seq])
        else:
            gt_path = Path(gt_dir_or_files) / f"{seq}.txt"
        gt = read_kitti_tracking(gt_path)
        res = read_kitti_tracking(Path(result_dir) / f"{seq}.txt")
        if (res.track_id < 0).any():
            frame = int(res.frame[res.track_id < 0][0])
            raise InputError("negative track id: results must be tracks with ids ≥ 0", res.path, frame)
        if frame_counts is not None:
            if seq not in frame_counts:
                raise InputError(f"sequence {seq} is not in the seqmap", seqmap)
            n_frames = frame_counts[seq]
        else:
            n_frames = 1 + int(max(gt.frame.max(initial=-1), res.frame.max(initial=-1)))

        per_sequence[seq], sums[seq] = {}, {}
        for cls in classes:
            data = preprocess_class(gt, res, cls, n_frames, protocol)
            args = (data.gt_ids, data.tracker_ids, data.similarity)
            h, c, i = hota_sums(*args), clear_sums(*args, protocol.match_iou), identity_sums(*args, protocol.match_iou)
            counts = {
                "GT_Dets": sum(len(x) for x in data.gt_ids),
                "Dets": sum(len(x) for x in data.tracker_ids),
                "GT_IDs": len(np.unique(np.concatenate(data.gt_ids))) if n_frames else 0,
                "IDs": len(np.unique(np.concatenate(data.tracker_ids))) if n_frames else 0,
            }
            sums[seq][cls] = {"hota": h, "clear": c, "ident": i, "counts": counts}
            per_sequence[seq][cls] = _metrics(h, c, i, counts)

    combined = combine_kitti_mot([sums[seq] for seq in sequences], classes)
    return KittiMotResults(combined, per_sequence, time.perf_counter() - start, sums)


def combine_kitti_mot(per_sequence_sums: Sequence[Mapping[str, Mapping[str, dict]]],
                      classes: Sequence[str] = ("Car", "Pedestrian")) -> dict[str, dict[str, float]]:
    """Metrics per class over several sequences from their ``KittiMotResults.sums[seq]``.

    Counts add up over sequences (as the benchmark combines them), so combining the sums of
    separately evaluated sequences gives the same numbers as evaluating them together.
    """
    combined = {}
    for cls in classes:
        s = [x[cls] for x in per_sequence_sums]
        counts = {k: sum(x["counts"][k] for x in s) for k in ("GT_Dets", "Dets", "GT_IDs", "IDs")}
        combined[cls] = _metrics(combine_hota_sums([x["hota"] for x in s]), combine_clear_sums([x["clear"] for x in s]),
                                 combine_identity_sums([x["ident"] for x in s]), counts)
    return combined


TABLE_COLUMNS = ("HOTA", "DetA", "AssA", "LocA", "MOTA", "MOTP", "IDF1", "IDSW", "Frag", "MT", "PT", "ML",
                 "TP", "FP", "FN", "GT_IDs")


def format_table(results: KittiMotResults | Mapping[str, Mapping[str, float]], per_sequence: bool = False) -> str:
    """Plain-text table: one row per class (and per sequence and class with ``per_sequence``)."""
    rows = []
    if per_sequence and isinstance(results, KittiMotResults):
        for seq, by_class in results.per_sequence.items():
            rows += [(seq, cls, m) for cls, m in by_class.items()]
    rows += [("all", cls, m) for cls, m in results.items()]
    header = f"{'seq':>5} {'class':<10} " + " ".join(f"{c:>7}" for c in TABLE_COLUMNS)
    lines = [header, "-" * len(header)]
    for seq, cls, m in rows:
        cells = [f"{m[c]:7d}" if isinstance(m[c], (int, np.integer)) else f"{m[c]:7.4f}" for c in TABLE_COLUMNS]
        lines.append(f"{seq:>5} {cls:<10} " + " ".join(cells))
    return "\n".join(lines)


def evaluate_first_frames(gt_dir: str | Path, result_dir: str | Path, sequences: Sequence[str],
                          classes: Sequence[str], n_frames: int) -> KittiMotResults:
    """``evaluate_kitti_mot`` over the first ``n_frames`` frames of each sequence: ground-truth
    rows from frame ``n_frames`` on are dropped, and a seqmap gives every sequence ``n_frames``
    frames (the truncated label files and the seqmap live in a temporary folder)."""
    with tempfile.TemporaryDirectory() as tmp:
        gt_files, lines = {}, []
        for seq in sequences:
            rows = [ln for ln in read_text(Path(gt_dir) / f"{seq}.txt", "KITTI tracking file").splitlines()
                    if ln.strip() and int(ln.split()[0]) < n_frames]
            gt_files[seq] = Path(tmp) / f"{seq}.txt"
            gt_files[seq].write_text("\n".join(rows) + "\n")
            lines.append(f"{seq} empty 000000 {n_frames:06d}")
        seqmap = Path(tmp) / "seqmap"
        seqmap.write_text("\n".join(lines) + "\n")
        return evaluate_kitti_mot(gt_files, result_dir, sequences, classes, seqmap)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine eval kitti-mot``'s options."""
    p.add_argument("--gt", type=input_folder, required=True, help="label_02 folder")
    p.add_argument("--results", type=input_folder, required=True, help="folder of <seq>.txt results")
    p.add_argument("--sequences", nargs="+", required=True)
    p.add_argument("--seqmap", type=input_file, help="seqmap with frame counts (else the largest frame seen)")
    p.add_argument("--classes", nargs="+", default=["Car", "Pedestrian"])
    p.add_argument("--frames", type=count(), help="evaluate only the first N frames of each sequence")
    p.add_argument("--per-sequence", action="store_true")


def run(args: argparse.Namespace) -> int:
    """``mine eval kitti-mot``: the metrics table on standard output."""
    if args.frames is not None:  # the first N frames only; --seqmap is not read
        results = evaluate_first_frames(Path(args.gt), args.results, args.sequences, tuple(args.classes), args.frames)
    else:
        results = evaluate_kitti_mot(Path(args.gt), args.results, args.sequences, tuple(args.classes), args.seqmap)
    print(format_table(results, per_sequence=args.per_sequence))
    return 0
