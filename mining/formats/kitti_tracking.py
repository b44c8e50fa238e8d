"""KITTI tracking label and result files (``label_02/<seq>.txt``, tracker output, detections).

One object per line, space separated (shared/data/SOURCES.md §1.4, §1.5):

    frame track_id type truncated occluded alpha x1 y1 x2 y2 h w l x y z rotation_y [score]

Ground truth has 17 columns; tracker results add an 18th, the score. A file must use one
column count throughout. DontCare rows carry track id −1 and placeholder values; they are
read like any other row (what they mean is up to the evaluation). Rows keep file order,
which the evaluation relies on for reproducible matching.

``read_seqmap`` reads a KITTI seqmap (the sequences of a split and their frame counts).

``write_tracking_results`` is the one writer of mined tubes as tracking results: `mine
track` feeds it tubes in memory, `mine export --format kitti` tubes from the catalogue.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from mining.errors import InputError
from mining.files import read_text

LABEL_COLUMNS = 17  # KITTI tracking devkit: label_02 lines
RESULT_COLUMNS = 18  # KITTI tracking devkit: result lines = label columns + score

# COCO category → KITTI type; everything else is written as Misc (KITTI MOT ignores it).
KITTI_TYPE = {"car": "Car", "person": "Pedestrian", "bicycle": "Cyclist", "motorcycle": "Cyclist",
              "truck": "Truck", "bus": "Truck", "train": "Tram"}


@dataclass
class KittiTrackingRows:
    """All rows of one file, column by column (N rows)."""

    path: Path
    frame: np.ndarray  # (N,) int64, 0-based frame index
    track_id: np.ndarray  # (N,) int64; −1 for DontCare and for untracked detections
    type: np.ndarray  # (N,) str, as written (Car, Van, Pedestrian, Person, DontCare, …)
    truncated: np.ndarray  # (N,) float64, truncation level 0/1/2 (−1 for DontCare)
    occluded: np.ndarray  # (N,) float64, occlusion level 0…3 (−1 for DontCare)
    alpha: np.ndarray  # (N,) float64, observation angle [rad]
    box: np.ndarray  # (N, 4) float64, x1 y1 x2 y2 in image_02 [px]
    dimensions: np.ndarray  # (N, 3) float64, h w l [m]
    location: np.ndarray  # (N, 3) float64, x y z bottom centre, rectified camera [m]
    rotation_y: np.ndarray  # (N,) float64 [rad]
    score: np.ndarray  # (N,) float64; NaN when the file has 17 columns (ground truth)

    def __len__(self) -> int:
        return int(self.frame.shape[0])

    @staticmethod
    def results(path: Path, frame, track_id, types, box, score, dimensions=None, location=None) -> KittiTrackingRows:
        """Tracker output rows: the fields a tracker fills, placeholders in the rest
        (−1 truncation/occlusion, −10 angles, and the devkit's −1 / −1000 for missing 3D)."""
        n = len(frame)
        return KittiTrackingRows(
            path=Path(path),
            frame=np.asarray(frame, np.int64).reshape(n),
            track_id=np.asarray(track_id, np.int64).reshape(n),
            type=np.asarray(types, dtype=object).reshape(n),
            truncated=np.full(n, -1.0),
            occluded=np.full(n, -1.0),
            alpha=np.full(n, -10.0),
            box=np.asarray(box, np.float64).reshape(n, 4),
            dimensions=np.full((n, 3), -1.0) if dimensions is None else np.asarray(dimensions, np.float64).reshape(n, 3),
            location=np.full((n, 3), -1000.0) if location is None else np.asarray(location, np.float64).reshape(n, 3),
            rotation_y=np.full(n, -10.0),
            score=np.asarray(score, np.float64).reshape(n),
        )

    @property
    def has_score(self) -> bool:
        return len(self) > 0 and not np.isnan(self.score).all()


def _as_int(text: str, what: str, path: Path, line_no: int, frame: int | None) -> int:
    try:
        return int(text)
    except ValueError:
        pass  # "3.0" is an integer too; anything else is reported below
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"line {line_no}: {what} {text!r} is not a number", path, frame) from None
    if not value.is_integer():
        raise InputError(f"line {line_no}: {what} {text!r} is not an integer", path, frame)
    return int(value)


