"""`mine export --format rerun`: each sequence as a Rerun recording (``DEST/<dataset>_<sequence>.rrd``),
which the Rerun viewer opens (``rerun DEST/kitti_0005.rrd``) and ``rerun.chunk.RrdReader`` reads.

One recording per sequence (application ``tube_miner``, recording id ``<dataset>/<sequence>``)
on two timelines: ``frame`` (the source's frame index) and ``time`` (seconds since the
sequence's first exported frame). Its frames are the ones the catalogue mined (the ``frames``
table) and those its tubes span. The entities:

* ``world`` — static view coordinates RDF: the world of a segment is its first camera's
  (x right, y down, z forward), as the catalogue's poses and positions are;
* ``world/camera`` — per frame the ego pose (the ``frames`` table's ``pose``, camera-to-world
  of the segment) as a transform, with the ``segment`` and ``source_frame`` as values;
* ``world/camera/image`` — with ``--images``: the pinhole of the source's rectified left
  camera, and under it ``rgb`` (the left frame, JPEG) and ``depth`` (the stereo depth of the
  job's own geometry stage, its disparity step with the job's ``[geometry.stereo]``, as
  ``mine render --depth`` draws it; uint16 in 1/256 m as KITTI's depth maps, 0 where none or
  beyond ``max_depth_m``). The
  catalogue keeps no depth, so without ``--images`` (or where the source frames are not
  reachable) there is none, nor an image;
* ``world/camera/image/tubes`` — the tubes' masks per frame as one segmentation image
  (class id = track id + 1; where masks overlap the higher-scored tube's pixel is shown;
  the annotation context on ``world`` names each class ``<track> <category>``); and
  ``world/camera/image/boxes``, their boxes (x1, y1, x2, y2 as the catalogue keeps them);
* ``world/tubes/<track>`` — a tube in 3D: per frame its filtered footpoint
  (``position_world``, a point) and a box of its filtered size standing on it (``Boxes3D``,
  axes along the frame's camera: the catalogue keeps no heading); statically its
  ``tube_id``, category, ``category_prob`` and score as values.

Track ids are 0, 1, … per sequence in catalogue order (the KITTI exports' ids). With the
job's ``export.observed_only`` (the default) frames where a tube is only predicted are left
out, as in the other tracking exports. The recording is streamed from the SDK's binary sink
into the file through ``catalog/safe_files.py``. Writing needs the Rerun SDK (``pip install
'tube-miner[rerun]'``).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np
import pyarrow as pa

from mining.catalog import safe_files
from mining.catalog.rows import decode_mask
from mining.config import JobConfig
from mining.errors import InputError
from mining.export.depth import stereo_depth
from mining.export.selection import Video, category_label, export_settings, frames_by_tube, videos
from mining.export.source_frames import read_frames
from mining.progress import Ticker

APPLICATION_ID = "tube_miner"  # ours: the recordings' application id (the viewer groups recordings by it)
FRAME_TIMELINE, TIME_TIMELINE = "frame", "time"  # ours: the timelines' names
JPEG_QUALITY = 90  # ours: the rgb images' JPEG quality (the recording stays a tenth of raw RGB)
FLUSH_EVERY = 32  # ours: frames logged between two copies of the SDK's buffer into the file
# REFERENCE: KITTI's depth maps' unit (uint16 PNGs of depth × 256): 3.9 mm steps up to 256 m, half the bytes of float32
DEPTH_UNITS_PER_M = 256.0
RRD_SUFFIX = ".rrd"  # REFERENCE: Rerun's recording files


def _rerun():
    """The Rerun SDK, or an InputError saying which extra brings it."""
    try:
        import rerun
    except ImportError:
        raise InputError("--format rerun needs the Rerun SDK: pip install 'tube-miner[rerun]'") from None
    return rerun


def recording_id(dataset: str, sequence: str) -> str:
    return f"{dataset}/{sequence}"


def _pose(row: dict) -> np.ndarray:
    return np.asarray(row["pose"], np.float64).reshape(4, 4)


def box_center(footpoint, size, pose: np.ndarray | None) -> np.ndarray:
    """The centre of a box of ``size`` (width, height, length) standing on ``footpoint``:
    half its height up along the camera's up (−y of the frame's camera in the world; the
    world's −y without a pose)."""
    up = np.array([0.0, -1.0, 0.0]) if pose is None else pose[:3, :3] @ np.array([0.0, -1.0, 0.0])
    return np.asarray(footpoint, np.float64) + up * float(size[1]) / 2


