"""Mined tubes → KITTI tracking result txt, for `mine track` (and `mine eval kitti-mot`, TrackEval).

The file format and its writer live in ``mining/formats/kitti_tracking.py``; this module
only says which tubes and fields go in: the selected tubes, each under its tube id, typed
by its category (the same rule as its known flag), scored by its total score.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import numpy as np

from mining.catalog import safe_files
from mining.formats.kitti_tracking import ResultFrame, ResultTrack, kitti_tracking_text, kitti_type, tracking_result_rows
from mining.types import MinedTube


def result_tracks(mined: Iterable[MinedTube], unclassified_as: str = "Misc") -> Iterator[ResultTrack]:
    """The selected tubes as tracking results."""
    for m in mined:
        if not m.selected:
            continue
        kind = kitti_type(m.category.category, m.category.known, unclassified_as)
        frames = (ResultFrame(f.frame, f.observed, f.box, f.size, f.position_cam) for f in m.tube.frames)
        yield ResultTrack(m.tube.tube_id, kind, m.score.total, frames)


def write_tubes_kitti(path: str | Path, mined: Iterable[MinedTube],
                      rect0_from_cam2: Callable[[np.ndarray], np.ndarray] | None = None,
                      observed_only: bool = True, unclassified_as: str = "Misc", overwrite: bool = False) -> int:
    """Write the selected tubes as a KITTI tracking result file; returns the rows written. The
    file keeps the destination rule (``safe_files.write_file``: never through a link, an
    existing file replaced only with ``overwrite``).

    ``rect0_from_cam2`` maps image_02 camera points to KITTI's rectified camera 0 (the
    frame of KITTI's 3D fields, ``KittiCalib.cam2_to_rect0``); without it the 3D fields
    are placeholders.
    """
    rows = tracking_result_rows(result_tracks(mined, unclassified_as), rect0_from_cam2, observed_only, path)
    safe_files.write_file(path, kitti_tracking_text(rows).encode(), overwrite)
    return len(rows)
