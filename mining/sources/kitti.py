"""KITTI tracking layout: ``<split>/{image_02,image_03}/<seq>/NNNNNN.png`` + ``calib/<seq>.txt``.

The tracking benchmark ships no timestamps: frames are 10 Hz, so frame ``i`` is at
``i × 100 ms``. The plan reads the calibration and the image file listing (plus one PNG
header for the image size), never image data.
"""

from __future__ import annotations

import re
import struct
from pathlib import Path

import cv2
import numpy as np

from mining.errors import InputError
from mining.files import check_regular, open_regular
from mining.formats.kitti_calib import KittiCalib, read_tracking_calib
from mining.names import check_name
from mining.sources.base import Source
from mining.types import SequencePlan, StereoCalib, StereoFrame

KITTI_FRAME_PERIOD_NS = 100_000_000  # ours: KITTI records at 10 Hz (Geiger et al. 2013); tracking has no timestamp file
_SPLITS = ("training", "testing")
SPLIT_MARK = "_"  # ours: "training_0005" names a sequence when the root holds both splits
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_size(path: Path, frame: int | None = None) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR chunk, reading 24 bytes only."""
    try:
        with open_regular(path, frame) as f:
            head = f.read(24)
    except OSError as e:
        raise InputError(f"cannot open image: {e.strerror}", path, frame) from None
    if len(head) < 24 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise InputError("not a PNG file (bad signature or IHDR header)", path, frame)
    return struct.unpack(">II", head[16:24])


def read_rgb(path: Path, frame: int) -> np.ndarray:
    """Decode a colour image to (H, W, 3) uint8 RGB; InputError when missing or undecodable."""
    if not check_regular(path, frame).is_file():  # a FIFO would hang OpenCV's read
        raise InputError("image file is missing", path, frame)
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:  # OpenCV returns None for unreadable or truncated files
        raise InputError("cannot decode image (unreadable or truncated)", path, frame)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def read_stereo_pair(left_path: Path, right_path: Path, frame: int, calib: StereoCalib) -> tuple[np.ndarray, np.ndarray]:
    """Decode both images and check their sizes against each other and the calibration."""
    left, right = read_rgb(left_path, frame), read_rgb(right_path, frame)
    (hl, wl), (hr, wr) = left.shape[:2], right.shape[:2]
    if (wl, hl) != (wr, hr):
        raise InputError(f"left image is {wl}×{hl} but right image {right_path} is {wr}×{hr}", left_path, frame)
    if (wl, hl) != (calib.width, calib.height):
        raise InputError(
            f"image is {wl}×{hl} but the calibration is for {calib.width}×{calib.height}", left_path, frame
        )
    return left, right


def listed_frames(left_dir: Path, right_dir: Path, digits: int) -> tuple[tuple[int, ...], dict[int, str]]:
    """Frame indices from the first to the last image (``<digits-wide index>.png``) in
    either folder, and the unreadable ones among them: index → message naming the missing
    file and the frame (present on one side only, or a hole in the numbering). From the
    directory listing alone."""
    for d in (left_dir, right_dir):
        if not d.is_dir():
            raise InputError("image folder is missing", d)

    pattern = re.compile(rf"(\d{{{digits}}})\.png")

    def listing(d: Path) -> dict[int, str]:
        return {int(m.group(1)): n for n in _names(d) if (m := pattern.fullmatch(n))}

    left, right = listing(left_dir), listing(right_dir)
    for d, names in ((left_dir, left), (right_dir, right)):
        if not names:
            raise InputError("no images found", d)
    frames = tuple(range(min(left.keys() | right.keys()), max(left.keys() | right.keys()) + 1))
    problems = {}
    for idx in frames:
        name = f"{idx:0{digits}d}.png"
        if idx in left and idx not in right:
            problems[idx] = str(InputError("right image is missing for this frame", right_dir / name, idx))
        elif idx in right and idx not in left:
            problems[idx] = str(InputError("left image is missing for this frame", left_dir / name, idx))
        elif idx not in left:
            prev = max(i for i in left if i < idx)
            nxt = min(i for i in left if i > idx)
            problems[idx] = str(InputError(f"image is missing: frame numbering jumps from {prev} to {nxt}",
                                           left_dir / name, idx))
    return frames, problems


def paired_frames(left_dir: Path, right_dir: Path, digits: int) -> tuple[int, ...]:
    """Frame indices whose image (``<digits-wide index>.png``) exists in both folders.

    Indices must be consecutive from the first. A frame present on one side only, or a
    hole in the numbering, raises InputError naming the missing file, from the directory
    listing alone.
    """
    frames, problems = listed_frames(left_dir, right_dir, digits)
    if problems:
        raise InputError(problems[min(problems)])
    return frames


def _names(d: Path) -> list[str]:
    try:
        return sorted(p.name for p in d.iterdir())
    except OSError as e:
        raise InputError(f"cannot list folder: {e.strerror}", d) from None


class KittiTrackingSource(Source):
    """KITTI tracking stereo sequences (image_02 left, image_03 right by default).

    The StereoCalib is that of the left camera's own frame (image_02: rectified camera 0
    shifted by ``KittiCalib.t_cam2``); KITTI labels and detections are in rectified
    camera 0, see ``kitti_calib(seq).rect0_to_cam2``.

    ``root`` holds ``training/`` and/or ``testing/``, or is itself a split folder. With
    one split, sequences are named ``"0005"``; with both, ``"training_0005"`` (a bare
    name is accepted when only one split has it). Names are one path component
    (``mining/names.py``), so the split joins with ``_``, never ``/``.
    """

    dataset = "kitti"
    _FRAME = re.compile(r"(\d{6})\.png")

    def __init__(self, root: str | Path, camera_pair: tuple[str, str] = ("image_02", "image_03")):
        if root is None:
            raise InputError("the kitti source needs a root folder")
        self.root = Path(root)
        if not self.root.is_dir():
            raise InputError("KITTI tracking root folder does not exist", self.root)
        self.camera_pair = tuple(camera_pair)
        # image_0N is imaged through P_N; the calibration follows the chosen pair.
        cams = [re.fullmatch(r"image_0([0-3])", c) for c in self.camera_pair]
        if len(cams) != 2 or not all(cams):
            raise InputError(f"camera_pair must name two of image_00..image_03, got {camera_pair!r}", self.root)
        self._cams = (int(cams[0].group(1)), int(cams[1].group(1)))
        if (self.root / "calib").is_dir() or (self.root / self.camera_pair[0]).is_dir():
            self._splits = {"": self.root}
        else:
            self._splits = {s: self.root / s for s in _SPLITS if (self.root / s).is_dir()}
        if not self._splits:
            raise InputError("no KITTI tracking split (training/, testing/ or calib/) under the root", self.root)

    # -- naming ---------------------------------------------------------------------

    def _split_dir(self, sequence: str) -> tuple[Path, str]:
        """Split folder and bare sequence id of a sequence name."""
        check_name(sequence, "sequence", "the kitti source", self.root)
        split, _, seq = sequence.partition(SPLIT_MARK)
        if seq and split in self._splits and len(self._splits) > 1:
            return self._splits[split], seq
        having = [d for d in self._splits.values() if (d / "calib" / f"{sequence}.txt").is_file()]
        if len(having) > 1:
            raise InputError(f"sequence {sequence!r} exists in several splits; name it as "
                             f"'training{SPLIT_MARK}{sequence}'", self.root)
        if not having:  # let the caller's next step name the missing calibration file
            return next(iter(self._splits.values())), sequence
        return having[0], sequence

    def sequences(self) -> list[str]:
        """Sequences that have a calibration file (images may be absent: calib-only use)."""
        out = []
        for split, d in self._splits.items():
            calib_dir = d / "calib"
            if not calib_dir.is_dir():
                continue
            names = sorted(p.stem for p in calib_dir.glob("*.txt"))
            out += [f"{split}{SPLIT_MARK}{n}" if len(self._splits) > 1 else n for n in names]
        return out

    def _image_dirs(self, sequence: str) -> tuple[Path, Path]:
        d, seq = self._split_dir(sequence)
        return d / self.camera_pair[0] / seq, d / self.camera_pair[1] / seq

    # -- calibration ----------------------------------------------------------------

    def kitti_calib(self, sequence: str) -> KittiCalib:
        """The raw KITTI matrices (P0..P3, R_rect, Tr_velo_cam, Tr_imu_velo) of a sequence."""
        d, seq = self._split_dir(sequence)
        return read_tracking_calib(d / "calib" / f"{seq}.txt")

    def calib(self, sequence: str) -> StereoCalib:
        """StereoCalib of image_02/image_03, usable without images.

        The image size comes from the first left image's PNG header when images exist,
        else from the recording day (KITTI_DAY_SIZES, keyed by fx).
        """
        kc = self.kitti_calib(sequence)
        left_dir, _ = self._image_dirs(sequence)
        first = self._first_image(left_dir)
        if first is not None:
            return self._checked_stereo(kc, first)
        size = kc.day_size()
        if size is None:
            raise InputError(
                f"no images in {left_dir} to take the image size from and fx = {kc.fx} matches no known KITTI day",
                kc.path,
            )
        return kc.stereo(*size, *self._cams)

    def _first_image(self, left_dir: Path) -> Path | None:
        if not left_dir.is_dir():
            return None
        names = [n for n in _names(left_dir) if self._FRAME.fullmatch(n)]
        return left_dir / names[0] if names else None

    def _checked_stereo(self, kc: KittiCalib, image: Path) -> StereoCalib:
        frame = int(image.stem)
        w, h = png_size(image, frame)
        day = kc.day_size()
        if day is not None and day != (w, h):
            raise InputError(
                f"image is {w}×{h} but calibration {kc.path} (fx {kc.fx}) belongs to a KITTI day "
                f"recorded at {day[0]}×{day[1]}",
                image,
                frame,
            )
        return kc.stereo(w, h, *self._cams)

    # -- Source interface -----------------------------------------------------------

    def survey(self, sequence: str) -> SequencePlan:
        kc = self.kitti_calib(sequence)
        left_dir, right_dir = self._image_dirs(sequence)
        frames, problems = listed_frames(left_dir, right_dir, 6)
        first = next((i for i in frames if i not in problems), None)
        if first is None:
            raise InputError("no frame has both its left and right image", left_dir)
        calib = self._checked_stereo(kc, left_dir / f"{first:06d}.png")
        t_ns = tuple(i * KITTI_FRAME_PERIOD_NS for i in frames)
        pos = {idx: k for k, idx in enumerate(frames)}
        return SequencePlan(self.dataset, sequence, calib, frames, t_ns,
                            problems=tuple((pos[i], msg) for i, msg in sorted(problems.items())))

    def read_frame(self, plan: SequencePlan, position: int) -> StereoFrame:
        idx = plan.frames[position]
        left_dir, right_dir = self._image_dirs(plan.sequence)
        name = f"{idx:06d}.png"
        left, right = read_stereo_pair(left_dir / name, right_dir / name, idx, plan.calib)
        return StereoFrame(self.dataset, plan.sequence, idx, plan.t_ns[position], left, right, plan.calib)
