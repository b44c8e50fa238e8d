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

    def __init__(self, cfg: StereoConfig):
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
                                           far_full_disparities=0))
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

    def _prepare(self, rgb: np.ndarray) -> np.ndarray:
        img = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if self.cfg.grayscale else rgb
        if self.cfg.downscale > 1:
            img = cv2.resize(img, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
        # SGBM cannot match the leftmost num_disparities columns (their partners lie
        # outside the right image); padding on the left lets it match them with the
        # disparities that do fit, at the cost of a wider image.
        if self.cfg.pad_left:
            img = cv2.copyMakeBorder(img, 0, 0, self._ndisp, 0, cv2.BORDER_REPLICATE)
        return img

    def compute(self, left_rgb: np.ndarray, right_rgb: np.ndarray) -> np.ndarray:
        """(H, W) float32 disparity in pixels (x_left − x_right); NaN where invalid."""
        if left_rgb.shape != right_rgb.shape or left_rgb.ndim != 3 or left_rgb.shape[2] != 3:
            raise ValueError(f"expected two (H, W, 3) images of equal shape, got {left_rgb.shape} and {right_rgb.shape}")
        raw = self._sgbm.compute(self._prepare(left_rgb), self._prepare(right_rgb))
        if self.cfg.pad_left:
            raw = raw[:, self._ndisp :]
        disp = raw.astype(np.float32) / 16.0  # SGBM returns fixed point with 4 fractional bits
        disp[~(disp > 0)] = np.nan  # SGBM marks invalid with minDisparity − 1
        if self.cfg.downscale > 1:
            h, w = left_rgb.shape[:2]
            disp = _upsample(disp, w, h) * np.float32(self.cfg.downscale)
        if self._far is not None:
            with np.errstate(invalid="ignore"):
                small = disp < self.cfg.far_full_disparities - self.cfg.far_full_margin_px
            rows = np.flatnonzero(small.any(axis=1))
            if rows.size:
                # only the band of rows that holds small disparities (not the near road at the bottom), with a
                # block's margin so the band's own border does not touch them
                r0 = max(0, int(rows[0]) - self.cfg.block_size)
                r1 = min(disp.shape[0], int(rows[-1]) + 1 + self.cfg.block_size)
                fine = self._far.compute(left_rgb[r0:r1], right_rgb[r0:r1])
                band = disp[r0:r1]
                far = np.isfinite(fine) & small[r0:r1]
                band[far] = fine[far]
        if self.cfg.pad_left:
            # Near the left edge only disparities up to the column index are possible;
            # the replicated border can produce larger ones that are meaningless.
            cols = np.arange(disp.shape[1], dtype=np.float32)
            disp[disp > cols[None, :]] = np.nan
        return disp


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