def read_kitti_tracking(path: str | Path, require_score: bool = False) -> KittiTrackingRows:
    """Read a KITTI tracking label (17 columns) or result (18 columns) file.

    An empty file is valid (no objects). ``require_score`` demands the 18-column result format.
    """
    p = Path(path)
    try:
        lines = read_text(p, "KITTI tracking file").splitlines()
    except OSError as e:
        raise InputError(f"cannot read KITTI tracking file: {e.strerror or e}", p) from None

    frames, ids, types, numbers, line_nos = [], [], [], [], []
    n_columns = None
    for line_no, line in enumerate(lines, start=1):
        fields = line.split()
        if not fields:
            continue  # a trailing blank line is common and harmless
        frame = _as_int(fields[0], "frame", p, line_no, None)
        if len(fields) not in (LABEL_COLUMNS, RESULT_COLUMNS):
            raise InputError(
                f"line {line_no}: expected {LABEL_COLUMNS} (label) or {RESULT_COLUMNS} (result) columns, got {len(fields)}",
                p, frame,
            )
        if n_columns is None:
            n_columns = len(fields)
        elif len(fields) != n_columns:
            raise InputError(f"line {line_no}: {len(fields)} columns where earlier lines have {n_columns}", p, frame)
        if frame < 0:
            raise InputError(f"line {line_no}: negative frame index {frame}", p, frame)
        frames.append(frame)
        line_nos.append(line_no)
        ids.append(_as_int(fields[1], "track id", p, line_no, frame))
        types.append(fields[2])
        try:
            row = [float(x) for x in fields[3:]]
        except ValueError:
            raise InputError(f"line {line_no}: a numeric column is not a number", p, frame) from None
        if n_columns == LABEL_COLUMNS:
            row.append(np.nan)
        numbers.append(row)

    if require_score and n_columns == LABEL_COLUMNS:
        raise InputError(f"tracking results need {RESULT_COLUMNS} columns (label columns + score), got {LABEL_COLUMNS}", p)

    num = np.asarray(numbers, np.float64).reshape(-1, RESULT_COLUMNS - 3)
    bad_box = ~np.isfinite(num[:, 3:7]).all(axis=1)
    if bad_box.any():
        i = int(np.flatnonzero(bad_box)[0])
        raise InputError(f"line {line_nos[i]}: 2D box is not finite", p, frames[i])
    return KittiTrackingRows(
        path=p,
        frame=np.asarray(frames, np.int64),
        track_id=np.asarray(ids, np.int64),
        type=np.asarray(types, dtype=str),
        truncated=num[:, 0],
        occluded=num[:, 1],
        alpha=num[:, 2],
        box=num[:, 3:7],
        dimensions=num[:, 7:10],
        location=num[:, 10:13],
        rotation_y=num[:, 13],
        score=num[:, 14],
    )


def read_seqmap(path: str | Path) -> dict[str, int]:
    """KITTI seqmap: ``SEQ empty 000000 NFRAMES`` per line → {seq: number of frames}."""
    p = Path(path)
    try:
        lines = read_text(p, "seqmap").splitlines()
    except OSError as e:
        raise InputError(f"cannot read seqmap: {e.strerror or e}", p) from None
    frames = {}
    for line_no, line in enumerate(lines, start=1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) < 4 or not fields[3].isdigit():
            raise InputError(f"line {line_no}: expected 'SEQ empty START NFRAMES', got {line!r}", p)
        frames[fields[0]] = int(fields[3])
    return frames


