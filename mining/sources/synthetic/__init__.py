"""The ``synthetic`` source: procedurally rendered stereo driving scenes with exact truth.

Sequence names are integers ("0000", "17", ...); name and ``seed_base`` fix the world. Any
frame renders the same bits whatever was rendered before (random access, nothing carried
between calls except pure caches). See ``scene.py`` for the world and the object
categories, ``render.py`` for the rasteriser, ``textures.py`` for the materials, and
``scenarios.py`` for the staged scenarios (option ``scenario``) that replace the random
traffic by one failure mode at a time, and ``roadside.py`` for the background clutter
(verge, fence, hedge) that one of them adds.
"""

from __future__ import annotations

import time
from collections import OrderedDict

import cv2
import numpy as np

from mining.errors import InputError
from mining.sources.base import Source
from mining.sources.synthetic.render import Camera, inverse_depth_planes, rasterize, shade, texture_tables, to_camera
from mining.sources.synthetic.scenarios import get_scenario
from mining.sources.synthetic.scene import KNOWN, R_N, R_NV, R_OBJ, R_TINT, Scene, frame_faces
from mining.sources.synthetic.textures import build_atlas
from mining.types import FrameTruth, ObjectTruth, SequencePlan, StereoCalib, StereoFrame

CX_FRAC = 609.5593 / 1242  # ours: principal point as a fraction of the size, from KITTI P2
CY_FRAC = 172.854 / 375
AMBIENT = 0.55  # ours: sky light on every face
DIFFUSE = 0.55  # ours: sun light, scaled by cos(normal, sun)
NOISE_DN = 1.5  # ours: sensor noise sigma, 8-bit levels
BLUR_SIGMA = 0.8  # ours: optics blur, pixels (also hides raster stair-steps)
SCENES_CACHED = 2  # ours: worlds kept in memory per source


