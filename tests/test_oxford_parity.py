"""The RobotCar reader's image steps against the SDK's algorithm, on synthetic data: GBRG
bilinear demosaic as colour-demosaicing does it (the SDK's `demosaicing_CFA_Bayer_bilinear`,
pattern 'GBRG'), then the LUT undistortion sampled bilinearly with zero fill outside the image."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from colour_demosaicing import demosaicing_CFA_Bayer_bilinear

from mining.sources.oxford import demosaic_gbrg, load_lut

H, W = 48, 64  # ours: a small synthetic frame
BORDER = 2  # ours: the two demosaics extend the image differently at its edge (OpenCV replicates, colour mirrors)
TOL_DEMOSAIC = 1.0  # ours: 8-bit rounding of the reader's output vs the float reference
SUBPIXEL = 32  # REFERENCE: OpenCV's INTER_TAB_SIZE: remap snaps map fractions to 1/32 pixel
TOL_REMAP = 1.0  # ours: 8-bit rounding and OpenCV's fixed-point weights, at the same 1/32-snapped coordinates


def _frame() -> np.ndarray:
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    smooth = 120 + 60 * np.sin(x / 7) + 40 * np.cos(y / 5)  # a smooth scene: bilinear is well defined
    return np.clip(smooth + np.random.default_rng(0).normal(0, 3, (H, W)), 0, 255).round().astype(np.uint8)


def _bilinear_zero_fill(img: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """Textbook bilinear sampling; neighbours outside the image count as 0."""
    x0, y0 = np.floor(mx).astype(int), np.floor(my).astype(int)
    fx, fy = (mx - x0)[..., None], (my - y0)[..., None]

    def at(yy, xx):
        ok = (yy >= 0) & (yy < img.shape[0]) & (xx >= 0) & (xx < img.shape[1])
        v = img[np.clip(yy, 0, img.shape[0] - 1), np.clip(xx, 0, img.shape[1] - 1)].astype(np.float64)
        return v * ok[..., None]

    return ((1 - fx) * (1 - fy) * at(y0, x0) + fx * (1 - fy) * at(y0, x0 + 1)
            + (1 - fx) * fy * at(y0 + 1, x0) + fx * fy * at(y0 + 1, x0 + 1))


def test_demosaic_matches_colour_demosaicing_gbrg_bilinear() -> None:
    raw = _frame()
    ours = demosaic_gbrg(raw).astype(np.float64)
    ref = demosaicing_CFA_Bayer_bilinear(raw.astype(np.float64), "GBRG")
    inner = (slice(BORDER, -BORDER), slice(BORDER, -BORDER))
    assert np.abs(ours[inner] - ref[inner]).max() <= TOL_DEMOSAIC


def test_lut_undistortion_matches_bilinear_zero_fill(tmp_path: Path) -> None:
    rgb = demosaic_gbrg(_frame())
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    r2 = ((x - W / 2) ** 2 + (y - H / 2) ** 2) / (W / 2) ** 2
    mx, my = W / 2 + (x - W / 2) * (1 + 0.15 * r2) + 0.3, H / 2 + (y - H / 2) * (1 + 0.15 * r2) - 0.2  # barrel, off the grid, partly outside
    lut = tmp_path / "cam_distortion_lut.bin"
    np.concatenate([mx.ravel(), my.ravel()]).astype("<f8").tofile(lut)
    maps = load_lut(lut, W, H)
    ours = cv2.remap(rgb, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT).astype(np.float64)
    ref = _bilinear_zero_fill(rgb, np.round(mx * SUBPIXEL) / SUBPIXEL, np.round(my * SUBPIXEL) / SUBPIXEL)
    assert (mx < 0).any() or (mx > W - 1).any()  # the zero fill is exercised
    assert np.abs(ours - ref).max() <= TOL_REMAP
