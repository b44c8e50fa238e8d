"""The geometry stage: per frame, disparity/depth, sparse scene flow, egomotion, ground.

``GeometryStage`` keeps the previous frame's stereo features (grey images and left/right
corner matches) so each frame is processed once; the first frame of a run has no flow
and no egomotion.
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from mining.errors import InputError
from mining.geometry.config import GeometryConfig
from mining.geometry.disparity import StereoMatcher
from mining.geometry.egomotion import estimate_egomotion
from mining.geometry.flow import StereoFeatures, bucket_select, match_quad, scene_flow, stereo_features
from mining.geometry.ground import estimate_ground
from mining.types import FrameGeometry, StereoCalib, StereoFrame


class GeometryStage:
    """Stateful per-run geometry: feed frames in time order with :meth:`run`."""

    def __init__(self, calib: StereoCalib, cfg: GeometryConfig | None = None):
        self.calib = calib
        self.cfg = cfg or GeometryConfig()
        self.matcher = StereoMatcher(self.cfg.stereo, calib.bf)
        self._prev: StereoFeatures | None = None
        self._prev_index: int | None = None
        self._last_motion: np.ndarray | None = None  # last good T_cur_prev, predicts the next matches

    def reset(self) -> None:
        """Forget the previous frame (e.g. after a recording gap)."""
        self._prev = self._prev_index = self._last_motion = None

    def _check(self, frame: StereoFrame) -> None:
        h, w = self.calib.height, self.calib.width
        for side, img in (("left", frame.left), ("right", frame.right)):
            if img is None or img.ndim != 3 or img.shape[:2] != (h, w) or img.shape[2] != 3 or img.dtype != np.uint8:
                shape = None if img is None else (img.shape, img.dtype)
                raise InputError(f"{side} image must be ({h}, {w}, 3) uint8 RGB, got {shape}", f"{frame.dataset}/{frame.sequence}", frame.index)
        if self._prev_index is not None and frame.index <= self._prev_index:
            raise InputError(f"frames out of order: {frame.index} after {self._prev_index}", f"{frame.dataset}/{frame.sequence}", frame.index)

    def _exact_disparity(self, frame: StereoFrame) -> np.ndarray:
        """The disparity of the source's exact depth (``stereo.exact_depth``); NaN where nothing was hit."""
        truth = frame.truth
        if truth is None or truth.depth.shape != (self.calib.height, self.calib.width):
            raise InputError("geometry.stereo.exact_depth needs the source's exact depth (synthetic only); this frame has "
                             + ("none" if truth is None else f"a {truth.depth.shape} depth map"),
                             f"{frame.dataset}/{frame.sequence}", frame.index)
        z = truth.depth.astype(np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            d = np.float32(self.calib.bf) / z
        d[~(z > 0)] = np.nan
        return d

    def run(self, frame: StereoFrame) -> FrameGeometry:
        self._check(frame)
        cfg, calib, timings = self.cfg, self.calib, {}

        t0 = time.perf_counter()
        left = cv2.cvtColor(frame.left, cv2.COLOR_RGB2GRAY)
        right = cv2.cvtColor(frame.right, cv2.COLOR_RGB2GRAY)
        if cfg.stereo.exact_depth:
            disparity = self._exact_disparity(frame)
        elif cfg.stereo.grayscale:
            disparity = self.matcher.compute(left, right)  # the same grey images the features use
        else:
            disparity = self.matcher.compute(frame.left, frame.right)
        depth = calib.depth_from_disparity(disparity)
        depth[depth > cfg.stereo.max_depth_m] = np.nan  # REFERENCE: beyond 90 m is ignored
        t1 = time.perf_counter()
        timings["disparity"] = (t1 - t0) * 1e3

        cur = stereo_features(left, right, disparity, cfg.flow)
        matches = None if self._prev is None else match_quad(self._prev, cur, calib, cfg.flow, self._last_motion)
        t2 = time.perf_counter()
        timings["flow"] = (t2 - t1) * 1e3

        flow = egomotion = None
        if matches is not None:
            use = bucket_select(matches.uv_left, cfg.flow.bucket_size_px, cfg.flow.bucket_max_features)
            egomotion = estimate_egomotion(matches, calib, cfg.egomotion, use)
            # Without a trusted motion the next frame's matching starts from no prediction.
            self._last_motion = egomotion.T_cur_prev if egomotion.ok else None
            flow = scene_flow(matches, calib, egomotion.T_cur_prev, cfg.egomotion.inlier_threshold_px)
        t3 = time.perf_counter()
        timings["egomotion"] = (t3 - t2) * 1e3

        ground = estimate_ground(disparity, calib, cfg.ground)
        timings["ground"] = (time.perf_counter() - t3) * 1e3

        self._prev, self._prev_index = cur, frame.index
        return FrameGeometry(frame.index, frame.t_ns, disparity, depth, flow, egomotion, ground, timings)
