"""KITTI raw "synced + rectified" drives: ``<date>/<date>_drive_NNNN_sync/…`` (SOURCES.md §2).

Stereo frames come from image_02 (left) and image_03 (right) with the image_02
timestamps. The evaluation helpers read what the tracking layout lacks: Velodyne scans
(→ sparse depth in the image_02 camera) and OXTS GPS/IMU packets (→ camera poses).
"""

from __future__ import annotations

import calendar
import math
import re
from datetime import datetime
from pathlib import Path
from typing import NamedTuple

import numpy as np

from mining.errors import InputError
from mining.files import check_regular, read_text
from mining.formats.kitti_calib import KittiCalib, read_raw_calib
from mining.sources.base import Source
from mining.sources.kitti import listed_frames, png_size, read_stereo_pair
from mining.types import SequencePlan, StereoFrame

_DATE = re.compile(r"\d{4}_\d{2}_\d{2}")
_DRIVE = re.compile(r"(\d{4}_\d{2}_\d{2})_drive_\d{4}_sync")
_TIMESTAMP = re.compile(r"(\d{4}-\d{2}-\d{2} \d{2}:\d{2}:\d{2})(?:\.(\d{1,9}))?")
_DIGITS = 10  # frame file names are 10-digit indices

EARTH_RADIUS_M = 6378137.0  # ours: WGS84 equatorial radius, as in the KITTI raw devkit's OXTS → pose conversion


class OxtsPacket(NamedTuple):
    """One OXTS line, fields in the order of ``oxts/dataformat.txt`` (14th field is az)."""

    lat: float  # deg
    lon: float  # deg
    alt: float  # m
    roll: float  # rad
    pitch: float  # rad
    yaw: float  # rad, 0 = east, counter-clockwise
    vn: float  # m/s north
    ve: float  # m/s east
    vf: float  # m/s forward
    vl: float  # m/s left
    vu: float  # m/s up
    ax: float
    ay: float
    az: float
    af: float
    al: float
    au: float
    wx: float
    wy: float
    wz: float
    wf: float
    wl: float
    wu: float
    pos_accuracy: float
    vel_accuracy: float
    navstat: float
    numsats: float
    posmode: float
    velmode: float
    orimode: float


