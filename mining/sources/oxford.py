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

The root may instead hold the traversal as downloaded, its tar chunks unextracted, and may be
a pyarrow filesystem URI (``s3://…``) either way: ``oxford_tar.py``.

``stride`` (ours) keeps every N-th line of ``stereo.timestamps`` (frame indices stay the
line numbers): the others are never read; ``rate_hz`` picks the stride nearest a target rate.
The plan's ``note`` says how many were skipped.
"""

from __future__ import annotations

import csv
import math
import posixpath
import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from mining.checks import Count
from mining.errors import ConfigError, InputError, decode_text
from mining.files import check_regular, open_regular
from mining.names import check_name
from mining.sources.base import Source
from mining.sources.oxford_tar import Located, TarTraversal, chunk_traversals
from mining.sources.tarchunks import Root, adopt_indexes, indexes_under
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
    path: str  # as shown in messages: a local path or a URI

    @property
    def lut_name(self) -> str:
        return self.name + "_distortion_lut.bin"


@dataclass(frozen=True)
class VoStep:
    """One row of RobotCar ``vo.csv`` as an egomotion in our camera convention."""

    t_prev_ns: int
    t_cur_ns: int
    T_cur_prev: np.ndarray  # (4, 4), X_cur = T_cur_prev @ X_prev, camera axes x right, y down, z forward


def load_camera_model(models_dir: str | Path | Root, name: str) -> CameraModel:
    """Read ``<models_dir>/<name>.txt`` (a folder or a URI); InputError when missing or malformed."""
    models = models_dir if isinstance(models_dir, Root) else Root(models_dir)
    path = models.show(f"{name}.txt")
    try:
        text = decode_text(models.read(f"{name}.txt"), path, "camera model")
    except FileNotFoundError:
        raise InputError(f"camera model {name} not found", path) from None
    lines = [ln.split() for ln in text.splitlines() if ln.strip()]
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
    path = Path(path)
    return lut_maps(np.fromfile(check_regular(path), dtype=np.uint8).tobytes(), width, height, path)


def lut_maps(data: bytes, width: int, height: int, path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """The LUT file's bytes ``data`` (named ``path``) as cv2.remap maps (x, y), float32 (H, W)."""
    n = len(data) // 8
    if n != 2 * width * height or len(data) % 8:
        raise InputError(
            f"distortion LUT holds {n} values but the {width}x{height} images need {2 * width * height}", path
        )
    lut = np.frombuffer(data, dtype="<f8")
    map_x = lut[: width * height].reshape(height, width).astype(np.float32)
    map_y = lut[width * height :].reshape(height, width).astype(np.float32)
    return map_x, map_y


def png_size(path: Path) -> tuple[int, int, int, int]:
    """(width, height, bit depth, colour type) from the PNG header, without decoding."""
    with open_regular(path) as f:
        return png_header(f.read(26), path)


def png_header(head: bytes, path: str | Path) -> tuple[int, int, int, int]:
    """(width, height, bit depth, colour type) from a PNG's first 26 bytes ``head``."""
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
        raise InputError(f"intrinsics differ from {posixpath.basename(left.path)}; not a rectified pair", right.path)
    if np.abs(left.G_camera_image[:3, :3] - right.G_camera_image[:3, :3]).max() > RECTIFIED_TOL:
        raise InputError(f"rotation differs from {posixpath.basename(left.path)}; not a rectified pair", right.path)
    baseline = float(np.linalg.norm(right.G_camera_image[:3, 3] - left.G_camera_image[:3, 3]))
    if not baseline > 0:
        raise InputError(f"zero baseline against {posixpath.basename(left.path)}", right.path)
    return StereoCalib(left.fx, left.fy, left.cx, left.cy, baseline, int(width), int(height))


@dataclass
class _Camera:
    folder: str  # the camera's stereo/ folder, and its chunks' camera name
    model: CameraModel
    maps: tuple[np.ndarray, np.ndarray] | None  # cv2.remap's (x, y) or fixed-point maps; None only with allow_missing_lut and no LUT


class OxfordSource(Source):
    """RobotCar stereo traversals under ``root`` (a folder or a pyarrow filesystem URI),
    extracted or as downloaded (tar chunks); ``pair`` is "wide" or "narrow".

    Undistortion is never skipped silently: a missing LUT is an InputError unless the
    caller passes ``allow_missing_lut=True`` (then frames are only demosaiced, which is
    right only for images that need no undistortion).

    ``lut_fixed_point`` (ours, default on): the LUT is turned once into OpenCV's fixed-point maps
    (``cv2.convertMaps``), which its bilinear remap otherwise rebuilds from the float maps for
    every image: the same pixels (tested), 6 instead of 8 bytes a pixel, remap ≈ 7 % cheaper at
    1280×960. False = the float maps (before issue 30).

    ``stride`` (ours): every N-th timestamp line is planned, the others never read (module docstring);
    ``rate_hz`` (ours) chooses that N for a target rate (the nearest whole stride to the recording's rate / it).
    """

    dataset = "oxford"
    layout = (f"each traversal a folder <root>/<traversal>/ holding {TIMESTAMPS_FILE} and stereo/{{left,centre,right}}/<µs>.png "
              "(raw Bayer GBRG), or its tar chunks as downloaded (<root>/<traversal>_stereo_<camera>_<NN>.tar), "
              "the camera models and LUTs in <root>/models/ (or --option models_dir=DIR): "
              "<camera>.txt and <camera>_distortion_lut.bin from the RobotCar SDK's models/ folder")

    def __init__(
        self,
        root: str | Path,
        pair: str = "wide",
        models_dir: str | Path | None = None,
        allow_missing_lut: bool = False,
        lut_fixed_point: bool = True,
        stride: Count = 1,
        rate_hz: float | None = None,
    ):
        if pair not in PAIRS:
            raise ConfigError(f"unknown RobotCar stereo pair {pair!r}; known: {sorted(PAIRS)}")
        if not (isinstance(stride, int) and stride >= 1):
            raise ConfigError(f"source.options.stride must be a whole number ≥ 1, got {stride!r}")
        if rate_hz is not None and not (isinstance(rate_hz, (int, float)) and math.isfinite(rate_hz) and rate_hz > 0):
            raise ConfigError(f"source.options.rate_hz must be a number > 0, got {rate_hz!r}")
        if rate_hz is not None and stride != 1:
            raise ConfigError("source.options: give stride or rate_hz, not both")
        self.where = Root(root)
        self.root = Path(root) if self.where.local else str(root)
        self.pair = pair
        self.models = Root(models_dir) if models_dir is not None else self.where.child("models")
        self.allow_missing_lut = allow_missing_lut
        self.lut_fixed_point = bool(lut_fixed_point)
        self.stride = stride
        self.rate_hz = rate_hz
        self._cameras: dict[str, tuple[_Camera, _Camera]] = {}
        self._tars: dict[str, TarTraversal | None] = {}  # traversal → its chunks (None: extracted)
        self._chunk_of: dict[str, dict[int, int]] = {}  # traversal → µs → chunk id (the tar layout's messages)

    def __getstate__(self) -> dict:
        # Shipped to workers without the LUT maps (~20 MB per 1280x960 pair) or listings; they reload.
        return {**self.__dict__, "_cameras": {}, "_tars": {}, "_chunk_of": {}}

    def shared_state(self) -> object | None:
        # The chunks' indexes: on an object store a chunk's index costs a request a member, which
        # every worker would otherwise pay again for the chunks it reads.
        return indexes_under(self.where) or None

    def adopt_state(self, state: object) -> None:
        adopt_indexes(state)  # type: ignore[arg-type]  # what shared_state gave

    @property
    def _folders(self) -> tuple[str, str]:
        (lfolder, _), (rfolder, _) = PAIRS[self.pair]
        return lfolder, rfolder

    def sequences(self) -> list[str]:
        names = self.where.names("")
        if names is None:
            raise InputError("RobotCar root folder not found", self.where.show())
        folders = {n for n in names if not n.endswith(".tar") and self.where.is_file(f"{n}/{TIMESTAMPS_FILE}")}
        return sorted(folders | chunk_traversals(names, self._folders))

    def _tar(self, sequence: str) -> TarTraversal | None:
        """The traversal's tar chunks of the pair's cameras; None when it has none (extracted)."""
        if sequence not in self._tars:
            t = TarTraversal.find(self.where, sequence, self._folders, self.where.names("") or set())
            self._tars[sequence] = t if t.has_chunks else None
        return self._tars[sequence]

    def _small(self, sequence: str, rel: str, what: str) -> tuple[bytes, str]:
        """A traversal's small file ``rel`` (a plain file first, else from its archives) and its name."""
        check_name(sequence, "sequence", "the oxford source", self.where.show())  # a traversal, never a path
        plain = f"{sequence}/{rel}"
        try:
            return self.where.read(plain), self.where.show(plain)
        except FileNotFoundError:
            pass
        tar = self._tar(sequence)
        if tar is not None and (hit := tar.small_file(rel)) is not None:
            return hit
        raise InputError(f"{what} not found" + (" (nor in the traversal's tar archives)" if tar else ""),
                         self.where.show(plain))

    # -- planning -------------------------------------------------------------------------

    def _read_timestamps(self, sequence: str) -> list[tuple[int, int]]:
        data, path = self._small(sequence, TIMESTAMPS_FILE, "timestamps file")
        text = decode_text(data, path, "timestamps file")
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
        self._chunk_of[sequence] = {t: c for t, c in rows}
        return rows

    def _load_cameras(self, sequence: str, width: int, height: int) -> tuple[_Camera, _Camera]:
        cams = []
        for folder, name in PAIRS[self.pair]:
            model = load_camera_model(self.models, name)
            try:
                lut = self.models.read(model.lut_name)
            except FileNotFoundError:
                lut = None
            if lut is not None:
                maps = lut_maps(lut, width, height, self.models.show(model.lut_name))
                if self.lut_fixed_point:
                    maps = cv2.convertMaps(maps[0], maps[1], cv2.CV_16SC2)
            elif self.allow_missing_lut:
                maps = None
            else:
                raise InputError(
                    "undistortion LUT not found (pass allow_missing_lut=True only for images that need no undistortion)",
                    self.models.show(model.lut_name),
                )
            cams.append(_Camera(folder, model, maps))
        return cams[0], cams[1]

    def _present(self, sequence: str, tar: TarTraversal | None) -> dict[str, dict[str, Located | None]]:
        """camera folder → image name (``<µs>.png``) → where it lies (None: an extracted file)."""
        out = {}
        for folder in self._folders:
            if tar is None:  # one directory listing per camera instead of a stat per frame
                out[folder] = dict.fromkeys(self.where.names(f"{sequence}/stereo/{folder}") or ())
            else:
                out[folder] = {posixpath.basename(n): loc for n, loc in tar.present(folder).items()}
        return out

    def _select(self, sequence: str, rows: list[tuple[int, int]], present: dict, downloaded: set[int],
                extracted: bool, stride: int) -> tuple[list[int], list[int], list[int], list[tuple[int, str]], int]:
        """(frames, t_ns, gaps, problems, skipped by the stride) of the timestamp ``rows``."""
        lfolder, rfolder = self._folders
        frames: list[int] = []
        t_ns: list[int] = []
        gaps: list[int] = []
        problems: list[tuple[int, str]] = []
        broken, prev_chunk, skipped = False, None, 0
        for line, (t_us, chunk) in enumerate(rows):
            broken |= prev_chunk is not None and chunk > prev_chunk + 1  # a chunk not even listed
            prev_chunk = chunk
            if chunk not in downloaded:
                broken = True  # chunk not downloaded: a gap
                continue
            if line % stride:
                skipped += 1
                continue
            name = f"{t_us}.png"
            has_l, has_r = name in present[lfolder], name in present[rfolder]
            if extracted and not (has_l and has_r):  # one image of a downloaded chunk: the frame keeps its place
                missing = self.where.show(f"{sequence}/stereo/{rfolder if has_l else lfolder}/{name}")
                problems.append((len(frames), str(InputError(f"stereo image missing within downloaded chunk {chunk}",
                                                             missing, line))))
            # (in chunks, a missing or truncated chunk fails its frames when read: their windows alone)
            if broken and frames:
                gaps.append(len(frames))
            broken = False
            frames.append(line)
            t_ns.append(t_us * 1000)
        return frames, t_ns, gaps, problems, skipped

    def _stride(self, rows: list[tuple[int, int]]) -> tuple[int, str]:
        """The stride, and for ``rate_hz`` how it was chosen ("rate 4 Hz of 16 Hz: "): the
        recording's rate is its median timestamp step."""
        if self.rate_hz is None or len(rows) < 2:
            return self.stride, ""
        native = 1e6 / float(np.median(np.diff([t for t, _ in rows])))
        return max(1, round(native / self.rate_hz)), f"rate {self.rate_hz:g} Hz of {native:.3g} Hz: "

    def survey(self, sequence: str) -> SequencePlan:
        rows = self._read_timestamps(sequence)
        tar = self._tar(sequence)
        lfolder, rfolder = self._folders
        present = self._present(sequence, tar)
        downloaded = {chunk for t_us, chunk in rows if f"{t_us}.png" in present[lfolder]
                      or f"{t_us}.png" in present[rfolder]}
        if tar is not None:  # a chunk file of either camera: downloaded, even when it turns out empty or cut
            downloaded |= {n for numbers in tar.chunks.values() for n in numbers}
        stride, rate = self._stride(rows)
        frames, t_ns, gaps, problems, skipped = self._select(sequence, rows, present, downloaded, tar is None, stride)

        def readable(k: int) -> bool:
            locs = [present[f].get(f"{t_ns[k] // 1000}.png", False) for f in (lfolder, rfolder)]
            return all(loc is None or (loc and not loc.index.truncated(loc.member)) for loc in locs)

        bad = {p for p, _ in problems}
        good = next((k for k in range(len(frames)) if k not in bad and readable(k)), None)
        where = self.where.show(f"{sequence}/stereo") if tar is None else self.where.show()
        if good is None:
            raise InputError(f"no {self.pair} stereo images for any of the {len(rows)} timestamps", where)
        name = f"{t_ns[good] // 1000}.png"
        loc = present[lfolder][name]
        if loc is None:
            rel = f"{sequence}/stereo/{lfolder}/{name}"
            first = self.where.show(rel)
            with self.where.open(rel) as f:
                head = f.read_at(0, 26)
        else:
            first = f"{self.where.show(loc.chunk)} (member {tar.member_name(lfolder, t_ns[good] // 1000)})"
            head = tar.read(loc)[:26]
        width, height, depth, ctype = png_header(head, first)
        if depth != 8 or ctype != 0:
            raise InputError(
                f"expected raw Bayer 8-bit single-channel PNG, got bit depth {depth}, colour type {ctype}",
                first,
                frames[good],
            )
        cams = self._load_cameras(sequence, width, height)
        self._cameras[sequence] = cams
        calib = stereo_calib(cams[0].model, cams[1].model, width, height)
        note = (f"{rate}stride {stride}: {stride - 1} of every {stride} frames skipped "
                f"({skipped} of {skipped + len(frames)})") if stride > 1 else ""
        return SequencePlan(self.dataset, sequence, calib, tuple(frames), tuple(t_ns), tuple(gaps), tuple(problems),
                            note)

    # -- reading --------------------------------------------------------------------------

    def read_frame(self, plan: SequencePlan, position: int) -> StereoFrame:
        cams = self._cameras.get(plan.sequence)
        if cams is None:
            cams = self._load_cameras(plan.sequence, plan.calib.width, plan.calib.height)
            self._cameras[plan.sequence] = cams
        index, t_ns = plan.frames[position], plan.t_ns[position]
        left, right = (self._load(plan.sequence, cam, t_ns, index, plan.calib) for cam in cams)
        return StereoFrame(self.dataset, plan.sequence, index, t_ns, left, right, plan.calib)

    def _bytes(self, sequence: str, cam: _Camera, t_us: int, index: int) -> tuple[np.ndarray, str]:
        """The PNG bytes of frame ``index``'s image of ``cam`` and how to name them."""
        tar = self._tar(sequence)
        if tar is None:
            rel = f"{sequence}/stereo/{cam.folder}/{t_us}.png"
            path = self.where.show(rel)
            try:
                return np.frombuffer(self.where.read(rel, index), np.uint8), path
            except FileNotFoundError:
                raise InputError("stereo image not found", path, index) from None
        if sequence not in self._chunk_of:  # a worker: the timestamps say which chunk holds the frame
            self._read_timestamps(sequence)
        found = tar.locate(cam.folder, t_us, self._chunk_of[sequence].get(t_us, 0), index)
        path = f"{self.where.show(found.chunk)} (member {tar.member_name(cam.folder, t_us)})"
        return np.frombuffer(tar.read(found), np.uint8), path

    def _load(self, sequence: str, cam: _Camera, t_ns: int, index: int, calib: StereoCalib) -> np.ndarray:
        data, path = self._bytes(sequence, cam, t_ns // 1000, index)
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
        data, path = self._small(sequence, "vo/vo.csv", "visual odometry file")
        text = decode_text(data, path, "visual odometry file")
        G = load_camera_model(self.models, PAIRS[self.pair][0][1]).G_camera_image
        G_inv = np.linalg.inv(G)
        steps = []
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