def kitti_tracking_text(rows: KittiTrackingRows, with_score: bool = True) -> str:
    """Rows in the KITTI tracking format; 18 columns with ``with_score`` (NaN scores → 1)."""
    out = []
    for i in range(len(rows)):
        values = [rows.alpha[i], *rows.box[i], *rows.dimensions[i], *rows.location[i], rows.rotation_y[i]]
        # Levels are small integers in KITTI files; %g keeps them so.
        text = (f"{rows.frame[i]} {rows.track_id[i]} {rows.type[i]} {rows.truncated[i]:g} {rows.occluded[i]:g} "
                + " ".join(f"{v:.6f}" for v in values))
        if with_score:
            score = 1.0 if np.isnan(rows.score[i]) else rows.score[i]
            text += f" {score:.6f}"
        out.append(text)
    return "\n".join(out) + ("\n" if out else "")


def write_kitti_tracking(path: str | Path, rows: KittiTrackingRows, with_score: bool = True) -> None:
    """Write rows in the KITTI tracking format (``kitti_tracking_text``) to ``path``, a file in a
    folder the caller owns (a private or temporary one: this opens ``path`` as given)."""
    Path(path).write_text(kitti_tracking_text(rows, with_score))


# -- mined tubes as tracking results ----------------------------------------------------


def kitti_type(category: str | None, known: bool | None, unclassified_as: str = "Misc") -> str:
    """The KITTI type of a tube, by the same rule as its ``known`` flag: a known tube's COCO
    category mapped by KITTI_TYPE (other COCO classes: Misc), an unknown tube "Misc" (KITTI's
    type for objects outside its classes), an unclassified one ``unclassified_as``."""
    if known is None:
        return unclassified_as
    return KITTI_TYPE.get(category, "Misc") if known else "Misc"


class ResultFrame(NamedTuple):
    """One frame of a tube, as a tracking result needs it."""

    frame: int
    observed: bool
    box: object  # (4,) x1 y1 x2 y2 in image_02 [px]
    size: object  # (3,) w h l [m]
    position_cam: object  # (3,) box centre in the image_02 camera [m]; NaN when unknown


class ResultTrack(NamedTuple):
    """One tube, as a tracking result needs it: its id in the file, KITTI type, score, frames."""

    track_id: int
    type: str
    score: float
    frames: Iterable[ResultFrame]


def tracking_result_rows(tracks: Iterable[ResultTrack],
                         rect0_from_cam2: Callable[[np.ndarray], np.ndarray] | None = None,
                         observed_only: bool = True, path: str | Path = "<tubes>") -> KittiTrackingRows:
    """One row per (observed) frame of each track, in (frame, track id) order.

    KITTI's 3D fields are the box's bottom centre in rectified camera 0 and h w l:
    ``rect0_from_cam2`` maps image_02 camera points there (e.g. ``KittiCalib.cam2_to_rect0``);
    without it, or where position or size is not finite, the 3D fields are placeholders.
    """
    rows = []
    for t in tracks:
        for f in t.frames:
            if observed_only and not f.observed:
                continue
            size, pos = np.asarray(f.size, np.float64), np.asarray(f.position_cam, np.float64)
            if rect0_from_cam2 is not None and np.isfinite(pos).all() and np.isfinite(size).all():
                loc = rect0_from_cam2((pos + np.array([0.0, size[1] / 2, 0.0]))[None])[0]  # KITTI: bottom centre
                dims = (size[1], size[0], size[2])  # KITTI: h w l
            else:
                loc, dims = (-1000.0, -1000.0, -1000.0), (-1.0, -1.0, -1.0)
            rows.append((f.frame, t.track_id, t.type, f.box, dims, loc, t.score))
    rows.sort(key=lambda r: (r[0], r[1]))
    return KittiTrackingRows.results(path, [r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows],
                                     [r[3] for r in rows], [r[6] for r in rows],
                                     dimensions=[r[4] for r in rows], location=[r[5] for r in rows])


def write_tracking_results(path: str | Path, tracks: Iterable[ResultTrack],
                           rect0_from_cam2: Callable[[np.ndarray], np.ndarray] | None = None,
                           observed_only: bool = True) -> int:
    """Write tracks as an 18-column KITTI tracking result file (folders made); returns the rows."""
    rows = tracking_result_rows(tracks, rect0_from_cam2, observed_only, path)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_kitti_tracking(path, rows, with_score=True)
    return len(rows)
