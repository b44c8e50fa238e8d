"""Products out of the catalogue: `mine export` (formats other tools read) and `mine render`.

One format a module, as TrackEval keeps one dataset a module: ``kitti.py`` (KITTI tracking,
KITTI-MOTS), ``crops.py``, ``video_json.py`` (YouTube-VIS, TAO), ``burst.py`` (BURST), listed in
``registry.py``;
``run.py`` is the command that selects, writes and publishes. ``selection.py`` holds what
every product reads (the job record, the selected rows and their groupings), ``dest.py``
the rules for where a product goes and the export record, ``render.py`` and ``video.py``
the video. Products sit above the catalogue (they read it and re-read the frames through
the job's source); nothing below them imports them.
"""
