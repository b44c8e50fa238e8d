"""World generation of the synthetic source: road, ego trajectory, structure, objects.

Everything is a pure function of the seed and the time, so any frame can be rendered in
any order. The *map* frame has x right, y down, z forward (like the camera) with the road
surface at y = 0; the first camera pose turns it into the world frame of ``FrameTruth``.

Geometry is planar convex polygons ("faces"), each carrying a texture frame anchored to the
surface it belongs to (the road's arc length, a building's wall, an object's own body), so
texture moves exactly with the 3D motion.

Categories. Known (a COCO class covers them): car (hatchback, saloon, estate, SUV and van
bodies), truck, bus, person (walking, standing or riding), bicycle. Unknown: cone (traffic
cone), bin (wheelie bin), crate, debris (a low-poly rock or lump lying on the road), blob (a
crawling low-poly ellipsoid the size of a large dog but with no legs, head or tail, so no
COCO animal class describes it), tyre (a loose car tyre, lying or standing), barrier (a
striped board on trestles or a concrete kerb barrier), box (cardboard), branch (a fallen
branch with leaves), cart (a two-wheeled hand cart) and tortoise (a giant tortoise crossing:
an animal, but none of COCO's ten). Only in staged scenarios or behind the source option
``more_unknowns`` (issue 29; by default the random worlds are drawn as before): deer (a roe deer) and boar (a wild boar), walking quadrupeds COCO's ten
animals do not include; trolley (a wire shopping trolley, mostly see-through); pallet (a Euro
pallet) and sack (a filled sack), a fallen load. The meshes are in ``meshes.py``. Objects
beyond the curb stand on the sidewalk (a curb height up).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from mining.sources.synthetic.faces import (  # noqa: F401  (the row layout is re-exported for the renderer)
    DOWN, MAXV, R_N, R_NV, R_O, R_OBJ, R_PART, R_SKEY, R_TILE, R_TINT, R_U, R_V, FaceList, rot_x, rot_y, rot_z,
)
from mining.sources.synthetic.meshes import (
    ANIMATED, CAR_COLOURS, CAR_SHAPES, CAR_WEIGHTS, CLOTHES, EURO_PALLET_M, QUADRUPEDS, TROUSERS, build_mesh,
    part_poses, rider_height,
)
from mining.sources.synthetic.nearby import Nearby, keep_mesh
from mining.sources.synthetic.textures import LANE_M, PARKING_M, Atlas

if TYPE_CHECKING:
    from mining.sources.synthetic.scenarios import Scenario

CAMERA_HEIGHT_M = 1.65  # ours: KITTI's camera height above the road
SIDEWALK_M = 4.5  # ours: sidewalk width
CURB_M = 0.12  # ours: curb height
GROUND_DROP_M = 0.02  # ours: the terrain plane lies this far below the road (no z-fighting)
MAX_SPEED = 15.0  # ours: ego speed limit, m/s
VIEW_AHEAD_M = 140.0  # ours: structure and objects further along the road are not drawn
VIEW_BEHIND_M = 25.0  # ours: ... nor further behind the camera
VIEW_SLACK_M = 0.5  # ours: an object's bounding sphere grows by this much in the view test (swinging limbs, mirrors)
KNOWN = {"car": True, "truck": True, "bus": True, "person": True, "bicycle": True,
         "cone": False, "bin": False, "crate": False, "debris": False, "blob": False, "tyre": False,
         "barrier": False, "box": False, "branch": False, "cart": False, "tortoise": False,
         # issue 29, in staged scenarios only (the random worlds stay as they were): COCO has no deer or
         # boar, no trolley, pallet or sack
         "deer": False, "boar": False, "trolley": False, "pallet": False, "sack": False}


# --------------------------------------------------------------------------- road and ego


class Road:
    """Centreline as heading θ(s) integrated from a smooth random curvature profile.
    ``turns=False`` keeps the gentle bends only (a staged scenario's road)."""

    DS = 0.5  # ours: sampling step of the centreline, metres

    def __init__(self, rng: np.random.Generator, s_min: float, s_max: float, turns: bool = True):
        self.s = np.arange(s_min, s_max + self.DS, self.DS)
        n = len(self.s)
        kappa = np.zeros(n)
        # gentle bends: a few random sinusoids, radius > ~400 m
        for _ in range(3):
            kappa += rng.uniform(-0.0012, 0.0012) * np.sin(2 * np.pi * self.s / rng.uniform(150, 600) + rng.uniform(0, 6.3))
        # turns: raised-cosine curvature bumps of radius 25–60 m turning 40–90°
        pos = rng.uniform(60, 160) if turns else np.inf
        while pos < s_max:
            radius = rng.uniform(25, 60)
            angle = np.radians(rng.uniform(40, 90))
            length = 2 * angle * radius  # the raised cosine averages half its peak
            w = np.clip((self.s - pos) / length, 0, 1)
            bump = 0.5 * (1 - np.cos(2 * np.pi * w)) * ((self.s >= pos) & (self.s <= pos + length))
            kappa += rng.choice([-1, 1]) / radius * bump
            pos += length + rng.uniform(120, 400)
        self.kappa = kappa
        i0 = np.searchsorted(self.s, 0.0)
        theta = np.concatenate([[0.0], np.cumsum(0.5 * (kappa[1:] + kappa[:-1]) * self.DS)])
        self.theta = theta - theta[i0]
        x = np.concatenate([[0.0], np.cumsum(0.5 * (np.sin(self.theta[1:]) + np.sin(self.theta[:-1])) * self.DS)])
        z = np.concatenate([[0.0], np.cumsum(0.5 * (np.cos(self.theta[1:]) + np.cos(self.theta[:-1])) * self.DS)])
        self.x, self.z = x - x[i0], z - z[i0]
        # plain-float copies for the scalar path (objects are placed one at a time, hundreds per frame)
        self._lists = (self.s.tolist(), self.x.tolist(), self.z.tolist(), self.theta.tolist())

    def _scalar(self, s: float) -> tuple[float, float, float]:
        """Centre x, z and heading θ at one arc length, interpolated linearly."""
        ss, xs, zs, ths = self._lists
        i = min(max(int((s - ss[0]) / self.DS), 0), len(ss) - 2)
        f = (s - ss[i]) / self.DS
        return xs[i] + f * (xs[i + 1] - xs[i]), zs[i] + f * (zs[i + 1] - zs[i]), ths[i] + f * (ths[i + 1] - ths[i])

    def frame(self, s):
        """Centre point (…,3), heading θ, tangent and right normal at arc length(s) ``s``."""
        if np.ndim(s) == 0:
            x, z, th = self._scalar(float(s))
            c, sn = math.cos(th), math.sin(th)
            return np.array([x, 0.0, z]), th, np.array([sn, 0.0, c]), np.array([c, 0.0, -sn])
        s = np.asarray(s, float)
        x = np.interp(s, self.s, self.x)
        z = np.interp(s, self.s, self.z)
        th = np.interp(s, self.s, self.theta)
        c = np.stack([x, np.zeros_like(x), z], -1)
        t = np.stack([np.sin(th), np.zeros_like(th), np.cos(th)], -1)
        nrm = np.stack([np.cos(th), np.zeros_like(th), -np.sin(th)], -1)
        return c, th, t, nrm

    def point(self, s, d, y=0.0):
        if np.ndim(s) == 0 and np.ndim(d) == 0 and np.ndim(y) == 0:
            x, z, th = self._scalar(float(s))
            return np.array([x + d * math.cos(th), y, z - d * math.sin(th)])  # centre + d · right normal
        c, _, _, nrm = self.frame(s)
        if np.ndim(s) == 0:
            return c + d * nrm + np.array([0.0, y, 0.0])
        return c + np.asarray(d)[..., None] * nrm + np.asarray([0.0, 1.0, 0.0]) * np.asarray(y)[..., None]

    def curvature(self, s):
        return np.interp(s, self.s, self.kappa)


def ego_speed_profile(rng: np.random.Generator, road: Road, duration_s: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Arc length and speed of the ego on a fine time grid: random target speeds (some stops),
    limited by lateral acceleration in turns and by ±2.5 m/s² longitudinal."""
    n = int(np.ceil(duration_s / dt)) + 2
    s = np.zeros(n)
    v = np.zeros(n)
    v[0] = rng.choice([0.0, rng.uniform(4, 12)], p=[0.25, 0.75])
    t_next, target = 0.0, v[0]
    stop_until = -1.0
    for i in range(1, n):
        t = i * dt
        if t >= t_next:
            if rng.random() < 0.2 and t > 3:
                stop_until = t + rng.uniform(2, 6)
                target = 0.0
            else:
                target = rng.uniform(3, MAX_SPEED)
            t_next = t + rng.uniform(4, 12)
        if t < stop_until:
            tgt = 0.0
        else:
            tgt = target if target > 0 else 8.0  # ours: pull away after a stop
        ahead = np.abs(road.curvature(s[i - 1] + np.arange(0, 40, 5.0))).max()
        tgt = min(tgt, np.sqrt(2.0 / max(ahead, 1e-6)))  # ours: 2 m/s² lateral in turns
        dv = np.clip(tgt - v[i - 1], -2.5 * dt, 2.0 * dt)
        v[i] = max(0.0, v[i - 1] + dv)
        s[i] = s[i - 1] + 0.5 * (v[i] + v[i - 1]) * dt
    return s, v


def speed_arc(times, speeds, t: float) -> float:
    """∫₀ᵗ v dt for a speed piecewise linear through the knots (times, speeds), constant before
    the first knot and after the last (exact: each piece integrates as a trapezoid)."""
    times, speeds = np.asarray(times, float), np.asarray(speeds, float)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (speeds[1:] + speeds[:-1]) * np.diff(times))])

    def arc_from_first_knot(x: float) -> float:
        if x <= times[0]:
            return float(speeds[0] * (x - times[0]))
        i = int(np.searchsorted(times, x, side="right")) - 1
        if i >= len(times) - 1:
            return float(cum[-1] + speeds[-1] * (x - times[-1]))
        h = x - times[i]
        slope = (speeds[i + 1] - speeds[i]) / (times[i + 1] - times[i])
        return float(cum[i] + speeds[i] * h + 0.5 * slope * h * h)

    return arc_from_first_knot(t) - arc_from_first_knot(0.0)


def knot_speed_profile(times, speeds, duration_s: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Arc length and speed of the ego on the fine time grid for a fixed speed profile (knots)."""
    n = int(np.ceil(duration_s / dt)) + 2
    grid = np.arange(n) * dt
    s = np.array([speed_arc(times, speeds, t) for t in grid])
    return s, np.interp(grid, times, speeds)


# --------------------------------------------------------------------------- objects


@dataclass
class Motion:
    """How an object moves in road coordinates (arc length s, lateral offset d)."""

    kind: str  # "static", "lane", "follow", "path", "speed"
    s0: float = 0.0
    d: float = 0.0
    v: float = 0.0  # lane: signed speed along s
    yaw: float = 0.0  # relative to the road heading (static, lane, follow, speed)
    gap: tuple[float, float, float] = (15.0, 5.0, 0.1)  # follow: mean, amplitude, rad/s
    times: np.ndarray | None = None  # path waypoints; speed: the profile's knots
    ss: np.ndarray | None = None
    dd: np.ndarray | None = None
    vs: np.ndarray | None = None  # speed: signed speed along s at the knots (one sign), linear between


@dataclass
class Obj:
    track_id: int
    category: str
    size: np.ndarray  # w, h, l
    tint: tuple[float, float, float]
    motion: Motion
    seed: int
    tint2: tuple[float, float, float] = (1, 1, 1)
    faces: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    material: str | None = None  # every face of this material (e.g. "flat": textureless); None: the category's own
    shape: str = ""  # the variant of the category (a car's body type, a tyre lying or upright, ...)
    riding: bool = False  # a person on a bicycle (seated, pedalling)
    stature: float = 0.0  # a person's standing height (size[1] is a rider's seated height)


class Scene:
    """The whole world of one sequence."""

    def __init__(self, seed: int, duration_s: float, atlas: Atlas, scenario: Scenario | None = None,
                 more_unknowns: bool = False):
        """``scenario`` (``scenarios.py``) stages its objects and the ego's speed instead of the
        random traffic and drive; without one, the world is exactly the seed's random one.
        ``more_unknowns`` (random worlds only) adds issue 29's kinds to it (``_more_unknowns``)
        after everything else, from a random stream of their own: the seed's other objects stay
        exactly as they are."""
        self.seed = seed
        self.atlas = atlas
        self.scenario = scenario
        rng = np.random.default_rng([seed, 1])
        self.lanes = int(rng.choice([1, 2], p=[0.6, 0.4]))
        if scenario is not None:
            self.lanes = scenario.lanes
        self.half = self.lanes * LANE_M + PARKING_M  # curb offset from the centreline
        self.road_tile = "road1" if self.lanes == 1 else "road2"
        self.duration = duration_s
        self.road = Road(rng, -200.0, duration_s * MAX_SPEED + 600.0, turns=scenario is None)
        self.dt = 0.02
        if scenario is None:
            self.ego_s, self.ego_v = ego_speed_profile(np.random.default_rng([seed, 2]), self.road, duration_s + 1.0, self.dt)
        else:
            self.ego_s, self.ego_v = knot_speed_profile(*scenario.ego_speed, duration_s + 1.0, self.dt)
        self.ego_d = LANE_M / 2 + (LANE_M if self.lanes == 2 and rng.random() < 0.5 else 0.0)
        if scenario is not None:
            self.ego_d = LANE_M / 2 + LANE_M * scenario.ego_lane
        self.wobble = rng.uniform(0, 6.3, 6)
        sun_az, sun_el = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(25, 60))
        self.sun = np.array([np.cos(sun_el) * np.sin(sun_az), -np.sin(sun_el), np.cos(sun_el) * np.cos(sun_az)])
        self.exposure = (rng.uniform(0.9, 1.1), rng.uniform(0.05, 0.15), rng.uniform(20, 60), rng.uniform(0, 6.3))
        self.right_gain = rng.uniform(0.96, 1.04, 3)
        self.objects: list[Obj] = []
        self.meshed: dict[int, Obj] = {}  # objects with a mesh, least recently drawn first (nearby.keep_mesh)
        self._nearby: Nearby | None = None
        self.roles: dict = {}  # track id → scenarios.Role (staged scenarios only)
        self._build_static(np.random.default_rng([seed, 3]))
        if scenario is None:
            self._build_objects(np.random.default_rng([seed, 4]))
            if more_unknowns:
                self._more_unknowns(np.random.default_rng([seed, 6]))
        else:
            self.roles = scenario.build(self, np.random.default_rng([seed, 4]))
        self.M0_inv = np.linalg.inv(self.camera_map(0.0))

    # ----- ego

    def ego_arc(self, t: float) -> float:
        return float(np.interp(t, np.arange(len(self.ego_s)) * self.dt, self.ego_s))

    def camera_map(self, t: float) -> np.ndarray:
        """4×4 camera-to-map transform at time t: lane centre, road heading, mild pitch/roll/yaw sway."""
        s = self.ego_arc(t)
        w = self.wobble
        lat = 0.15 * np.sin(0.31 * t + w[0])
        c, th, _, nrm = self.road.frame(s)
        pos = c + (self.ego_d + lat) * nrm + np.array([0.0, -CAMERA_HEIGHT_M, 0.0])
        yaw = th + 0.004 * np.sin(0.5 * t + w[1])
        pitch = np.radians(0.4) * np.sin(1.3 * t + w[2]) + np.radians(0.2) * np.sin(3.1 * t + w[3])
        roll = np.radians(0.3) * np.sin(0.9 * t + w[4])
        M = np.eye(4)
        M[:3, :3] = rot_y(yaw) @ rot_x(pitch) @ rot_z(roll)
        M[:3, 3] = pos
        return M

    def pose(self, t: float) -> np.ndarray:
        """Camera-to-world (world = first camera)."""
        return self.M0_inv @ self.camera_map(t)

    def exposure_at(self, t: float) -> float:
        a, b, period, ph = self.exposure
        return a * (1 + b * np.sin(2 * np.pi * t / period + ph))

    # ----- static structure

    def _build_static(self, rng: np.random.Generator) -> None:
        fl = FaceList(self.atlas)
        road = self.road
        s_lo, s_hi = road.s[0] + 1, road.s[-1] - 1
        # adaptive nodes: ≤ 8 m and ≤ 2.5° of heading per segment
        nodes = [s_lo]
        while nodes[-1] < s_hi:
            k = abs(road.curvature(nodes[-1])) + abs(road.curvature(nodes[-1] + 4))
            nodes.append(min(s_hi, nodes[-1] + float(np.clip(np.radians(2.5) / max(k / 2, 1e-9), 2.0, 8.0))))
        nodes = np.array(nodes)
        h, sw = self.half, SIDEWALK_M
        up = np.array([0.0, -1.0, 0.0])
        for a, b in zip(nodes[:-1], nodes[1:]):
            key = 0.5 * (a + b)
            ca, _, ta, na = road.frame(a)
            cb, _, tb, nb = road.frame(b)
            chord = (cb - ca) / np.linalg.norm(cb - ca)
            right = np.array([chord[2], 0.0, -chord[0]])
            # road: u along the arc (origin carries the arc length), v across
            pts = [ca - h * na, cb - h * nb, cb + h * nb, ca + h * na]
            o = ca - h * right
            fl.add(pts, up, o, chord, right, self.road_tile, skey=key, offset=(a % 12.0, 0.0))
            for side in (-1, 1):
                y = np.array([0, -CURB_M, 0])
                inner_a, inner_b = ca + side * h * na, cb + side * h * nb
                outer_a, outer_b = ca + side * (h + sw) * na, cb + side * (h + sw) * nb
                fl.add([inner_a, inner_b, inner_b + y, inner_a + y], -side * right, inner_a + y, chord, DOWN,
                       "concrete", skey=key, offset=(a % 4.0, 0))
                fl.add([inner_a + y, inner_b + y, outer_b + y, outer_a + y], up, inner_a + y, chord, side * right,
                       "sidewalk", skey=key, offset=(a % 3.0, 0))
                g = np.array([0, GROUND_DROP_M, 0])
                fl.add([outer_a + y, outer_b + y, outer_b + g, outer_a + g], side * right, outer_a + y, chord, DOWN,
                       "concrete", skey=key, offset=(a % 4.0, 0))
        for side in (-1, 1):
            back = self.scenario.right_setback_m if side > 0 and self.scenario is not None else 0.0
            self._lots(fl, rng, side, s_lo + 5, s_hi - 5, back)
        self.static_verts, self.static_rows = fl.arrays()
        self._static_spheres()

    def _static_spheres(self) -> None:
        """Bounding spheres of the static faces for the view test (padded vertices repeat a real
        one: the box is exact)."""
        lo, hi = self.static_verts.min(1), self.static_verts.max(1)
        self.static_centres = (lo + hi) / 2
        self.static_radii = np.linalg.norm(hi - lo, axis=1) / 2

    def add_static(self, fl: FaceList) -> None:
        """More static structure (a staged scenario's roadside): background faces (object id 0,
        so no ``ObjectTruth``), drawn like the rest, each kept within view by its ``R_SKEY``."""
        v, r = fl.arrays()
        if len(v):
            self.static_verts = np.concatenate([self.static_verts, v])
            self.static_rows = np.concatenate([self.static_rows, r])
            self._static_spheres()

    def _lots(self, fl: FaceList, rng, side: int, s_lo: float, s_hi: float, back_m: float = 0.0) -> None:
        """Buildings, walls, fences, trees and street furniture along one side; ``back_m`` moves
        the lots (not the street furniture) that much further from the sidewalk."""
        road = self.road
        front = self.half + SIDEWALK_M + back_m
        s = s_lo
        facades = ["facade_brick", "facade_plaster", "facade_glass", "facade_stone"]
        while s < s_hi:
            k = abs(road.curvature(s))
            length = rng.uniform(8, 28) if k < 0.01 else rng.uniform(6, 10)
            kind = rng.choice(["building", "wall", "fence", "trees", "open"], p=[0.5, 0.12, 0.1, 0.18, 0.1])
            mid = s + length / 2
            c, th, t, n = road.frame(mid)
            R = rot_y(float(th))
            setback = rng.uniform(0.0, 1.5)
            if kind == "building" or (kind in ("wall", "fence") and rng.random() < 0.5):
                depth = rng.uniform(8, 14)
                hgt = rng.uniform(5, 18)
                back = 0 if kind == "building" else rng.uniform(3, 8)
                dc = side * (front + setback + back + depth / 2)
                cen = c + dc * n + np.array([0, -hgt / 2, 0])
                tint = tuple(rng.uniform(0.75, 1.0, 3))
                mat = str(rng.choice(facades))
                fl.box(cen, (length / 2 - rng.uniform(0, 1), hgt / 2, depth / 2), R @ rot_y(np.pi / 2),
                       {"all": mat}, tint, skey=mid, offset=tuple(rng.uniform(0, 3, 2)), skip=("bottom", "top"))
            if kind in ("wall", "fence"):
                hgt = rng.uniform(1.6, 2.6) if kind == "wall" else rng.uniform(1.0, 1.4)
                dc = side * (front + 0.15)
                cen = c + dc * n + np.array([0, -hgt / 2 + GROUND_DROP_M, 0])
                mat = "concrete" if kind == "wall" else "fence"
                fl.box(cen, (length / 2, hgt / 2, 0.15), R @ rot_y(np.pi / 2), {"all": mat},
                       tuple(rng.uniform(0.8, 1.0, 3)), skey=mid, skip=("bottom",))
            if kind == "trees":
                for st in np.arange(s + 2, s + length - 1, rng.uniform(5, 9)):
                    self._tree(fl, rng, st, side * (front + rng.uniform(1.0, 4.0)))
            # street furniture on the sidewalk edge: poles and the odd street tree
            if rng.random() < 0.5:
                st = s + rng.uniform(0, length)
                if rng.random() < 0.4:
                    self._tree(fl, rng, st, side * (self.half + 0.6))
                else:
                    cp = road.point(st, side * (self.half + 0.3), -3.0)
                    fl.box(cp, (0.08, 3.0, 0.08), rot_y(float(road.frame(st)[1])), {"all": "metal"}, skey=st)
            s += length

    def _tree(self, fl: FaceList, rng, s: float, d: float) -> None:
        road = self.road
        trunk_h = rng.uniform(2.0, 3.5)
        base = road.point(s, d, 0.0)
        R = rot_y(rng.uniform(0, np.pi))
        fl.box(base + np.array([0, -trunk_h / 2, 0]), (0.12, trunk_h / 2, 0.12), R, {"all": "bark"}, skey=s,
               offset=tuple(rng.uniform(0, 1, 2)))
        r = rng.uniform(1.3, 2.2)
        hc = rng.uniform(1.6, 2.6)
        cen = base + np.array([0, -trunk_h - hc / 2, 0])
        ang = np.arange(6) * np.pi / 3 + rng.uniform(0, 1)
        ring = np.stack([np.cos(ang) * r, np.zeros(6), np.sin(ang) * r], 1) * rng.uniform(0.85, 1.15, (6, 1))
        pts = np.concatenate([cen + ring, cen + [[0, -hc / 2, 0], [0, hc / 2, 0]]])  # hexagonal bipyramid
        tint = tuple(rng.uniform(0.8, 1.1, 3))
        start = len(fl.rows)
        fl.convex(pts, "foliage", tint, offset=tuple(rng.uniform(0, 2, 2)))
        for row in fl.rows[start:]:
            row[R_SKEY] = s

    # ----- objects

    def add_object(self, rng: np.random.Generator, category: str, motion: Motion, size=None,
                   shape: str | None = None) -> Obj:
        """One more object (its track id is the next free one); size, tint and mesh seed from ``rng``;
        ``shape``: the variant (a car's body, a tyre's pose, a barrier's kind) instead of a random one."""
        return self._new(rng, category, motion, size, shape=shape)

    def _new(self, rng, category: str, motion: Motion, size=None, riding: bool = False, shape: str | None = None) -> Obj:
        if shape is not None:  # chosen by the caller (a staged scenario): no draw for it
            body = next((c for c in CAR_SHAPES if c.name == shape), None) if category == "car" else None
            if category == "car" and body is None:
                raise KeyError(f"no car body {shape!r}")
        elif category == "car":
            body = CAR_SHAPES[int(rng.choice(len(CAR_SHAPES), p=CAR_WEIGHTS))]
            shape = body.name
        elif category == "tyre":
            shape = str(rng.choice(["lying1", "lying2", "lying3", "upright"], p=[0.35, 0.2, 0.1, 0.35]))
        elif category == "barrier":
            shape = "jersey" if rng.random() < 0.35 else "board"
        else:
            shape = ""
        if size is None:
            if category == "car":
                size = (rng.uniform(*body.width), rng.uniform(*body.height), rng.uniform(*body.length))
            elif category == "tyre":
                size = (0.2, 0.62, 0.62) if shape == "upright" else (0.62, 0.205 * int(shape[-1]), 0.62)
            elif category == "barrier":
                size = (0.6, 0.8, rng.uniform(2.0, 3.0)) if shape == "jersey" else (0.6, 1.0, rng.uniform(1.2, 2.0))
            else:
                size = {
                    "truck": lambda: (2.4, rng.uniform(3.0, 3.6), rng.uniform(7, 9)),
                    "bus": lambda: (2.5, 3.1, rng.uniform(10, 12)),
                    "person": lambda: (0.5, rng.uniform(1.55, 1.9), 0.3),
                    "bicycle": lambda: (0.5, 1.05, 1.78),
                    "cone": lambda: (0.4, rng.uniform(0.5, 0.75), 0.4),
                    "bin": lambda: (0.6, 1.07, 0.72),
                    "crate": lambda: tuple([rng.uniform(0.4, 1.0)] * 2 + [rng.uniform(0.4, 1.2)]),
                    "debris": lambda: (rng.uniform(0.3, 0.9), rng.uniform(0.2, 0.5), rng.uniform(0.3, 1.0)),
                    "blob": lambda: (rng.uniform(0.6, 0.9), rng.uniform(0.5, 0.8), rng.uniform(0.9, 1.4)),
                    "box": lambda: (rng.uniform(0.3, 0.7), rng.uniform(0.25, 0.6), rng.uniform(0.3, 0.7)),
                    "branch": lambda: (rng.uniform(0.8, 1.6), rng.uniform(0.3, 0.6), rng.uniform(1.5, 3.0)),
                    "cart": lambda: (0.8, 1.0, rng.uniform(1.3, 1.6)),
                    "tortoise": lambda: (rng.uniform(0.6, 0.8), rng.uniform(0.4, 0.5), rng.uniform(0.8, 1.1)),
                    # a deer 0.9–1.05 of its nominal build, a boar 0.8–1.1 (meshes.QUADRUPEDS)
                    "deer": lambda: tuple(np.array(QUADRUPEDS["deer"].size) * rng.uniform(0.9, 1.05)),
                    "boar": lambda: tuple(np.array(QUADRUPEDS["boar"].size) * rng.uniform(0.8, 1.1)),
                    # ours: a shopping trolley ~0.58 × 1.0 × 0.95 m (100 l) down to ~0.85 of it (60–80 l)
                    "trolley": lambda: tuple(np.array([0.58, 1.0, 0.95]) * rng.uniform(0.85, 1.0)),
                    "pallet": lambda: EURO_PALLET_M,
                    # ours: a filled 25–50 kg sack lying flat, ~0.4–0.55 × 0.1–0.16 × 0.6–0.9 m
                    "sack": lambda: (rng.uniform(0.4, 0.55), rng.uniform(0.1, 0.16), rng.uniform(0.6, 0.9)),
                }[category]()
        palette = [(0.9, 0.9, 0.9), (0.15, 0.15, 0.17), (0.6, 0.62, 0.65), (0.7, 0.1, 0.1), (0.15, 0.25, 0.6),
                   (0.85, 0.85, 0.8), (0.3, 0.35, 0.3), (0.8, 0.6, 0.2)]
        tint2 = tuple(rng.uniform(0.15, 0.8, 3))
        if category == "car":
            colours, weights = zip(*CAR_COLOURS)
            c = np.array(colours[int(rng.choice(len(colours), p=np.array(weights) / sum(weights)))])
            tint = tuple(np.clip(c * rng.uniform(0.92, 1.06, 3), 0, 1))
        elif category in ("truck", "bus"):
            tint = palette[rng.integers(len(palette))]
        elif category == "person":
            tint = tuple(np.clip(np.array(CLOTHES[int(rng.integers(len(CLOTHES)))]) * rng.uniform(0.8, 1.15, 3), 0, 1))
            tint2 = tuple(np.clip(np.array(TROUSERS[int(rng.integers(len(TROUSERS)))]) * rng.uniform(0.85, 1.15, 3), 0, 1))
        elif category == "bin":
            tint = [(0.2, 0.4, 0.2), (0.3, 0.3, 0.32), (0.15, 0.25, 0.55), (0.45, 0.3, 0.15)][rng.integers(4)]
        elif category in ("blob", "tortoise"):
            tint = tuple(rng.uniform([0.4, 0.3, 0.2], [0.8, 0.6, 0.45]))
        elif category in QUADRUPEDS:
            coats = QUADRUPEDS[category].coats
            tint = tuple(np.clip(np.array(coats[int(rng.integers(len(coats)))]) * rng.uniform(0.9, 1.1, 3), 0, 1))
        elif category == "trolley":  # the handle's plastic: red, blue, green, grey
            tint = [(0.75, 0.1, 0.1), (0.1, 0.25, 0.65), (0.15, 0.5, 0.2), (0.35, 0.35, 0.37)][rng.integers(4)]
        elif category == "pallet":  # pale new spruce to weathered grey
            tint = tuple(np.array([1.0, 0.9, 0.72]) * rng.uniform(0.7, 1.0))
        elif category == "sack":  # white woven polypropylene, brown paper, green feed, jute
            tint = [(0.92, 0.92, 0.9), (0.7, 0.55, 0.38), (0.35, 0.5, 0.3), (0.62, 0.52, 0.36)][rng.integers(4)]
        else:
            tint = tuple(rng.uniform(0.2, 0.95, 3))
        o = Obj(len(self.objects) + 1, category, np.array(size, float), tint, motion, int(rng.integers(1 << 30)),
                tint2, shape=shape)
        if category == "person":
            o.stature, o.riding = float(o.size[1]), riding
            if riding:  # the truth box of a rider: seated height, the length of the bicycle under it
                o.size = np.array([0.55, rider_height(o), 1.0])
        self.objects.append(o)
        return o

    def _build_objects(self, rng: np.random.Generator) -> None:
        T = self.duration
        s_end = self.ego_s[-1]
        lo, hi = self.road.s[0] + 20, self.road.s[-1] - 20
        h = self.half
        # parked cars and static clutter in the parking strips, static unknowns on the centre line
        for side in (-1, 1):
            s = lo
            while s < min(hi, s_end + 250):
                r = rng.random()
                if r < 0.45:
                    cat, gap = "car", rng.uniform(5.5, 8)
                    yaw = (0 if side > 0 else np.pi) + rng.normal(0, 0.03)
                elif r < 0.53:
                    cat, gap, yaw = "cone", rng.uniform(1.5, 3), 0.0
                elif r < 0.57:
                    cat, gap, yaw = "crate", 2.0, rng.uniform(0, 3)
                elif r < 0.61:
                    cat, gap, yaw = "debris", 2.0, rng.uniform(0, 6)
                elif r < 0.68:  # the other unknowns left at the kerb
                    cat = str(rng.choice(["tyre", "barrier", "box", "cart"], p=[0.3, 0.3, 0.25, 0.15]))
                    gap, yaw = rng.uniform(2.0, 3.5), rng.uniform(0, 6.3) if cat != "barrier" else rng.normal(0, 0.1)
                else:
                    cat, gap, yaw = None, rng.uniform(4, 20), 0.0
                if cat:
                    dd = side * (self.lanes * LANE_M + PARKING_M / 2 + rng.uniform(-0.1, 0.1))
                    self._new(rng, cat, Motion("static", s0=s + gap / 2, d=dd, yaw=yaw))
                s += gap
            s = lo
            while s < min(hi, s_end + 250):  # bins, crates, boxes and carts by the buildings
                s += rng.uniform(10, 60)
                cat = str(rng.choice(["bin", "crate", "box", "cart", "barrier"], p=[0.5, 0.15, 0.15, 0.1, 0.1]))
                self._new(rng, cat, Motion("static", s0=s, d=side * (h + SIDEWALK_M - 0.5), yaw=rng.uniform(-0.3, 0.3) + (0 if side > 0 else np.pi)))
        s = lo
        while s < min(hi, s_end + 250):
            s += rng.uniform(30, 120)
            cat = str(rng.choice(["cone", "debris", "crate", "tyre", "box", "branch"]))
            d = rng.normal(0, 0.05) if cat != "branch" else rng.choice([-1, 1]) * (self.lanes * LANE_M - 0.6)
            for j in range(rng.integers(1, 4) if cat == "cone" else 1):
                self._new(rng, cat, Motion("static", s0=s + 2.5 * j, d=d, yaw=rng.uniform(0, 6)))
        # moving traffic: one train of vehicles per lane, all at the lane's speed (never colliding)
        lanes = [(-(LANE_M / 2 + LANE_M * j), -1) for j in range(self.lanes)]
        lanes += [(LANE_M / 2 + LANE_M * j, 1) for j in range(self.lanes) if abs(LANE_M / 2 + LANE_M * j - self.ego_d) > 0.1]
        for d, direction in lanes:
            v = rng.uniform(7, 14) * direction
            s = lo - abs(v) * T if direction > 0 else lo
            stop = hi if direction > 0 else hi + abs(v) * T
            while s < stop:
                cat = rng.choice(["car", "truck", "bus"], p=[0.8, 0.12, 0.08])
                s += rng.uniform(25, 110)
                self._new(rng, str(cat), Motion("lane", s0=s, d=d + rng.normal(0, 0.1), v=v, yaw=0 if v > 0 else np.pi))
        if rng.random() < 0.6:  # a lead vehicle that keeps a varying gap ahead of the ego
            self._new(rng, "car", Motion("follow", d=self.ego_d, gap=(rng.uniform(14, 25), rng.uniform(2, 6), rng.uniform(0.05, 0.2))))
        # cyclists (bicycle + rider) and walkers in bands along the sidewalks
        for side in (-1, 1):
            v = rng.uniform(3.5, 6) * side
            s = lo - abs(v) * T
            while s < hi + abs(v) * T:
                s += rng.uniform(40, 160)
                d = side * (h + 1.1)
                self._new(rng, "bicycle", Motion("lane", s0=s, d=d, v=v, yaw=0 if v > 0 else np.pi))
                self._new(rng, "person", Motion("lane", s0=s, d=d, v=v, yaw=0 if v > 0 else np.pi), riding=True)
            for band, direction in ((2.3, 1), (3.4, -1)):
                v = rng.uniform(1.0, 1.6) * direction
                s = lo - abs(v) * T
                while s < hi + abs(v) * T:
                    s += rng.uniform(12, 60)
                    self._new(rng, "person", Motion("lane", s0=s, d=side * (h + band), v=v, yaw=0 if v > 0 else np.pi))
        for side in (-1, 1):  # tortoises plodding along the outer edge of the sidewalks
            v = rng.uniform(0.25, 0.45) * rng.choice([-1, 1])  # ours: a giant tortoise walks ~0.3 m/s
            s = lo + rng.uniform(0, 150)
            while s < min(hi, s_end + 250):
                self._new(rng, "tortoise", Motion("lane", s0=s, d=side * (h + SIDEWALK_M - 1.4), v=v,
                                                  yaw=0 if v > 0 else np.pi))
                s += rng.uniform(150, 400)
        self._crossings(rng)

    def _more_unknowns(self, rng: np.random.Generator) -> None:
        """Issue 29's kinds in a random world (opt-in): trolleys, pallets and sacks left in the
        parking strips where no parked object stands, trolleys on the sidewalks, deer and boar
        walking or standing at the sidewalks' outer edge and crossing the road like the
        pedestrians (``_crossings``)."""
        s_end = self.ego_s[-1]
        lo, hi = self.road.s[0] + 20, self.road.s[-1] - 20
        strip = [(o.motion.s0, np.sign(o.motion.d)) for o in self.objects
                 if o.motion.kind == "static" and abs(o.motion.d) < self.half]
        for side in (-1, 1):
            s = lo + rng.uniform(0, 40)
            while s < min(hi, s_end + 250):  # ours: one every 25–80 m a side, none within 4 m of a parked object
                cat = str(rng.choice(["trolley", "pallet", "sack"], p=[0.4, 0.3, 0.3]))
                d = side * (self.lanes * LANE_M + PARKING_M / 2 + rng.uniform(-0.3, 0.3))
                yaw = rng.uniform(0, 2 * np.pi)
                if all(abs(s - s0) > 4.0 or sd != side for s0, sd in strip):
                    self._new(rng, cat, Motion("static", s0=s, d=d, yaw=yaw))
                s += rng.uniform(25, 80)
            s = lo + rng.uniform(0, 80)
            while s < min(hi, s_end + 250):  # ours: a trolley left on the sidewalk every 60–150 m
                self._new(rng, "trolley", Motion("static", s0=s, d=side * (self.half + SIDEWALK_M - 1.0),
                                                 yaw=rng.uniform(0, 2 * np.pi)))
                s += rng.uniform(60, 150)
            s = lo + rng.uniform(0, 100)
            while s < min(hi, s_end + 250):  # ours: a deer or boar every 80–200 m walking along the sidewalk's
                # outer edge (a walk: scenarios.ANIMAL_SPEED_MS) or standing there
                cat = str(rng.choice(["deer", "boar"]))
                v = rng.uniform(1.0, 1.5) * rng.choice([-1, 1]) if rng.random() < 0.7 else 0.0
                d = side * (self.half + SIDEWALK_M - 0.8)
                self._new(rng, cat, Motion("lane", s0=s, d=d, v=v, yaw=0 if v >= 0 else np.pi) if v else
                          Motion("static", s0=s, d=d, yaw=rng.uniform(0, 2 * np.pi)))
                s += rng.uniform(80, 200)
        # ours: an animal starts across every 6–15 s (speeds: scenarios.ANIMAL_SPEED_MS's walk), when the
        # road is clear (as for the pedestrians, seldom)
        self._crossings(rng, (("deer", 0.5), ("boar", 0.5)), {"deer": (1.2, 1.6), "boar": (1.0, 1.4)}, (6.0, 15.0))

    def _crossings(self, rng, kinds=(("person", 0.7), ("blob", 0.15), ("tortoise", 0.15)),
                   speeds=None, every_s: tuple[float, float] = (3.0, 9.0)) -> None:
        """Pedestrians, blobs and tortoises (or ``kinds``: (category, share)) crossing the road
        ahead of the ego, one every ``every_s`` seconds, timed to clear its lane."""
        # ours (a tortoise: faster than life, to cross in time; seldom does)
        speeds = speeds or {"person": (1.0, 1.6), "blob": (0.6, 1.4), "tortoise": (0.5, 0.8)}
        t = rng.uniform(0, 4)
        t_axis = np.arange(len(self.ego_s)) * self.dt
        h = self.half
        while t < self.duration:
            cat = str(rng.choice([k for k, _ in kinds], p=[p for _, p in kinds]))
            speed = rng.uniform(*speeds[cat])
            ahead = rng.uniform(20, 60)
            s_c = self.ego_arc(t) + ahead
            direction = rng.choice([-1, 1])
            d0, d1 = -direction * (h + 2.0), direction * (h + 2.0)
            walk_in = 8.0
            t_cross = abs(d1 - d0) / speed
            # the ego lane must be clear before the ego (or a lead car) gets within 12 m of s_c
            t_reach = np.interp(s_c - 30.0, self.ego_s, t_axis) if s_c - 30 < self.ego_s[-1] else self.duration + 99
            frac_ego = (self.ego_d + 1.5 - d0) / (d1 - d0) if direction > 0 else (d0 - (self.ego_d - 1.5)) / (d0 - d1)
            t_start = min(t, t_reach - frac_ego * t_cross - walk_in / speed - 0.5)
            if t_start > -walk_in / speed and self._lanes_clear(s_c, t_start + walk_in / speed, t_cross, d0, d1):
                times = np.array([t_start, t_start + walk_in / speed, t_start + walk_in / speed + t_cross,
                                  t_start + 2 * walk_in / speed + t_cross])
                sign = rng.choice([-1, 1])
                ss = np.array([s_c - sign * walk_in, s_c, s_c, s_c + sign * walk_in])
                dd = np.array([d0, d0, d1, d1])
                self._new(rng, cat, Motion("path", times=times, ss=ss, dd=dd))
            t += rng.uniform(*every_s)

    def _lanes_clear(self, s_c, t0, dur, d0, d1) -> bool:
        for o in self.objects:
            m = o.motion
            if m.kind == "static" and abs(m.s0 - s_c) < 3.5 and min(d0, d1) < m.d < max(d0, d1):
                return False
            if m.kind in ("lane", "follow"):
                for tt in np.linspace(t0, t0 + dur, 12):
                    st = self.state(o, tt)
                    if st is not None and abs(st[3] - s_c) < 8 + o.size[2] / 2 and min(d0, d1) <= m.d <= max(d0, d1):
                        return False
        return True

    def nearby(self) -> Nearby:
        """The index of what is near the ego (``nearby.py``), made once the world is built."""
        if self._nearby is None or not self._nearby.fits(self.static_rows[:, R_SKEY], self.objects):
            self._nearby = Nearby(self.static_rows[:, R_SKEY], self.objects)
        return self._nearby

    def state(self, o: Obj, t: float):
        """(position (3,) map, yaw (map), distance walked, s) or None when the object is absent."""
        m = o.motion
        if m.kind == "static":
            s, d, walked = m.s0, m.d, 0.0
        elif m.kind == "lane":
            s, d, walked = m.s0 + m.v * t, m.d, abs(m.v) * t
        elif m.kind == "follow":
            g = m.gap
            s = self.ego_arc(t) + g[0] + g[1] * np.sin(g[2] * t)
            d, walked = m.d, 0.0
        elif m.kind == "speed":
            s, d = m.s0 + speed_arc(m.times, m.vs, t), m.d
            walked = abs(s - m.s0)
        else:
            if t < m.times[0] or t > m.times[-1]:
                return None
            s = float(np.interp(t, m.times, m.ss))
            d = float(np.interp(t, m.times, m.dd))
            seg = min(np.searchsorted(m.times, t, side="right") - 1, len(m.times) - 2)
            ds_, dd_ = m.ss[seg + 1] - m.ss[seg], m.dd[seg + 1] - m.dd[seg]
            _, th, tan, nrm = self.road.frame(s)
            vec = ds_ * tan + dd_ * nrm
            yaw = float(np.arctan2(vec[0], vec[2]))
            cum = np.concatenate([[0], np.cumsum(np.hypot(np.diff(m.ss), np.diff(m.dd)))])
            walked = float(np.interp(t, m.times, cum))
            return self.road.point(s, d, self._ground(d)), yaw, walked, s
        if not (self.road.s[0] < s < self.road.s[-1]):
            return None
        _, th, _, _ = self.road.frame(s)
        return self.road.point(s, d, self._ground(d)), float(th) + m.yaw, walked, s

    def _ground(self, d: float) -> float:
        """Height (y, down) of the surface an object at lateral offset d stands on: the sidewalk beyond the curb."""
        return -CURB_M if abs(d) > self.half else 0.0


# --------------------------------------------------------------------------- frame assembly


def transform_faces(verts: np.ndarray, rows: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Faces moved by x → R_f x + t_f; ``R`` (3,3) or one per face (F,3,3), ``t`` (3,) or (F,3)."""
    R = np.broadcast_to(R, (len(verts), 3, 3))
    t = np.broadcast_to(t, (len(verts), 3))
    Rt = R.transpose(0, 2, 1)  # x @ Rᵀ by columns: cheaper than einsum for 3×3 blocks
    v = t[:, None, :] + verts[:, :, 0:1] * Rt[:, None, 0] + verts[:, :, 1:2] * Rt[:, None, 1] + verts[:, :, 2:3] * Rt[:, None, 2]
    r = rows.copy()
    for c in (R_N, R_U, R_V, R_O):
        x = rows[:, c : c + 3]
        r[:, c : c + 3] = x[:, 0:1] * Rt[:, 0] + x[:, 1:2] * Rt[:, 1] + x[:, 2:3] * Rt[:, 2]
    r[:, R_O : R_O + 3] += t
    return v, r


def _in_view(M: np.ndarray, centres: np.ndarray, radii: np.ndarray, view: tuple[float, float, float]) -> np.ndarray:
    """Which spheres (map frame) may show in a camera at pose M (camera to map) whose image spans
    |x/z| ≤ view[0], |y/z| ≤ view[1], or in one moved sideways by up to view[2] (the stereo baseline)."""
    tx, ty, margin = view
    P = (centres - M[:3, 3]) @ M[:3, :3]  # map → camera frame
    r = radii + margin
    return ((P[:, 2] > -r) & (np.abs(P[:, 0]) - P[:, 2] * tx <= r * math.hypot(1, tx))
            & (np.abs(P[:, 1]) - P[:, 2] * ty <= r * math.hypot(1, ty)))


def frame_faces(scene: Scene, t: float, view: tuple[float, float, float] | None = None):
    """All faces near the ego at time t (map frame) and the visible-candidate objects' states.
    ``view`` (tan of the half field of view across and down, sideways margin): leave out the
    faces and objects no camera of the rig can see (none are left out without it)."""
    s_ego = scene.ego_arc(t)
    near = scene.nearby()
    sel = near.static(s_ego - VIEW_BEHIND_M, s_ego + VIEW_AHEAD_M)
    M = scene.camera_map(t)
    if view is not None:
        sel = sel[_in_view(M, scene.static_centres[sel], scene.static_radii[sel], view)]
    verts = [scene.static_verts[sel]]
    rows = [scene.static_rows[sel]]
    # terrain: one big square below the road, texture anchored at the map origin
    c = M[:3, 3]
    g = np.array([round(c[0] / 16) * 16, GROUND_DROP_M, round(c[2] / 16) * 16])
    r = 400.0
    fl = FaceList(scene.atlas)
    fl.add([g + [-r, 0, -r], g + [r, 0, -r], g + [r, 0, r], g + [-r, 0, r]], np.array([0, -1.0, 0]),
           np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 0, 1.0]), "grass")
    v, rw = fl.arrays()
    verts.append(v)
    rows.append(rw)
    states = {}
    # objects: local faces and, per face, which rigid motion (object pose ∘ body-part pose) moves it
    local_v, local_r, motion_of_face, Rs, ts = [], [], [], [], []
    for o in near.candidates(t, s_ego - VIEW_BEHIND_M - 20, s_ego + VIEW_AHEAD_M):  # cheap test, then the exact state
        st = scene.state(o, t)
        if st is None or not (s_ego - VIEW_BEHIND_M - 20 < st[3] < s_ego + VIEW_AHEAD_M):
            continue
        if o.faces is None:
            o.faces = build_mesh(o, scene.atlas)
        keep_mesh(scene.meshed, o)
        pos, yaw, walked, _ = st
        if view is not None and not _in_view(M, (pos - [0.0, o.size[1] / 2, 0.0])[None],
                                             np.array([0.5 * float(np.linalg.norm(o.size)) + VIEW_SLACK_M]), view)[0]:
            continue
        Ro = rot_y(yaw)
        lv, lr = o.faces
        if o.category in ANIMATED:
            Rp, tp = part_poses(o, walked)
            Rs.append(Ro @ Rp)
            ts.append(tp @ Ro.T + pos)
            motion_of_face.append(lr[:, R_PART].astype(int))
        else:
            Rs.append(Ro[None])
            ts.append(pos[None])
            motion_of_face.append(np.zeros(len(lr), int))
        local_v.append(lv)
        local_r.append(lr)
        states[o.track_id] = (o, pos, yaw)
    if local_v:
        first = np.cumsum([0] + [len(x) for x in Rs[:-1]])  # each object's first motion
        idx = np.concatenate([mf + k0 for mf, k0 in zip(motion_of_face, first)])
        v, rw = transform_faces(np.concatenate(local_v), np.concatenate(local_r), np.concatenate(Rs)[idx], np.concatenate(ts)[idx])
        verts.append(v)
        rows.append(rw)
    return np.concatenate(verts), np.concatenate(rows), states
