"""The export formats: name → the module and function that write it (one format a module).

A writer is ``write(tubes, frames, job, dest, **options) -> int``: the selected ``tubes`` and
their ``tube_frames`` rows (``selection.selected_rows``), the typed config of the job that
made the catalogue (None without ``job.json``), the folder to fill, and the options its
entry names; it returns the items it wrote (``items`` says what they are). Writers are
imported when used, so the CLI reads the names (its ``--format`` choices) without loading
OpenCV or Arrow.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class ExportFormat:
    name: str  # --format
    module: str  # mining.export.<module>
    writer: str  # its writing function
    items: str  # what the count a writer returns counts (the command's summary line)
    # keyword options beyond the rows: margin (crops); images, video_frames (videos); video_rates (burst:
    # frames per second); frame_rows (the catalogue's frames rows per sequence: poses)
    options: tuple[str, ...] = ()
    masks: bool = True  # the format writes or reads the masks: a tube with a bad one is left out (selection.py)

    @property
    def video(self) -> bool:
        """One video per sequence: the writer takes the catalogue's frames and --images."""
        return "images" in self.options

    def load(self) -> Callable[..., int]:
        """The writing function (imported now)."""
        return getattr(importlib.import_module(f"mining.export.{self.module}"), self.writer)


FORMATS: dict[str, ExportFormat] = {f.name: f for f in (
    ExportFormat("kitti", "kitti", "export_kitti", "rows", masks=False),  # boxes only: masks are not read
    ExportFormat("kitti-mots", "kitti", "export_kitti_mots", "masks", ("unknown_class",)),
    ExportFormat("crops", "crops", "export_crops", "crops", ("margin",)),
    ExportFormat("youtube-vis", "video_json", "export_youtube_vis", "tube annotations", ("images", "video_frames")),
    ExportFormat("tao", "video_json", "export_tao", "frame annotations", ("images", "video_frames")),
    ExportFormat("burst", "burst", "export_burst", "masks", ("images", "video_frames", "video_rates")),
    ExportFormat("fiftyone", "fiftyone_video", "export_fiftyone", "videos", ("images", "video_frames")),
    ExportFormat("rerun", "rerun_rrd", "export_rerun", "recordings", ("images", "video_frames", "frame_rows")),
)}
VIDEO_FORMATS = tuple(name for name, f in FORMATS.items() if f.video)
