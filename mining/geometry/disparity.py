"""Dense disparity with OpenCV's semi-global block matching (SGBM).

The original used ELAS; SGBM is a well-kept library alternative of similar accuracy on
KITTI. Invalid pixels are NaN, never zero, so no one mistakes them for "infinitely far".
"""

from __future__ import annotations

import cv2
import numpy as np

from dataclasses import replace

from mining.geometry.config import StereoConfig

_MODES = {
    "sgbm": cv2.STEREO_SGBM_MODE_SGBM,
    "sgbm_3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    "hh": cv2.STEREO_SGBM_MODE_HH,
    "hh4": cv2.STEREO_SGBM_MODE_HH4,
}


class StereoMatcher:
    """One SGBM matcher per configuration; create once and reuse for every frame."""

    def __init__(self, cfg: StereoConfig, bf: float | None = None):
        """``bf`` (px·m) is needed only with ``min_depth_m``, which sets the search range from it."""
        if cfg.min_depth_m > 0:
            if bf is None or not bf > 0:
                raise ValueError("geometry.stereo.min_depth_m needs the pair's bf (focal length × baseline)")
            cfg = replace(cfg, num_disparities=search_range(cfg, bf), min_depth_m=0.0)
        if cfg.mode not in _MODES:
            raise ValueError(f"unknown SGBM mode {cfg.mode!r}; expected one of {sorted(_MODES)}")
        if cfg.num_disparities <= 0 or cfg.num_disparities % 16:
            raise ValueError(f"num_disparities must be a positive multiple of 16, got {cfg.num_disparities}")
        if cfg.block_size < 1 or cfg.block_size % 2 == 0:
            raise ValueError(f"block_size must be odd and positive, got {cfg.block_size}")
        if cfg.downscale not in (1, 2):
            raise ValueError(f"downscale must be 1 or 2, got {cfg.downscale}")
        if (cfg.num_disparities // cfg.downscale) % 16:
            raise ValueError(f"num_disparities / downscale must be a multiple of 16, got {cfg.num_disparities}")
        if cfg.far_full_disparities % 16:
            raise ValueError(f"far_full_disparities must be a multiple of 16, got {cfg.far_full_disparities}")
        self.cfg = cfg
        # the far pass: the same matcher at full resolution over the small disparities only
        self._far = (StereoMatcher(replace(cfg, downscale=1, num_disparities=cfg.far_full_disparities,
                                           far_full_disparities=0, max_match_rows=0))
                     if cfg.far_full_disparities and cfg.downscale > 1 else None)
        self._ndisp = cfg.num_disparities // cfg.downscale  # search range at the matching scale
        channels = 1 if cfg.grayscale else 3
        area = channels * cfg.block_size**2
        self._sgbm = cv2.StereoSGBM_create(
            minDisparity=0,
            numDisparities=self._ndisp,
            blockSize=cfg.block_size,
            P1=cfg.p1_factor * area,
            P2=cfg.p2_factor * area,
            disp12MaxDiff=cfg.disp12_max_diff,
            preFilterCap=cfg.pre_filter_cap,
            uniquenessRatio=cfg.uniqueness_ratio,
            speckleWindowSize=cfg.speckle_window,
            speckleRange=cfg.speckle_range,
            mode=_MODES[cfg.mode],
        )

    def vertical_factor(self, height: int) -> int:
        """The extra vertical reduction of a ``height``-row image (``max_match_rows``); 1 = none."""
        rows = int(round(height / self.cfg.downscale))  # as cv2.resize rounds the half-resolution size
        if not self.cfg.max_match_rows or rows <= self.cfg.max_match_rows:
            return 1
        return -(-rows // self.cfg.max_match_rows)

    def _prepare(self, img: np.ndarray, vertical: int) -> np.ndarray:
        if img.ndim == 3 and self.cfg.grayscale:
            img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        if vertical > 1:
            h, w = img.shape[:2]
            size = (int(round(w / self.cfg.downscale)), max(1, int(round(h / self.cfg.downscale / vertical))))
            img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        elif self.cfg.downscale > 1:
            img = cv2.resize(img, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
        # SGBM cannot match the leftmost num_disparities columns (their partners lie
        # outside the right image); padding on the left lets it match them with the
        # disparities that do fit, at the cost of a wider image.
        if self.cfg.pad_left:
            img = cv2.copyMakeBorder(img, 0, 0, self._ndisp, 0, cv2.BORDER_REPLICATE)
        return img

    def compute(self, left_rgb: np.ndarray, right_rgb: np.ndarray, vertical: int | None = None) -> np.ndarray:
        """(H, W) float32 disparity in pixels (x_left − x_right); NaN where invalid. With ``grayscale``
        the images may be given grey already, (H, W) uint8 (the geometry stage has them: no second conversion).
        ``vertical``: match one row in that many (default: ``vertical_factor``'s)."""
        grey = self.cfg.grayscale and left_rgb.ndim == 2
        if left_rgb.shape != right_rgb.shape or not (grey or (left_rgb.ndim == 3 and left_rgb.shape[2] == 3)):
            raise ValueError(f"expected two (H, W, 3) images of equal shape, got {left_rgb.shape} and {right_rgb.shape}")
        vertical = self.vertical_factor(left_rgb.shape[0]) if vertical is None else vertical
        raw = self._sgbm.compute(self._prepare(left_rgb, vertical), self._prepare(right_rgb, vertical))
        if self.cfg.pad_left:
            raw = raw[:, self._ndisp :]
        disp = raw.astype(np.float32) / 16.0  # SGBM returns fixed point with 4 fractional bits
        disp[~(disp > 0)] = np.nan  # SGBM marks invalid with minDisparity − 1
        if self.cfg.downscale > 1 or vertical > 1:
            h, w = left_rgb.shape[:2]
            disp = _upsample(disp, w, h) * np.float32(self.cfg.downscale)  # disparity scales with the columns only
        if self._far is not None:
            with np.errstate(invalid="ignore"):
                small = disp < self.cfg.far_full_disparities - self.cfg.far_full_margin_px
            rows = np.flatnonzero(small.any(axis=1))
            if rows.size:
                # only the band of rows that holds small disparities (not the near road at the bottom), with a
                # block's margin so the band's own border does not touch them
                r0 = max(0, int(rows[0]) - self.cfg.block_size)
                r1 = min(disp.shape[0], int(rows[-1]) + 1 + self.cfg.block_size)
                fine = self._far.compute(left_rgb[r0:r1], right_rgb[r0:r1], vertical=self.cfg.far_row_step)
                band = disp[r0:r1]
                far = np.isfinite(fine) & small[r0:r1]
                band[far] = fine[far]
        if self.cfg.pad_left:
            # Near the left edge only disparities up to the column index are possible;
            # the replicated border can produce larger ones that are meaningless.
            cols = np.arange(disp.shape[1], dtype=np.float32)
            disp[disp > cols[None, :]] = np.nan
        return disp


def search_range(cfg: StereoConfig, bf: float) -> int:
    """``num_disparities`` (full-resolution px) reaching depths down to ``cfg.min_depth_m`` for a pair of ``bf`` px·m."""
    block = 16 * cfg.downscale  # SGBM searches in blocks of 16 at the matching scale
    return max(block, int(np.ceil(bf / cfg.min_depth_m / block - 1e-9)) * block)


def _upsample(disp: np.ndarray, w: int, h: int) -> np.ndarray:
    """Bilinear upsampling that averages valid neighbours only (NaN must not bleed)."""
    valid = np.isfinite(disp).astype(np.float32)
    num = cv2.resize(np.where(valid > 0, disp, 0).astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    den = cv2.resize(valid, (w, h), interpolation=cv2.INTER_LINEAR)
    near = cv2.resize(valid, (w, h), interpolation=cv2.INTER_NEAREST)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = num / den
    out[near == 0] = np.nan  # keep the invalid footprint of the coarse map
    return out


_CACHE: dict[tuple, StereoMatcher] = {}


def compute_disparity(left_rgb: np.ndarray, right_rgb: np.ndarray, cfg: StereoConfig) -> np.ndarray:
    """Disparity of a rectified pair with a matcher cached per configuration."""
    key = tuple(sorted(vars(cfg).items()))
    matcher = _CACHE.get(key)
    if matcher is None:
        matcher = _CACHE[key] = StereoMatcher(cfg)
    return matcher.compute(left_rgb, right_rgb)