def parse_timestamp_ns(text: str) -> int | None:
    """'YYYY-MM-DD HH:MM:SS.nnnnnnnnn' → integer ns, exactly; the wall-clock time is read as UTC
    (KITTI writes local time; only differences matter)."""
    m = _TIMESTAMP.fullmatch(text.strip())
    if m is None:
        return None
    try:
        seconds = calendar.timegm(datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S").timetuple())
    except ValueError:
        return None
    return seconds * 1_000_000_000 + int((m.group(2) or "0").ljust(9, "0"))


def lidar_depth_image(points: np.ndarray, calib: KittiCalib, width: int, height: int) -> np.ndarray:
    """Sparse depth (H, W) float32 of Velodyne points in the image_02 camera; NaN = no point.

    Each point goes Velodyne → rectified camera 0 → image via P2. The homogeneous w of
    P2·X is the depth in image_02's own frame (z_rect0 + P2[2,3]). Points behind the
    camera are dropped; where several points land on one pixel the nearest wins.
    """
    pts = np.asarray(points, np.float64)
    X = np.c_[pts[:, :3], np.ones(len(pts))]
    uvw = X @ (calib.P2 @ calib.T_rect0_velo).T
    w = uvw[:, 2]
    front = w > 0
    uvw, w = uvw[front], w[front]
    u = np.round(uvw[:, 0] / w).astype(np.int64)  # pixel centres at integer coordinates
    v = np.round(uvw[:, 1] / w).astype(np.int64)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    flat, w = v[inside] * width + u[inside], w[inside]
    order = np.lexsort((w, flat))  # by pixel, then nearest first
    flat, w = flat[order], w[order]
    first = np.ones(len(flat), bool)
    first[1:] = flat[1:] != flat[:-1]
    depth = np.full(width * height, np.nan, np.float32)
    depth[flat[first]] = w[first]
    return depth.reshape(height, width)


def oxts_to_world(packets: list[OxtsPacket]) -> np.ndarray:
    """(N, 4, 4) IMU-to-world transforms, world = the first packet's IMU frame.

    KITTI raw devkit convention (Geiger et al., IJRR 2013): position by a Mercator
    projection whose scale is fixed by the first latitude; orientation
    R = Rz(yaw) · Ry(pitch) · Rx(roll) in an east-north-up frame.
    """
    scale = math.cos(math.radians(packets[0].lat))
    out = np.empty((len(packets), 4, 4))
    for i, p in enumerate(packets):
        x = scale * EARTH_RADIUS_M * math.radians(p.lon)
        y = scale * EARTH_RADIUS_M * math.log(math.tan(math.radians(90.0 + p.lat) / 2.0))
        cr, sr = math.cos(p.roll), math.sin(p.roll)
        cp, sp = math.cos(p.pitch), math.sin(p.pitch)
        cy, sy = math.cos(p.yaw), math.sin(p.yaw)
        Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
        Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
        Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
        out[i] = np.eye(4)
        out[i, :3, :3] = Rz @ Ry @ Rx
        out[i, :3, 3] = (x, y, p.alt)
    return np.linalg.inv(out[0]) @ out


class KittiRawSource(Source):
    """KITTI raw synced+rectified drives, named ``"2011_09_26_drive_0001_sync"``.

    ``root`` holds date folders (``2011_09_26/``) or is a date folder itself. The form
    ``"2011_09_26/2011_09_26_drive_0001_sync"`` is accepted too.
    """

    dataset = "kitti-raw"

    def __init__(self, root: str | Path):
        if root is None:
            raise InputError("the kitti-raw source needs a root folder")
        self.root = Path(root)
        if not self.root.is_dir():
            raise InputError("KITTI raw root folder does not exist", self.root)

    # -- naming ---------------------------------------------------------------------

    def _date_dirs(self) -> list[Path]:
        if _DATE.fullmatch(self.root.name) or (self.root / "calib_cam_to_cam.txt").exists():
            return [self.root]
        return sorted(p for p in self.root.iterdir() if p.is_dir() and _DATE.fullmatch(p.name))

    def _drive_dir(self, sequence: str) -> Path:
        name = sequence.rsplit("/", 1)[-1]
        m = _DRIVE.fullmatch(name)
        if m is None:
            raise InputError(f"{sequence!r} is not a KITTI raw drive name like 2011_09_26_drive_0001_sync", self.root)
        date_dir = self.root if self.root.name == m.group(1) else self.root / m.group(1)
        if not date_dir.is_dir() and (self.root / "calib_cam_to_cam.txt").exists():
            date_dir = self.root  # a date folder under another name
        drive = date_dir / name
        if not drive.is_dir():
            raise InputError("drive folder does not exist", drive)
        return drive

    def sequences(self) -> list[str]:
        return [p.name for d in self._date_dirs() for p in sorted(d.iterdir()) if p.is_dir() and _DRIVE.fullmatch(p.name)]

    # -- calibration ----------------------------------------------------------------

    def kitti_calib(self, sequence: str) -> KittiCalib:
        """P_rect_00..03, R_rect_00, velo→cam and imu→velo of the drive's recording day."""
        return read_raw_calib(self._drive_dir(sequence).parent)

    def velo_to_cam(self, sequence: str) -> np.ndarray:
        """4×4 mapping Velodyne points into rectified camera 0: R_rect_00 · [R | T]."""
        return self.kitti_calib(sequence).T_rect0_velo

    # -- Source interface -----------------------------------------------------------

    def survey(self, sequence: str) -> SequencePlan:
        drive = self._drive_dir(sequence)
        kc = read_raw_calib(drive.parent)
        left_dir, right_dir = drive / "image_02" / "data", drive / "image_03" / "data"
        frames, problems = listed_frames(left_dir, right_dir, _DIGITS)
        k = next((i for i in frames if i not in problems), None)
        if k is None:
            raise InputError("no frame has both its left and right image", left_dir)
        first = left_dir / f"{k:0{_DIGITS}d}.png"
        size = png_size(first, k)
        if size != kc.image_size:
            raise InputError(
                f"image is {size[0]}×{size[1]} but S_rect_02 in {kc.path} says {kc.image_size[0]}×{kc.image_size[1]}",
                first,
                k,
            )
        t_ns = self._timestamps(drive / "image_02" / "timestamps.txt", frames)
        pos = {idx: p for p, idx in enumerate(frames)}
        return SequencePlan(self.dataset, sequence, kc.stereo(*size), frames, t_ns,
                            problems=tuple((pos[i], msg) for i, msg in sorted(problems.items())))

    @staticmethod
    def _timestamps(path: Path, frames: tuple[int, ...]) -> tuple[int, ...]:
        """t_ns of the given frames (line i = frame i), strictly increasing."""
        if not check_regular(path).is_file():
            raise InputError("timestamps file is missing", path)
        lines = read_text(path, "timestamps file").splitlines()
        out: list[int] = []
        for idx in frames:
            if idx >= len(lines):
                raise InputError(f"no timestamp line for this frame ({len(lines)} lines)", path, idx)
            t = parse_timestamp_ns(lines[idx])
            if t is None:
                raise InputError(f"line {idx + 1}: bad timestamp {lines[idx].strip()!r}", path, idx)
            if out and t <= out[-1]:
                raise InputError(f"timestamps not increasing: {lines[idx].strip()} follows {lines[idx - 1].strip()}", path, idx)
            out.append(t)
        return tuple(out)

    def read_frame(self, plan: SequencePlan, position: int) -> StereoFrame:
        idx = plan.frames[position]
        drive = self._drive_dir(plan.sequence)
        name = f"{idx:0{_DIGITS}d}.png"
        left, right = read_stereo_pair(drive / "image_02" / "data" / name, drive / "image_03" / "data" / name, idx, plan.calib)
        return StereoFrame(self.dataset, plan.sequence, idx, plan.t_ns[position], left, right, plan.calib)

    # -- evaluation helpers ---------------------------------------------------------

    def velodyne(self, sequence: str, frame: int) -> np.ndarray:
        """(N, 4) float32 Velodyne scan: x forward, y left, z up (m), reflectance."""
        path = self._drive_dir(sequence) / "velodyne_points" / "data" / f"{frame:0{_DIGITS}d}.bin"
        if not check_regular(path, frame).is_file():
            raise InputError("Velodyne scan is missing", path, frame)
        size = path.stat().st_size
        if size % 16:
            raise InputError(f"size {size} B is not a multiple of 16 B (4 float32 per point)", path, frame)
        return np.fromfile(path, dtype="<f4").reshape(-1, 4)

    def lidar_depth(self, sequence: str, frame: int) -> np.ndarray:
        """Sparse LiDAR depth image of one frame in the image_02 camera (NaN = no point)."""
        kc = self.kitti_calib(sequence)
        return lidar_depth_image(self.velodyne(sequence, frame), kc, *kc.image_size)

    def oxts(self, sequence: str) -> dict[int, OxtsPacket]:
        """OXTS packets by frame index, for the frames whose oxts/data file exists."""
        data = self._drive_dir(sequence) / "oxts" / "data"
        if not data.is_dir():
            raise InputError("OXTS folder is missing", data)
        out: dict[int, OxtsPacket] = {}
        for path in sorted(data.glob("*.txt")):
            if not re.fullmatch(rf"\d{{{_DIGITS}}}", path.stem):
                continue
            frame = int(path.stem)
            values = read_text(path, "OXTS file", frame).split()
            if len(values) != len(OxtsPacket._fields):
                raise InputError(f"{len(values)} values, expected {len(OxtsPacket._fields)}", path, frame)
            try:
                out[frame] = OxtsPacket(*map(float, values))
            except ValueError:
                raise InputError("a value is not a number", path, frame) from None
        return out

    def oxts_poses(self, sequence: str) -> tuple[tuple[int, ...], np.ndarray]:
        """Frames with both images and OXTS, and their (N, 4, 4) image_02 camera-to-world poses.

        World = the first such frame's image_02 camera (its pose is the identity):
        pose_i = inv(W_0) · W_i with W_i = T_world_imu,i · inv(T_cam2_imu).
        """
        plan_frames = self.plan(sequence).frames
        packets = self.oxts(sequence)
        frames = tuple(f for f in plan_frames if f in packets)
        if not frames:
            raise InputError("no frame has both images and an OXTS packet", self._drive_dir(sequence) / "oxts" / "data")
        T_world_imu = oxts_to_world([packets[f] for f in frames])
        W = T_world_imu @ np.linalg.inv(self.kitti_calib(sequence).T_cam2_imu)
        return frames, np.linalg.inv(W[0]) @ W
