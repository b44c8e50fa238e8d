"""Oxford RobotCar stereo (Bumblebee XB3) in the dataset's own traversal layout.

Layout of one traversal (the sequence is the folder name)::

    <root>/<traversal>/stereo.timestamps          "<µs> <chunk id>" per line, line = frame index
    <root>/<traversal>/stereo/{left,centre,right}/<µs>.png   raw Bayer GBRG, 8 bit, 1 channel
    <root>/<traversal>/vo/vo.csv                  optional visual odometry
    <root>/models/<camera>.txt                    (or ``models_dir``) pinhole model, see below
    <root>/models/<camera>_distortion_lut.bin     undistortion look-up table

A camera model file holds ``fx fy cx cy`` on line 1 and the 4×4 ``G_camera_image`` on
lines 2–5 (image axes x right, y down, z forward → camera base frame x forward, y right,
z down). The LUT holds float64 values: W·H source x coordinates, then W·H source y
coordinates, one per *output* pixel in row-major order (the RobotCar SDK's format).

The pinhole models describe the undistorted, pair-rectified cameras, so a frame is
demosaiced, remapped through the LUT and is then rectified. The wide pair is left/right,
the narrow pair is centre/right; each pair has its own models (``stereo_wide_*``,
``stereo_narrow_*``) because the right image is rectified differently for each partner.

RobotCar downloads come in chunks; ``stereo.timestamps`` lists every frame of the
traversal, including chunks that were not downloaded. Frames whose chunk has no images
on disk are a *gap* (dropped, recorded in ``SequencePlan.gaps``), not an error.
"""

from __future__ import annotations

import csv
import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from mining.errors import ConfigError, InputError
from mining.files import check_regular, open_regular, read_text
from mining.names import check_name
from mining.sources.base import Source
from mining.types import SequencePlan, StereoCalib, StereoFrame

# Image folder and camera model name of (left, right) for each stereo pair.
PAIRS: dict[str, tuple[tuple[str, str], tuple[str, str]]] = {
    "wide": (("left", "stereo_wide_left"), ("right", "stereo_wide_right")),
    "narrow": (("centre", "stereo_narrow_left"), ("right", "stereo_narrow_right")),
}

# RobotCar stereo sensors are Bayer GBRG (SDK: BAYER_STEREO = 'gbrg'). OpenCV names a Bayer
# code after the 2nd and 3rd pixel of the 2nd row, so GBRG is OpenCV's "GR"; the fixture
# round-trip test shows the other three codes are clearly worse.
BAYER_GBRG_TO_RGB = cv2.COLOR_BayerGR2RGB

# ours: a left and right model of one rectified pair must agree on the intrinsics and the
# rotation to within this; beyond it the files do not describe a rectified pair.
RECTIFIED_TOL = 1e-3

# RobotCar layout: the stereo camera's timestamps file in each traversal folder.
TIMESTAMPS_FILE = "stereo.timestamps"

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@dataclass(frozen=True)
class CameraModel:
    """One RobotCar camera: pinhole intrinsics and the image-to-camera-base transform."""

    name: str
    fx: float
    fy: float
    cx: float
    cy: float
    G_camera_image: np.ndarray  # (4, 4)
    path: Path

    @property
    def lut_path(self) -> Path:
        return self.path.with_name(self.name + "_distortion_lut.bin")


@dataclass(frozen=True)
class VoStep:
    """One row of RobotCar ``vo.csv`` as an egomotion in our camera convention."""

    t_prev_ns: int
    t_cur_ns: int
    T_cur_prev: np.ndarray  # (4, 4), X_cur = T_cur_prev @ X_prev, camera axes x right, y down, z forward


def load_camera_model(models_dir: Path, name: str) -> CameraModel:
    """Read ``<models_dir>/<name>.txt``; InputError when missing or malformed."""
    path = Path(models_dir) / f"{name}.txt"
    try:
        lines = [ln.split() for ln in read_text(path, "camera model").splitlines() if ln.strip()]
    except FileNotFoundError:
        raise InputError(f"camera model {name} not found", path) from None
    try:
        fx, fy, cx, cy = (float(v) for v in lines[0])
        G = np.array([[float(v) for v in row] for row in lines[1:5]])
    except (ValueError, IndexError):
        raise InputError("camera model: expected 'fx fy cx cy' then a 4x4 G_camera_image", path) from None
    if G.shape != (4, 4) or len(lines) != 5:
        raise InputError("camera model: expected 'fx fy cx cy' then a 4x4 G_camera_image", path)
    return CameraModel(name, fx, fy, cx, cy, G, path)


