"""KITTI calibration files: both tracking key dialects and the raw-data calib_*.txt files.

KITTI's projection matrices ``P0..P3`` map points given in *rectified camera-0*
coordinates into each camera's image: ``P_i = K [I | t_i]``. All cameras share ``K``
after rectification and differ only by the translation ``t_i``. The left colour camera
(image_02) sits ~6 cm right of camera 0, so its own frame is rectified camera 0 shifted
by ``t_2 = K⁻¹ P2[:, 3]``. Our ``StereoCalib`` describes the image_02/image_03 pair in
the image_02 frame; ``KittiCalib`` keeps the matrices needed to move KITTI labels,
detections and LiDAR points (all in or relative to rectified camera 0) into it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mining.errors import InputError
from mining.files import check_regular, read_text
from mining.types import StereoCalib

# Object-detection dialect key → official tracking key (SOURCES.md §1.3).
_TRACKING_ALIASES = {"R0_rect": "R_rect", "Tr_velo_to_cam": "Tr_velo_cam", "Tr_imu_to_velo": "Tr_imu_velo"}
# Keys whose values are text, not numbers (raw-data files start with a date).
_TEXT_KEYS = {"calib_time"}

# ours: image size (w, h) of each KITTI recording day, keyed by P2 fx (SOURCES.md §1.1).
# Used only when a sequence has no images to read the size from, and to catch a
# calibration file paired with images of another day.
KITTI_DAY_SIZES: dict[float, tuple[int, int]] = {
    721.5377: (1242, 375),  # 2011_09_26 (tracking 0000–0013, raw 2011_09_26_*)
    707.0493: (1224, 370),  # 2011_09_28/29 (tracking 0014–0017)
    718.3351: (1238, 374),  # 2011_09_30 (tracking 0018–0019)
    718.856: (1241, 376),  # 2011_10_03 (tracking 0020)
}
_FX_TOL = 1e-3  # ours: fx values in the files carry 4–7 decimals


def read_calib_file(path: str | Path) -> dict[str, np.ndarray]:
    """``key[:] v1 v2 …`` lines → {key: float64 array}; a trailing ':' is stripped.

    Blank lines are skipped; a value that is not a number raises InputError naming the
    file and the line (except known text keys such as ``calib_time``).
    """
    path = Path(path)
    if not check_regular(path).is_file():  # a FIFO or device is named as what it is, not as missing
        raise InputError("calibration file is missing", path)
    out: dict[str, np.ndarray] = {}
    for lineno, line in enumerate(read_text(path, "calibration file").splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        key, values = parts[0], parts[1:]
        if key.endswith(":"):
            key = key[:-1]
        elif ":" in key:  # "key:1.0 2.0" with no space after the colon
            key, first = key.split(":", 1)
            values = [first, *values]
        if key in _TEXT_KEYS:
            continue
        try:
            out[key] = np.array([float(v) for v in values], dtype=np.float64)
        except ValueError:
            raise InputError(f"line {lineno}: key {key!r} has a value that is not a number", path) from None
    return out


def _take(values: dict[str, np.ndarray], key: str, shape: tuple[int, ...], path: Path) -> np.ndarray:
    if key not in values:
        raise InputError(f"calibration key {key!r} is missing", path)
    v = values[key]
    if v.size != int(np.prod(shape)):
        raise InputError(f"calibration key {key!r} has {v.size} values, expected {int(np.prod(shape))}", path)
    return v.reshape(shape)


def _homogeneous(m: np.ndarray) -> np.ndarray:
    """3×3 or 3×4 → 4×4 with a [0 0 0 1] last row."""
    out = np.eye(4)
    out[: m.shape[0], : m.shape[1]] = m
    return out


@dataclass(frozen=True, eq=False)  # arrays: compare fields with numpy, not ==
class KittiCalib:
    """The KITTI calibration of one sequence (tracking) or one recording day (raw).

    ``P2``/``P3`` are 3×4 projections from rectified camera-0 coordinates into
    image_02/image_03; ``R_rect`` (3×3) rotates unrectified camera 0 into rectified
    camera 0; ``Tr_velo_cam`` (3×4) maps Velodyne → unrectified camera 0;
    ``Tr_imu_velo`` (3×4) maps IMU → Velodyne.
    """

    P0: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    P3: np.ndarray
    R_rect: np.ndarray
    Tr_velo_cam: np.ndarray
    Tr_imu_velo: np.ndarray
    path: str  # the file (or the raw cam-to-cam file) the numbers come from
    image_size: tuple[int, int] | None = None  # (w, h) when the file states it (raw S_rect_02)

    @property
    def fx(self) -> float:
        return float(self.P2[0, 0])

    @property
    def baseline_m(self) -> float:
        """image_02 ↔ image_03 baseline, (P2[0,3] − P3[0,3]) / fx."""
        return float((self.P2[0, 3] - self.P3[0, 3]) / self.P2[0, 0])

    def P(self, camera: int) -> np.ndarray:
        """3×4 projection of camera 0–3 (image_0N)."""
        if camera not in (0, 1, 2, 3):
            raise ValueError(f"KITTI has cameras 0–3, not {camera}")
        return getattr(self, f"P{camera}")

    def t_cam(self, camera: int) -> np.ndarray:
        """(3,) offset of a camera's own frame: X_cam = X_rect0 + t_cam, since P = K [I | t]."""
        P = self.P(camera)
        return np.linalg.solve(P[:, :3], P[:, 3])

    @property
    def t_cam2(self) -> np.ndarray:
        """(3,) offset of image_02's frame: X_cam2 = X_rect0 + t_cam2."""
        return self.t_cam(2)

    @property
    def T_cam2_rect0(self) -> np.ndarray:
        """4×4: rectified camera-0 coordinates → image_02 camera coordinates."""
        T = np.eye(4)
        T[:3, 3] = self.t_cam2
        return T

    @property
    def T_rect0_velo(self) -> np.ndarray:
        """4×4: Velodyne → rectified camera 0, R_rect · Tr_velo_cam."""
        return _homogeneous(self.R_rect) @ _homogeneous(self.Tr_velo_cam)

    @property
    def T_cam2_imu(self) -> np.ndarray:
        """4×4: IMU → image_02 camera (IMU → Velodyne → camera 0 → rectified → image_02)."""
        return self.T_cam2_rect0 @ self.T_rect0_velo @ _homogeneous(self.Tr_imu_velo)

    def rect0_to_cam2(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) points in rectified camera 0 (KITTI labels/detections) → image_02 frame."""
        return np.asarray(points, np.float64) + self.t_cam2

    def cam2_to_rect0(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) points in the image_02 frame → rectified camera 0 (the frame of KITTI's 3D fields)."""
        return np.asarray(points, np.float64) - self.t_cam2

    def camera2_poses(self, poses_rect0: np.ndarray) -> np.ndarray:
        """(N, 4, 4) poses of the left colour camera from poses of rectified camera 0 (same rig).

        pose2_k = T · pose0_k · T⁻¹ with T = T_cam2_rect0: world = camera 2 at the first frame.
        """
        T = self.T_cam2_rect0
        return np.einsum("ij,njk,kl->nil", T, poses_rect0, np.linalg.inv(T))

    def day_size(self) -> tuple[int, int] | None:
        """(w, h) of this calibration's recording day from KITTI_DAY_SIZES, or None."""
        for fx, size in KITTI_DAY_SIZES.items():
            if abs(self.fx - fx) < _FX_TOL:
                return size
        return None

    def stereo(self, width: int, height: int, left: int = 2, right: int = 3) -> StereoCalib:
        """StereoCalib of a camera pair (default image_02 / image_03), in the left camera's frame."""
        Pl, Pr = self.P(left), self.P(right)
        for name, v in ((f"P{left} fx", Pl[0, 0]), (f"P{left} fy", Pl[1, 1]), (f"P{right} fx", Pr[0, 0])):
            if not (np.isfinite(v) and v > 0):  # before the baseline: it divides by fx
                raise InputError(f"calibration {name} = {float(v)!r} is not a positive finite focal length", self.path)
        if not np.all(np.isfinite(Pl[:, 3])) or not np.all(np.isfinite(Pr[:, 3])):
            raise InputError(f"calibration P{left} or P{right} has a non-finite translation", self.path)
        b = float((Pl[0, 3] - Pr[0, 3]) / Pl[0, 0])
        if not b > 0:
            raise InputError(f"baseline P{left}→P{right} = {b:.4f} m is not positive (left and right swapped?)", self.path)
        cx, cy = float(Pl[0, 2]), float(Pl[1, 2])
        if not (0 < cx < width and 0 < cy < height):
            raise InputError(f"principal point ({cx:.1f}, {cy:.1f}) lies outside the {width}×{height} image", self.path)
        return StereoCalib(
            fx=float(Pl[0, 0]), fy=float(Pl[1, 1]), cx=cx, cy=cy, baseline_m=b, width=int(width), height=int(height)
        )


