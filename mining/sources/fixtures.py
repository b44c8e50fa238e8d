"""Writers that turn real RGB stereo frames into other datasets' on-disk formats.

Tests and benchmarks use them to build RobotCar-layout traversals and ROS 2 MCAP logs
from real KITTI frames, so the ``oxford`` and ``mcap`` adapters are exercised on real
image content without shipping those datasets.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from mining.sources.oxford import PAIRS
from mining.types import StereoCalib

# ours: RobotCar's Bumblebee XB3 runs at 16 Hz (SOURCES.md §4).
ROBOTCAR_HZ = 16.0

# Row/column offsets of the R, G (twice) and B sites in a 2×2 Bayer cell, per pattern.
BAYER_SITES: dict[str, dict[str, list[tuple[int, int]]]] = {
    "gbrg": {"G": [(0, 0), (1, 1)], "B": [(0, 1)], "R": [(1, 0)]},
    "rggb": {"R": [(0, 0)], "G": [(0, 1), (1, 0)], "B": [(1, 1)]},
    "bggr": {"B": [(0, 0)], "G": [(0, 1), (1, 0)], "R": [(1, 1)]},
    "grbg": {"G": [(0, 0), (1, 1)], "R": [(0, 1)], "B": [(1, 0)]},
}


def bayer_mosaic(rgb: np.ndarray, pattern: str = "gbrg") -> np.ndarray:
    """Sample an RGB image (H, W, 3) as a single-channel Bayer sensor would."""
    raw = np.empty(rgb.shape[:2], rgb.dtype)
    for channel, sites in BAYER_SITES[pattern].items():
        c = "RGB".index(channel)
        for dy, dx in sites:
            raw[dy::2, dx::2] = rgb[dy::2, dx::2, c]
    return raw


def radial_distortion_maps(calib: StereoCalib, k1: float) -> tuple[np.ndarray, np.ndarray]:
    """For every undistorted pixel, the distorted pixel it comes from (one-coefficient
    radial model about the principal point): float64 maps (H, W), RobotCar LUT semantics."""
    K = calib.K
    maps = cv2.initUndistortRectifyMap(
        K, np.array([k1, 0.0, 0.0, 0.0]), None, K, (calib.width, calib.height), cv2.CV_32FC1
    )
    return maps[0].astype(np.float64), maps[1].astype(np.float64)


def distort_image(rgb: np.ndarray, calib: StereoCalib, k1: float) -> np.ndarray:
    """What a camera with radial distortion ``k1`` would have recorded: for each
    distorted pixel, sample the undistorted image where that pixel undistorts to."""
    h, w = rgb.shape[:2]
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([u.ravel(), v.ravel()], axis=-1).reshape(-1, 1, 2)
    K = calib.K
    und = cv2.undistortPointsIter(
        pts, K, np.array([k1, 0.0, 0.0, 0.0]), None, K, (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-6)
    ).reshape(h, w, 2)
    return cv2.remap(
        rgb, und[..., 0].astype(np.float32), und[..., 1].astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
    )


def write_camera_model(path: Path, calib: StereoCalib, translation_y: float) -> None:
    """A RobotCar model file: ``fx fy cx cy`` and the G_camera_image of the SDK's stereo
    models (image axes → camera base axes), offset ``translation_y`` to the right."""
    G = np.array([[0.0, 0.0, 1.0, 0.0], [1.0, 0.0, 0.0, translation_y], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    lines = [f"{calib.fx:.6f} {calib.fy:.6f} {calib.cx:.6f} {calib.cy:.6f}"]
    lines += [" ".join(f"{v:.6f}" for v in row) for row in G]
    path.write_text("\n".join(lines) + "\n")


def write_robotcar_fixture(
    out_dir: str | Path,
    left_frames: Sequence[np.ndarray],
    right_frames: Sequence[np.ndarray],
    calib: StereoCalib,
    traversal: str = "2015-01-01-00-00-00",
    pair: str = "wide",
    k1: float = -0.08,
    t0_us: int = 1_420_070_400_000_000,
    frames_per_chunk: int = 2,
    missing_chunks: Sequence[int] = (),
    list_missing: bool = True,
    write_lut: bool = True,
) -> Path:
    """Write a RobotCar traversal (and ``models/``) under ``out_dir`` from RGB frames.

    Each RGB frame is distorted with radial coefficient ``k1`` and mosaicked to GBRG; the
    LUT written beside the models maps back, so demosaic + remap recovers the frames.
    Chunk ids start at 1, ``frames_per_chunk`` frames each; chunks in ``missing_chunks``
    get no images (as if not downloaded) and, unless ``list_missing``, no timestamps
    either. Returns the traversal folder.
    """
    out_dir = Path(out_dir)
    (left_dir, left_model), (right_dir, right_model) = PAIRS[pair]
    models = out_dir / "models"
    models.mkdir(parents=True, exist_ok=True)
    write_camera_model(models / f"{left_model}.txt", calib, 0.0)
    write_camera_model(models / f"{right_model}.txt", calib, calib.baseline_m)
    if write_lut:
        map_x, map_y = radial_distortion_maps(calib, k1)
        lut = np.concatenate([map_x.ravel(), map_y.ravel()]).astype("<f8")
        for name in (left_model, right_model):
            lut.tofile(models / f"{name}_distortion_lut.bin")

    trav = out_dir / traversal
    for d in (left_dir, right_dir):
        (trav / "stereo" / d).mkdir(parents=True, exist_ok=True)
    lines = []
    for i, (lf, rf) in enumerate(zip(left_frames, right_frames, strict=True)):
        t_us = t0_us + round(i * 1e6 / ROBOTCAR_HZ)
        chunk = 1 + i // frames_per_chunk
        if chunk in missing_chunks:
            if list_missing:
                lines.append(f"{t_us} {chunk}")
            continue
        lines.append(f"{t_us} {chunk}")
        for d, rgb in ((left_dir, lf), (right_dir, rf)):
            raw = bayer_mosaic(distort_image(rgb, calib, k1) if write_lut else rgb, "gbrg")
            cv2.imwrite(str(trav / "stereo" / d / f"{t_us}.png"), raw)
    (trav / "stereo.timestamps").write_text("\n".join(lines) + "\n")
    return trav
