"""Products out of the catalogue: `mine export` (formats other tools read) and `mine render`.

One format a module, as TrackEval keeps one dataset a module: ``kitti.py`` (KITTI tracking,
KITTI-MOTS), ``crops.py``, ``video_json.py`` (YouTube-VIS, TAO), ``burst.py`` (BURST),
``fiftyone_video.py``, ``rerun_rrd.py``, listed in ``registry.py``; a format imports only the
shared modules, never another format (as TrackEval's datasets import only their base).
``run.py`` is the command that selects, writes and publishes, ``render.py`` the `mine render`
command. The shared modules: ``selection.py`` holds what every product reads (the job record,
the selected rows and their groupings, the videos), ``source_frames.py`` the frames re-read
through the job's source, ``json_annotations.py`` what the JSON annotation formats share,
``depth.py`` the stereo depth and its colours, ``dest.py`` the rules for where a product
goes and the export record, ``video.py`` the video files. Products sit above the catalogue
(they read it and re-read the frames through the job's source); nothing below them imports
them.
"""