class _Tubes:
    """One sequence's tubes with their track ids, rows and colours."""

    def __init__(self, v: Video, per_tube: dict[str, list[dict]], observed_only: bool):
        self.tubes = v.tubes
        self.by_frame: dict[int, list[tuple[int, dict, dict]]] = {}  # frame → (track, tube, row), by score
        for track, t in enumerate(v.tubes):
            for row in per_tube.get(t["tube_id"], []):
                if row["observed"] or not observed_only:
                    self.by_frame.setdefault(row["frame"], []).append((track, t, row))
        for rows in self.by_frame.values():
            rows.sort(key=lambda x: x[1]["score"])  # painted in score order: the best tube's pixel is on top

    def name(self, track: int) -> str:
        return f"{track} {category_label(self.tubes[track])}"


def _log_static(rr, rec, v: Video, tubes: _Tubes) -> None:
    rec.log("world", rr.ViewCoordinates.RDF, static=True)
    rec.log("world", rr.AnnotationContext(
        [rr.ClassDescription(info=rr.AnnotationInfo(id=track + 1, label=tubes.name(track)))
         for track in range(len(v.tubes))]), static=True)
    for track, t in enumerate(v.tubes):
        rec.log(f"world/tubes/{track}", rr.AnyValues(
            tube_id=t["tube_id"], category=category_label(t), score=float(t["score"]),
            **({} if t["category_prob"] is None else {"category_prob": float(t["category_prob"])})), static=True)


def _log_frame(rr, rec, v: Video, tubes: _Tubes, frame: int, pose_row: dict | None) -> None:
    pose = None if pose_row is None else _pose(pose_row)
    if pose is not None:
        rec.log("world/camera", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]),
                rr.AnyValues(segment=int(pose_row["segment"]), source_frame=int(frame)))
    here = tubes.by_frame.get(frame, [])
    segmentation = np.zeros((v.height, v.width), np.uint16)
    for track, _, row in here:
        segmentation[decode_mask(row).astype(bool)] = track + 1
    rec.log("world/camera/image/tubes", rr.SegmentationImage(segmentation))
    rec.log("world/camera/image/boxes", rr.Boxes2D(
        array=np.array([row["bbox"] for _, _, row in here], np.float32).reshape(-1, 4),
        array_format=rr.Box2DFormat.XYXY, class_ids=[track + 1 for track, _, _ in here]))
    for track, t, row in here:
        rec.log(f"world/tubes/{track}", rr.Points3D([row["position_world"]], class_ids=[track + 1]),
                rr.Boxes3D(centers=[box_center(row["position_world"], row["size"], pose)],
                           sizes=[row["size"]], labels=[tubes.name(track)],
                           **({} if pose is None else {"quaternions": [_quaternion(pose[:3, :3])]})))