def load_lut(path: Path, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """The undistortion LUT as cv2.remap maps (x, y), float32 (H, W); checks its size."""
    n = check_regular(path).stat().st_size // 8
    if n != 2 * width * height or path.stat().st_size % 8:
        raise InputError(
            f"distortion LUT holds {n} values but the {width}x{height} images need {2 * width * height}", path
        )
    lut = np.fromfile(path, dtype="<f8")
    map_x = lut[: width * height].reshape(height, width).astype(np.float32)
    map_y = lut[width * height :].reshape(height, width).astype(np.float32)
    return map_x, map_y


def png_size(path: Path) -> tuple[int, int, int, int]:
    """(width, height, bit depth, colour type) from the PNG header, without decoding."""
    with open_regular(path) as f:
        head = f.read(26)
    if len(head) < 26 or head[:8] != PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise InputError("not a PNG file (bad header)", path)
    w, h, depth, ctype = struct.unpack(">IIBB", head[16:26])
    return w, h, depth, ctype


def demosaic_gbrg(raw: np.ndarray) -> np.ndarray:
    """Raw GBRG Bayer (H, W) uint8 → RGB (H, W, 3) uint8."""
    return cv2.cvtColor(raw, BAYER_GBRG_TO_RGB)


def stereo_calib(left: CameraModel, right: CameraModel, width: int, height: int) -> StereoCalib:
    """Calibration of a rectified pair; the baseline is the distance between the two
    cameras' ``G_camera_image`` translations."""
    k_l = np.array([left.fx, left.fy, left.cx, left.cy])
    k_r = np.array([right.fx, right.fy, right.cx, right.cy])
    if np.abs(k_l - k_r).max() > RECTIFIED_TOL * max(1.0, np.abs(k_l).max()):
        raise InputError(f"intrinsics differ from {left.path.name}; not a rectified pair", right.path)
    if np.abs(left.G_camera_image[:3, :3] - right.G_camera_image[:3, :3]).max() > RECTIFIED_TOL:
        raise InputError(f"rotation differs from {left.path.name}; not a rectified pair", right.path)
    baseline = float(np.linalg.norm(right.G_camera_image[:3, 3] - left.G_camera_image[:3, 3]))
    if not baseline > 0:
        raise InputError(f"zero baseline against {left.path.name}", right.path)
    return StereoCalib(left.fx, left.fy, left.cx, left.cy, baseline, int(width), int(height))


@dataclass
class _Camera:
    folder: Path
    model: CameraModel
    maps: tuple[np.ndarray, np.ndarray] | None  # cv2.remap's (x, y) or fixed-point maps; None only with allow_missing_lut and no LUT


class OxfordSource(Source):
    """RobotCar stereo traversals under ``root``; ``pair`` is "wide" or "narrow".

    Undistortion is never skipped silently: a missing LUT is an InputError unless the
    caller passes ``allow_missing_lut=True`` (then frames are only demosaiced, which is
    right only for images that need no undistortion).

    ``lut_fixed_point`` (ours, default on): the LUT is turned once into OpenCV's fixed-point maps
    (``cv2.convertMaps``), which its bilinear remap otherwise rebuilds from the float maps for
    every image: the same pixels (tested), 6 instead of 8 bytes a pixel, remap ≈ 7 % cheaper at
    1280×960. False = the float maps (before issue 30).
    """

    dataset = "oxford"
    layout = (f"each traversal a folder <root>/<traversal>/ holding {TIMESTAMPS_FILE} and stereo/{{left,centre,right}}/<µs>.png "
              "(raw Bayer GBRG), the camera models and LUTs in <root>/models/ (or --option models_dir=DIR): "
              "<camera>.txt and <camera>_distortion_lut.bin from the RobotCar SDK's models/ folder")

    def __init__(
        self,
        root: str | Path,
        pair: str = "wide",
        models_dir: str | Path | None = None,
        allow_missing_lut: bool = False,
        lut_fixed_point: bool = True,
    ):
        if pair not in PAIRS:
            raise ConfigError(f"unknown RobotCar stereo pair {pair!r}; known: {sorted(PAIRS)}")
        self.root = Path(root)
        self.pair = pair
        self.models_dir = Path(models_dir) if models_dir is not None else self.root / "models"
        self.allow_missing_lut = allow_missing_lut
        self.lut_fixed_point = bool(lut_fixed_point)
        self._cameras: dict[str, tuple[_Camera, _Camera]] = {}

    def __getstate__(self) -> dict:
        # Shipped to workers without the LUT maps (~20 MB per 1280x960 pair); they reload.
        return {**self.__dict__, "_cameras": {}}

    def sequences(self) -> list[str]:
        if not self.root.is_dir():
            raise InputError("RobotCar root folder not found", self.root)
        return sorted(p.name for p in self.root.iterdir() if (p / TIMESTAMPS_FILE).is_file())

    # -- planning -------------------------------------------------------------------------

    def _read_timestamps(self, sequence: str) -> list[tuple[int, int]]:
        check_name(sequence, "sequence", "the oxford source", self.root)  # a traversal folder, never a path
        path = self.root / sequence / TIMESTAMPS_FILE
        try:
            text = read_text(path, "timestamps file")
        except FileNotFoundError:
            raise InputError("timestamps file not found", path) from None
        rows: list[tuple[int, int]] = []
        for line_no, line in enumerate(text.splitlines(), start=1):
            if not line.strip():
                continue
            parts = line.split()
            try:
                t_us, chunk = int(parts[0]), int(parts[1])
            except (ValueError, IndexError):
                raise InputError(f"line {line_no}: expected '<microseconds> <chunk id>', got {line!r}", path) from None
            if rows and t_us <= rows[-1][0]:
                raise InputError(
                    f"line {line_no}: timestamp {t_us} does not increase (previous {rows[-1][0]})", path, len(rows)
                )
            rows.append((t_us, chunk))
        if not rows:
            raise InputError("timestamps file is empty", path)
        return rows

    def _load_cameras(self, sequence: str, width: int, height: int) -> tuple[_Camera, _Camera]:
        cams = []
        for folder, name in PAIRS[self.pair]:
            model = load_camera_model(self.models_dir, name)
            if model.lut_path.is_file():
                maps = load_lut(model.lut_path, width, height)
                if self.lut_fixed_point:
                    maps = cv2.convertMaps(maps[0], maps[1], cv2.CV_16SC2)
            elif self.allow_missing_lut:
                maps = None
            else:
                raise InputError(
                    "undistortion LUT not found (pass allow_missing_lut=True only for images that need no undistortion)",
                    model.lut_path,
                )
            cams.append(_Camera(self.root / sequence / "stereo" / folder, model, maps))
        return cams[0], cams[1]

    def survey(self, sequence: str) -> SequencePlan:
        rows = self._read_timestamps(sequence)
        (lfolder, _), (rfolder, _) = PAIRS[self.pair]
        stereo = self.root / sequence / "stereo"
        # One directory listing per camera instead of a stat per frame.
        present = {}
        for folder in (lfolder, rfolder):
            d = stereo / folder
            present[folder] = {p.name for p in d.iterdir()} if d.is_dir() else set()
        chunk_has_images: dict[int, bool] = {}
        for t_us, chunk in rows:
            name = f"{t_us}.png"
            if name in present[lfolder] or name in present[rfolder]:
                chunk_has_images[chunk] = True

        frames: list[int] = []
        t_ns: list[int] = []
        gaps: list[int] = []
        problems: list[tuple[int, str]] = []
        prev_line, prev_chunk = None, None
        for line, (t_us, chunk) in enumerate(rows):
            name = f"{t_us}.png"
            has_l, has_r = name in present[lfolder], name in present[rfolder]
            if not (has_l and has_r):
                if not chunk_has_images.get(chunk):
                    continue  # chunk not downloaded: a gap
                # One image of a downloaded chunk is missing: the frame keeps its place.
                missing = stereo / (rfolder if has_l else lfolder) / name
                problems.append((len(frames), str(InputError(f"stereo image missing within downloaded chunk {chunk}",
                                                             missing, line))))
            if prev_line is not None and (line != prev_line + 1 or chunk > prev_chunk + 1):
                gaps.append(len(frames))
            frames.append(line)
            t_ns.append(t_us * 1000)
            prev_line, prev_chunk = line, chunk
        bad = {p for p, _ in problems}
        good = [k for k in range(len(frames)) if k not in bad]
        if not good:
            raise InputError(f"no {self.pair} stereo images for any of the {len(rows)} timestamps", stereo)

        first = stereo / lfolder / f"{t_ns[good[0]] // 1000}.png"
        width, height, depth, ctype = png_size(first)
        if depth != 8 or ctype != 0:
            raise InputError(
                f"expected raw Bayer 8-bit single-channel PNG, got bit depth {depth}, colour type {ctype}",
                first,
                frames[good[0]],
            )
        cams = self._load_cameras(sequence, width, height)
        self._cameras[sequence] = cams
        calib = stereo_calib(cams[0].model, cams[1].model, width, height)
        return SequencePlan(self.dataset, sequence, calib, tuple(frames), tuple(t_ns), tuple(gaps), tuple(problems))

    # -- reading --------------------------------------------------------------------------

    def read_frame(self, plan: SequencePlan, position: int) -> StereoFrame:
        cams = self._cameras.get(plan.sequence)
        if cams is None:
            cams = self._load_cameras(plan.sequence, plan.calib.width, plan.calib.height)
            self._cameras[plan.sequence] = cams
        index, t_ns = plan.frames[position], plan.t_ns[position]
        left, right = (self._load(cam, t_ns, index, plan.calib) for cam in cams)
        return StereoFrame(self.dataset, plan.sequence, index, t_ns, left, right, plan.calib)

    def _load(self, cam: _Camera, t_ns: int, index: int, calib: StereoCalib) -> np.ndarray:
        path = cam.folder / f"{t_ns // 1000}.png"
        data = np.fromfile(path, np.uint8) if check_regular(path, index).is_file() else None
        if data is None:
            raise InputError("stereo image not found", path, index)
        if data.size == 0:  # cv2.imdecode raises a bare cv2.error on an empty buffer
            raise InputError("stereo image is empty (0 bytes): an incomplete download or copy", path, index)
        try:
            raw = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        except cv2.error as e:
            raise InputError(f"cannot decode PNG ({str(e).strip()})", path, index) from None
        if raw is None:
            raise InputError("cannot decode PNG (truncated or corrupt)", path, index)
        if raw.ndim != 2 or raw.dtype != np.uint8:
            raise InputError(f"expected raw Bayer 8-bit single-channel image, got {raw.dtype} {raw.shape}", path, index)
        if raw.shape != (calib.height, calib.width):
            raise InputError(
                f"image is {raw.shape[1]}x{raw.shape[0]} but the sequence (and its LUT) is {calib.width}x{calib.height}",
                path,
                index,
            )
        rgb = demosaic_gbrg(raw)
        if cam.maps is None:
            return rgb
        return cv2.remap(rgb, cam.maps[0], cam.maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)

    # -- visual odometry ------------------------------------------------------------------

    def vo(self, sequence: str) -> list[VoStep]:
        """Relative poses from ``<traversal>/vo/vo.csv`` as egomotions in camera axes.

        A row ``source, destination, x, y, z, roll, pitch, yaw`` is, as the SDK chains it
        (``pose_source = pose_destination · T``), the transform that maps points from the
        source frame into the destination frame, in the vehicle-style camera base frame
        (x forward, y right, z down; R = Rz(yaw)·Ry(pitch)·Rx(roll)). We turn it into
        ``T_cur_prev`` in the image axes of the left camera of the pair.
        """
        path = self.root / check_name(sequence, "sequence", "the oxford source", self.root) / "vo" / "vo.csv"
        G = load_camera_model(self.models_dir, PAIRS[self.pair][0][1]).G_camera_image
        G_inv = np.linalg.inv(G)
        steps = []
        try:
            text = read_text(path, "visual odometry file")
        except FileNotFoundError:
            raise InputError("visual odometry file not found", path) from None
        reader = csv.reader(text.splitlines())
        header = next(reader, None)
        if header is None or [h.strip() for h in header[:2]] != ["source_timestamp", "destination_timestamp"]:
            raise InputError("expected header 'source_timestamp,destination_timestamp,x,y,z,roll,pitch,yaw'", path)
        for line_no, row in enumerate(reader, start=2):
            try:
                src, dst = int(row[0]), int(row[1])
                x, y, z, roll, pitch, yaw = (float(v) for v in row[2:8])
            except (ValueError, IndexError):
                raise InputError(f"line {line_no}: expected 2 timestamps and 6 numbers, got {row!r}", path) from None
            T = np.eye(4)
            T[:3, :3] = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
            T[:3, 3] = (x, y, z)
            T_dst_src = G_inv @ T @ G  # base frame → image axes
            if src > dst:  # source is the later frame: X_prev = T @ X_cur
                steps.append(VoStep(dst * 1000, src * 1000, np.linalg.inv(T_dst_src)))
            else:
                steps.append(VoStep(src * 1000, dst * 1000, T_dst_src))
        return steps