class SyntheticSource(Source):
    dataset = "synthetic"

    def __init__(self, root: str | None = None, n_frames: int = 500, width: int = 1242, height: int = 375,
                 fx: float = 721.5377, baseline_m: float = 0.5327, hz: float = 10.0, seed_base: int = 0,
                 sequences: list[str] | None = None, drop_frames: list[list[int]] | None = None,
                 scenario: str | None = None, more_unknowns: bool = False):
        """``drop_frames``: ranges [a, b) of frames left out of every plan, as if never recorded
        (each is a recording gap, ``SequencePlan.gaps``); the world goes on moving through them.
        ``scenario``: stage one of ``scenarios.SCENARIOS`` in every sequence instead of the random
        traffic (the sequence name still seeds the rest of the world). ``more_unknowns`` (issue 29,
        default off: the random worlds as before): add deer, boar, trolleys, pallets and sacks to
        a random world, the seed's other objects unchanged (ignored with a scenario)."""
        if n_frames <= 0 or width < 16 or height < 16 or hz <= 0:
            raise InputError(f"bad synthetic options n_frames={n_frames} size={width}x{height} hz={hz}")
        self.dropped: set[int] = set()
        for r in drop_frames or ():
            if len(r) != 2 or not 0 <= int(r[0]) < int(r[1]) <= n_frames:
                raise InputError(f"bad synthetic option drop_frames={drop_frames}: ranges [a, b) with 0 <= a < b <= n_frames")
            self.dropped.update(range(int(r[0]), int(r[1])))
        self.n_frames, self.hz, self.seed_base = int(n_frames), float(hz), int(seed_base)
        self.scenario = get_scenario(scenario) if scenario else None
        self.more_unknowns = bool(more_unknowns)
        self.calib = StereoCalib(fx, fx, width * CX_FRAC, height * CY_FRAC, baseline_m, width, height)
        self._names = list(sequences) if sequences else [f"{i:04d}" for i in range(4)]
        self._atlas = None
        self._scenes: OrderedDict[str, Scene] = OrderedDict()
        self._noise = None
        self._cam: Camera | None = None

    def sequences(self) -> list[str]:
        return list(self._names)

    def _seed(self, sequence: str) -> int:
        try:
            return int(sequence)
        except ValueError:
            raise InputError(f"synthetic sequence names are integers, got {sequence!r}") from None

    def survey(self, sequence: str) -> SequencePlan:
        self._seed(sequence)
        frames = tuple(i for i in range(self.n_frames) if i not in self.dropped)
        t_ns = tuple(int(round(i * 1e9 / self.hz)) for i in frames)
        gaps = tuple(p for p in range(1, len(frames)) if frames[p] != frames[p - 1] + 1)
        return SequencePlan(self.dataset, sequence, self.calib, frames, t_ns, gaps)

    def scene(self, sequence: str) -> Scene:
        if self._atlas is None:
            self._atlas = build_atlas(self.seed_base)
        if sequence not in self._scenes:
            seed = self.seed_base * 1_000_003 + self._seed(sequence)
            self._scenes[sequence] = Scene(seed, self.n_frames / self.hz + 1.0, self._atlas, self.scenario,
                                           self.more_unknowns)
            while len(self._scenes) > SCENES_CACHED:
                self._scenes.popitem(last=False)
        return self._scenes[sequence]

    def read_frame(self, plan: SequencePlan, position: int) -> StereoFrame:
        if not 0 <= position < len(plan):
            raise InputError(f"position {position} outside the plan of {len(plan)} frames", frame=position)
        index = plan.frames[position]
        t = plan.t_ns[position] / 1e9
        sc = self.scene(plan.sequence)
        c = self.calib
        if self._cam is None:
            self._cam = Camera(c.fx, c.fy, c.cx, c.cy, c.width, c.height)
        cam = self._cam
        verts, rows, states = frame_faces(sc, t, self._view())
        M = sc.camera_map(t)
        Rcm = M[:3, :3].T
        lambert = AMBIENT + DIFFUSE * np.clip(rows[:, R_N : R_N + 3] @ sc.sun, 0, 1)
        light = rows[:, R_TINT : R_TINT + 3] * lambert[:, None]
        gain = sc.exposure_at(t)
        sky = self._sky(cam, Rcm)  # coarse; depends on the rotation only: the same for both eyes
        rng = np.random.default_rng([sc.seed, index, 99])
        images, truth_bufs = [], None
        for k, shift in enumerate((0.0, c.baseline_m)):
            tcm = -Rcm @ M[:3, 3] - np.array([shift, 0, 0])
            V, rows_cam = to_camera(verts, rows, Rcm, tcm)
            C, dp = inverse_depth_planes(cam, rows_cam, V)
            ids, invz = rasterize(cam, V, rows_cam, C, dp)
            tab = texture_tables(cam, self._atlas, V, rows_cam, C)
            # exposure and the right camera's colour gain folded into the per-face light (the
            # atlas is 0–255, so the image comes out in 8-bit levels)
            g = gain * (sc.right_gain if k else np.ones(3))
            sky_img = cv2.resize(sky * (255.0 * g).astype(np.float32), (cam.w, cam.h), interpolation=cv2.INTER_LINEAR)
            img = shade(cam, self._atlas, ids, invz, tab, (light * g).astype(np.float32), sky_img)
            img = cv2.GaussianBlur(img, (5, 5), BLUR_SIGMA)  # the ±2 taps of sigma 0.5 weigh 3e-4: left out
            images.append(cv2.add(img, self._noise_at(rng, c.height, c.width), dtype=cv2.CV_8U))  # rounds, saturates
            if k == 0:
                truth_bufs = (ids, invz)
        truth = self._truth(sc, t, M, truth_bufs, rows, states)
        return StereoFrame(self.dataset, plan.sequence, index, plan.t_ns[position], images[0], images[1], c, truth)

    def unoccluded(self, plan: SequencePlan, position: int) -> dict[int, tuple[int, tuple[float, float, float, float] | None]]:
        """Per object near the ego: (pixels it would cover in the left image if nothing else
        were drawn, its untruncated box: the projection of all its vertices, None when some
        lie behind the camera). Rasterised by the same code as the frame, object by object,
        so ``visible pixels / unoccluded pixels`` is the share not hidden by other things."""
        if not 0 <= position < len(plan):
            raise InputError(f"position {position} outside the plan of {len(plan)} frames", frame=plan.frames[0])
        t = plan.t_ns[position] / 1e9
        sc = self.scene(plan.sequence)
        c = self.calib
        cam = self._cam or Camera(c.fx, c.fy, c.cx, c.cy, c.width, c.height)
        self._cam = cam
        verts, rows, states = frame_faces(sc, t, self._view())
        M = sc.camera_map(t)
        Rcm = M[:3, :3].T
        V, rows_cam = to_camera(verts, rows, Rcm, -Rcm @ M[:3, 3])
        obj = rows[:, R_OBJ].astype(np.int64)
        out = {}
        for tid in states:
            sel = np.flatnonzero(obj == tid)
            v, r = V[sel], rows_cam[sel]
            C, dp = inverse_depth_planes(cam, r, v)
            ids, _ = rasterize(cam, v, r, C, dp)
            pts = np.concatenate([v[k, : int(r[k, R_NV])] for k in range(len(sel))])
            box = None
            if pts[:, 2].min() > 1e-3:
                u = c.fx * pts[:, 0] / pts[:, 2] + c.cx
                w = c.fy * pts[:, 1] / pts[:, 2] + c.cy
                box = (float(u.min()), float(w.min()), float(u.max()), float(w.max()))
            out[tid] = (int((ids >= 0).sum()), box)
        return out

    def _view(self) -> tuple[float, float, float]:
        """The rig's field of view for ``frame_faces``: tan of the half angles (to the farther image
        border, plus a pixel), and the baseline (the right camera sits that far to the side)."""
        c = self.calib
        return ((max(c.cx, c.width - c.cx) + 1) / c.fx, (max(c.cy, c.height - c.cy) + 1) / c.fy, c.baseline_m)

    def _sky(self, cam: Camera, Rcm: np.ndarray) -> np.ndarray:
        """Sky gradient by ray elevation (horizon haze → blue zenith) on an 8× coarser grid
        (it is smooth: the caller resizes it to the image)."""
        yn = ((cam.v[::8, None] - cam.cy) / cam.fy).astype(np.float64)
        xn = (cam.u[None, ::8] - cam.cx) / cam.fx
        Rmc = Rcm.T
        dy = Rmc[1, 0] * xn + Rmc[1, 1] * yn + Rmc[1, 2]
        norm = np.sqrt(xn * xn + yn * yn + 1)
        e = np.clip(-dy / norm * 2.5, 0, 1).astype(np.float32)[..., None]
        horizon = np.array([0.86, 0.88, 0.90], np.float32)
        zenith = np.array([0.50, 0.64, 0.86], np.float32)
        return horizon * (1 - e) + zenith * e

    def _noise_at(self, rng: np.random.Generator, h: int, w: int) -> np.ndarray:
        """Sensor noise: a fixed bank of Gaussian noise, cut at a per-frame seeded offset."""
        if self._noise is None or self._noise.shape[0] < h + 64:
            self._noise = np.random.default_rng(self.seed_base + 12345).normal(0, NOISE_DN, (h + 64, w + 64, 3)).astype(np.float32)
        oy, ox = rng.integers(0, 64, 2)
        return self._noise[oy : oy + h, ox : ox + w]

    def _truth(self, sc: Scene, t: float, M: np.ndarray, bufs, rows, states) -> FrameTruth:
        ids, invz = bufs
        sky = ids < 0
        depth = np.reciprocal(invz)
        depth[sky] = np.nan
        face_obj = np.concatenate([rows[:, R_OBJ].astype(np.int32), [0]])
        objmap = np.take(face_obj, ids, mode="wrap")  # sky (−1) wraps to the trailing 0
        # group object pixels by track id (one sort instead of one full-frame compare per object)
        flat = objmap.ravel()
        pix = np.flatnonzero(flat)
        pix = pix[np.argsort(flat[pix], kind="stable")]
        labels = flat[pix]
        starts = np.flatnonzero(np.r_[True, labels[1:] != labels[:-1]]) if len(pix) else np.zeros(0, int)
        ends = np.r_[starts[1:], len(pix)]
        Mcm = np.linalg.inv(M)
        Rwm = sc.M0_inv[:3, :3]
        objs = []
        W = objmap.shape[1]
        for a, b in zip(starts, ends):
            tid = int(labels[a])
            o, pos, yaw = states[tid]
            mask = np.zeros(objmap.shape, bool)
            mask.ravel()[pix[a:b]] = True
            xs = pix[a:b] % W  # rows: the group is in ascending pixel order, first and last suffice
            y_top, y_bottom = int(pix[a]) // W, int(pix[b - 1]) // W
            centre_map = pos + np.array([0.0, -o.size[1] / 2, 0.0])
            centre = Mcm[:3, :3] @ centre_map + Mcm[:3, 3]
            p1, p0 = sc.state(o, t + 1e-3), sc.state(o, t - 1e-3)
            vel = (p1[0] - p0[0]) / 2e-3 if p1 is not None and p0 is not None else np.zeros(3)
            objs.append(ObjectTruth(tid, o.category, KNOWN[o.category], mask,
                                    (float(xs.min()), float(y_top), float(xs.max() + 1), float(y_bottom + 1)),
                                    centre, o.size.copy(), Rwm @ vel))
        return FrameTruth(depth, sc.pose(t), objs)


def bench_render(n: int = 10, sequence: str = "0000", **options) -> float:
    """Min milliseconds per ``read_frame`` (left + right + truth) over n frames, one thread."""
    cv2.setNumThreads(1)
    src = SyntheticSource(**options)
    plan = src.plan(sequence)
    src.read_frame(plan, 0)  # builds the atlas and the world
    best = float("inf")
    for i in range(1, n + 1):
        t0 = time.perf_counter()
        src.read_frame(plan, i % len(plan))
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


__all__ = ["SyntheticSource", "bench_render"]
