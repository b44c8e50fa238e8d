"""Stereo depth as the products show it: the geometry stage's depth of a frame
(``stereo_depth``) and its colours (``depth_colours``, ``depth_legend``): what `mine render
--depth` draws beside each frame and `mine export --format rerun --images` logs as a depth image.

The colours are OpenCV's turbo map on a fixed logarithmic range (``DEPTH_NEAR_M`` to the
job's ``geometry.stereo.max_depth_m``): near red, far blue, no depth black, so a colour
means the same depth in every frame and every video.
"""

from __future__ import annotations

import cv2
import numpy as np

from mining.draw import FONT

DEPTH_NEAR_M = 2.0  # ours: the depth colour map's near end (red); KITTI's 128 px search reaches ≈ 3 m
DEPTH_TICKS_M = (2, 5, 10, 20, 50, 90)  # ours: legend ticks (the far end is the job's geometry.stereo.max_depth_m)


def depth_colours(depth_m: np.ndarray, far_m: float) -> np.ndarray:
    """(H, W, 3) BGR turbo colours of depth on the fixed log range [DEPTH_NEAR_M, far_m]:
    near red, far blue, no depth (NaN) black."""
    valid = np.isfinite(depth_m)
    z = np.clip(np.where(valid, depth_m, far_m), DEPTH_NEAR_M, far_m)
    t = (np.log(z) - np.log(DEPTH_NEAR_M)) / (np.log(far_m) - np.log(DEPTH_NEAR_M))
    out = cv2.applyColorMap(np.round((1.0 - t) * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    out[~valid] = 0
    return out


def stereo_depth(matcher, frame, far_m: float) -> np.ndarray:
    """The geometry stage's depth of ``frame`` (``GeometryStage.run``'s disparity step: SGBM
    with the job's settings, NaN where invalid or beyond ``far_m``), without its flow,
    egomotion and ground steps, which the panel does not show (they would double its cost)."""
    depth = frame.calib.depth_from_disparity(matcher.compute(frame.left, frame.right))
    depth[depth > far_m] = np.nan
    return depth


def depth_legend(img: np.ndarray, far_m: float) -> None:
    """The colour bar of ``depth_colours`` with its ticks, in the panel's bottom-left corner."""
    h, w = img.shape[:2]
    bar_w, bar_h, pad = min(300, w - 40), 12, 6
    x0, y0 = 10, h - bar_h - 34
    cv2.rectangle(img, (x0 - pad, y0 - 22), (x0 + bar_w + pad + 24, h - 4), (0, 0, 0), cv2.FILLED)
    z = np.exp(np.linspace(np.log(DEPTH_NEAR_M), np.log(far_m), bar_w, dtype=np.float32))
    img[y0:y0 + bar_h, x0:x0 + bar_w] = depth_colours(np.tile(z, (bar_h, 1)), far_m)
    cv2.putText(img, "depth (m), stereo", (x0, y0 - 7), FONT, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    span = np.log(far_m) - np.log(DEPTH_NEAR_M)
    for tick in (t for t in DEPTH_TICKS_M if DEPTH_NEAR_M <= t <= far_m):
        x = x0 + int(round((np.log(tick) - np.log(DEPTH_NEAR_M)) / span * (bar_w - 1)))
        cv2.line(img, (x, y0 + bar_h), (x, y0 + bar_h + 3), (255, 255, 255), 1)
        (tw, _), _ = cv2.getTextSize(str(tick), FONT, 0.4, 1)
        cv2.putText(img, str(tick), (x - tw // 2, y0 + bar_h + 15), FONT, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
