"""Minimal real-data readers for the geometry tests (cv2 images, KITTI text files).

Kept beside the tests on purpose: the geometry tests should not depend on the source
adapters they do not test.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from mining.types import StereoCalib, StereoFrame


def rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, f"cannot read {path}"
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def key_values(path: Path) -> dict[str, np.ndarray]:
    out = {}
    for line in Path(path).read_text().splitlines():
        if not line.split():
            continue
        key = line.split()[0].rstrip(":")  # both "P2:" and "R_rect" dialects
        values = line.split()[1:]
        try:
            out[key] = np.array([float(v) for v in values])
        except ValueError:
            pass
    return out


def calib_from_projections(P2: np.ndarray, P3: np.ndarray, width: int, height: int) -> StereoCalib:
    fx = P2[0, 0]
    return StereoCalib(fx, P2[1, 1], P2[0, 2], P2[1, 2], (P2[0, 3] - P3[0, 3]) / fx, width, height)


def tracking_calib(root: Path) -> StereoCalib:
    c = key_values(root / "training/calib/0005.txt")
    return calib_from_projections(c["P2"].reshape(3, 4), c["P3"].reshape(3, 4), 1242, 375)


def tracking_frame(root: Path, calib: StereoCalib, i: int) -> StereoFrame:
    left = rgb(root / f"training/image_02/0005/{i:06d}.png")
    right = rgb(root / f"training/image_03/0005/{i:06d}.png")
    return StereoFrame("kitti", "0005", i, i * 100_000_000, left, right, calib)


def tracking_poses(root: Path) -> np.ndarray:
    rows = np.loadtxt(root / "training/egoposes_orbslam3/0005.txt").reshape(-1, 3, 4)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3] = rows
    return poses


RAW_DRIVE = "2011_09_26/2011_09_26_drive_0001_sync"


def raw_calib(root: Path) -> tuple[StereoCalib, np.ndarray, np.ndarray]:
    c = key_values(root / "2011_09_26/calib_cam_to_cam.txt")
    P2, P3 = c["P_rect_02"].reshape(3, 4), c["P_rect_03"].reshape(3, 4)
    return calib_from_projections(P2, P3, 1242, 375), P2, c["R_rect_00"].reshape(3, 3)


def raw_frame(root: Path, calib: StereoCalib, i: int) -> StereoFrame:
    left = rgb(root / f"{RAW_DRIVE}/image_02/data/{i:010d}.png")
    right = rgb(root / f"{RAW_DRIVE}/image_03/data/{i:010d}.png")
    return StereoFrame("kitti_raw", "0001", i, i * 100_000_000, left, right, calib)


def raw_lidar(root: Path, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, depth) of the Velodyne points that project into image_02."""
    _, P2, R0 = raw_calib(root)
    v = key_values(root / "2011_09_26/calib_velo_to_cam.txt")
    velo_to_cam = np.eye(4)
    velo_to_cam[:3, :3], velo_to_cam[:3, 3] = v["R"].reshape(3, 3), v["T"]
    rect = np.eye(4)
    rect[:3, :3] = R0
    pts = np.fromfile(root / f"{RAW_DRIVE}/velodyne_points/data/{i:010d}.bin", np.float32).reshape(-1, 4)
    p = P2 @ rect @ velo_to_cam @ np.c_[pts[:, :3], np.ones(len(pts))].T
    w = p[2]
    front = w > 0.5
    u, vv, w = p[0, front] / w[front], p[1, front] / w[front], w[front]
    inside = (u >= 0) & (u <= 1241) & (vv >= 0) & (vv <= 374)
    return u[inside], vv[inside], w[inside]


def oxts_positions(root: Path, n: int) -> np.ndarray:
    """(n, 3) metric IMU positions from OXTS lat/lon/alt (Mercator, as the KITTI devkit)."""
    earth = 6378137.0
    rows = [np.loadtxt(root / f"{RAW_DRIVE}/oxts/data/{i:010d}.txt") for i in range(n)]
    scale = np.cos(np.radians(rows[0][0]))
    return np.array(
        [[scale * np.radians(r[1]) * earth, scale * earth * np.log(np.tan(np.radians(90 + r[0]) / 2)), r[2]] for r in rows]
    )