def read_tracking_calib(path: str | Path) -> KittiCalib:
    """A KITTI tracking ``calib/<seq>.txt`` in either key dialect (SOURCES.md §1.3)."""
    path = Path(path)
    raw = read_calib_file(path)
    v = {_TRACKING_ALIASES.get(k, k): a for k, a in raw.items()}
    return KittiCalib(
        P0=_take(v, "P0", (3, 4), path),
        P1=_take(v, "P1", (3, 4), path),
        P2=_take(v, "P2", (3, 4), path),
        P3=_take(v, "P3", (3, 4), path),
        R_rect=_take(v, "R_rect", (3, 3), path),
        Tr_velo_cam=_take(v, "Tr_velo_cam", (3, 4), path),
        Tr_imu_velo=_take(v, "Tr_imu_velo", (3, 4), path),
        path=str(path),
    )


def read_raw_calib(date_dir: str | Path) -> KittiCalib:
    """The three calib_*.txt files of a KITTI raw recording day (SOURCES.md §2)."""
    date_dir = Path(date_dir)
    cam_path = date_dir / "calib_cam_to_cam.txt"
    velo_path = date_dir / "calib_velo_to_cam.txt"
    imu_path = date_dir / "calib_imu_to_velo.txt"
    cam, velo, imu = read_calib_file(cam_path), read_calib_file(velo_path), read_calib_file(imu_path)
    w, h = _take(cam, "S_rect_02", (2,), cam_path)
    if w != int(w) or h != int(h) or w <= 0 or h <= 0:
        raise InputError(f"S_rect_02 = {w} {h} is not a positive integer image size", cam_path)
    return KittiCalib(
        P0=_take(cam, "P_rect_00", (3, 4), cam_path),
        P1=_take(cam, "P_rect_01", (3, 4), cam_path),
        P2=_take(cam, "P_rect_02", (3, 4), cam_path),
        P3=_take(cam, "P_rect_03", (3, 4), cam_path),
        R_rect=_take(cam, "R_rect_00", (3, 3), cam_path),
        Tr_velo_cam=np.hstack([_take(velo, "R", (3, 3), velo_path), _take(velo, "T", (3, 1), velo_path)]),
        Tr_imu_velo=np.hstack([_take(imu, "R", (3, 3), imu_path), _take(imu, "T", (3, 1), imu_path)]),
        path=str(cam_path),
        image_size=(int(w), int(h)),
    )