def _quaternion(r: np.ndarray) -> list[float]:
    """The unit quaternion (x, y, z, w) of rotation matrix ``r``."""
    w = np.sqrt(max(0.0, 1.0 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    x = np.sqrt(max(0.0, 1.0 + r[0, 0] - r[1, 1] - r[2, 2])) / 2
    y = np.sqrt(max(0.0, 1.0 - r[0, 0] + r[1, 1] - r[2, 2])) / 2
    z = np.sqrt(max(0.0, 1.0 - r[0, 0] - r[1, 1] + r[2, 2])) / 2
    x, y, z = np.copysign(x, r[2, 1] - r[1, 2]), np.copysign(y, r[0, 2] - r[2, 0]), np.copysign(z, r[1, 0] - r[0, 1])
    return [float(x), float(y), float(z), float(w)]


def _log_images(rr, rec, job: JobConfig, v: Video) -> Callable[[int], None]:
    """Log the pinhole once; returns a function logging frame ``k``'s rgb and depth (the
    frames are read in order, one at a time)."""
    from mining.geometry.disparity import StereoMatcher

    plan, pairs = read_frames(job, v.sequence, v.frames, (v.height, v.width), "--images")
    calib = plan.calib
    rec.log("world/camera/image", rr.Pinhole(image_from_camera=calib.K, resolution=[calib.width, calib.height]),
            static=True)
    matcher, far = StereoMatcher(job.geometry.stereo, calib.bf), job.geometry.stereo.max_depth_m
    it = iter(pairs)

    def log(k: int) -> None:
        pair = next(it)
        ok, jpeg = cv2.imencode(".jpg", cv2.cvtColor(pair.left, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise InputError("cannot encode the frame as JPEG", job.source.root, v.frames[k])
        rec.log("world/camera/image/rgb", rr.EncodedImage(contents=jpeg.tobytes(), media_type="image/jpeg"))
        depth = np.nan_to_num(stereo_depth(matcher, pair, far), nan=0.0)
        depth = np.clip(np.round(depth * DEPTH_UNITS_PER_M), 0, np.iinfo(np.uint16).max).astype(np.uint16)
        rec.log("world/camera/image/depth", rr.DepthImage(depth, meter=DEPTH_UNITS_PER_M))
    return log


def write_recording(rr, f: BinaryIO, job: JobConfig | None, v: Video, tubes: _Tubes, poses: dict[int, dict],
                    images: bool, tick: Callable[[], None]) -> None:
    """One sequence's recording, streamed into ``f``."""
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id(v.dataset, v.sequence), send_properties=False)
    stream = rec.binary_stream()
    _log_static(rr, rec, v, tubes)
    image_of = _log_images(rr, rec, job, v) if images else None
    t0 = min((poses[f]["t_ns"] for f in v.frames if f in poses), default=None)
    times = {row["frame"]: row["t_ns"] for rows in tubes.by_frame.values() for _, _, row in rows}
    t0 = min(times.values(), default=0) if t0 is None else t0
    for k, frame in enumerate(v.frames):
        rec.set_time(FRAME_TIMELINE, sequence=int(frame))
        t = poses[frame]["t_ns"] if frame in poses else times.get(frame)
        if t is not None:
            rec.set_time(TIME_TIMELINE, duration=(int(t) - int(t0)) / 1e9)
        _log_frame(rr, rec, v, tubes, frame, poses.get(frame))
        if image_of is not None:
            image_of(k)
        tick()
        if (k + 1) % FLUSH_EVERY == 0:
            f.write(stream.read(flush=True) or b"")
    rec.flush()
    f.write(stream.read(flush=True) or b"")


def export_rerun(tubes: pa.Table, frames: pa.Table, job: JobConfig | None, dest: Path,
                 video_frames: dict[tuple[str, str], list[int]] | None = None,
                 frame_rows: dict[tuple[str, str], list[dict]] | None = None, images: bool = False) -> int:
    """``DEST/<dataset>_<sequence>.rrd`` per sequence; returns the recordings written."""
    rr = _rerun()
    observed_only = export_settings(job).observed_only
    per_tube = frames_by_tube(frames)
    vids = videos(tubes, frames, video_frames or {})
    ticker = Ticker("rerun frames", sum(len(v.frames) for v in vids))
    done = [0]

    def tick() -> None:
        done[0] += 1
        ticker.tick(done[0])
    for v in vids:
        poses = {r["frame"]: r for r in (frame_rows or {}).get((v.dataset, v.sequence), [])}
        seq_tubes = _Tubes(v, per_tube, observed_only)
        safe_files.write_atomic(dest, v.name + RRD_SUFFIX,
                                lambda f, v=v, p=poses, s=seq_tubes: write_recording(rr, f, job, v, s, p, images, tick))
    ticker.close()
    return len(vids)
