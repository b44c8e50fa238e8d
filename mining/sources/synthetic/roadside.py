"""Roadside clutter for staged scenarios: a grass verge with tufts, a post-and-rail fence with
gaps, and a clipped hedge behind it (scenario ``verge``).

All of it is background: static faces with object id 0, so it shows in the images and the
depth map but has no ``ObjectTruth`` (the miner should not keep it). Each piece is keyed by
its arc length (``R_SKEY``) so the view window culls it like the rest of the structure, and
its texture is anchored to the arc length, so it runs on without seams from piece to piece.
The layout across the road (one side, offsets from the curb and the sidewalk's outer edge):

    curb │ verge (grass, raised, tufts) │ footpath │ fence (posts, two rails) │ hedge │ lots
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mining.sources.synthetic.faces import DOWN, R_SKEY, FaceList, rot_y
from mining.sources.synthetic.scene import CURB_M, GROUND_DROP_M, SIDEWALK_M, Scene

VERGE_W_M = 2.4  # ours: grass strip between the curb and the footpath (German residential streets: 1.5–3 m)
VERGE_RAISE_M = 0.05  # ours: the turf stands this far above the sidewalk slab it covers ("slightly raised")
VERGE_STEP_M = 4.0  # ours: verge pieces along the road (chord error on a 250 m bend: 8 mm)
TUFTS_PER_M2 = 1.3  # ours: clumps of longer grass on the verge
TUFT_H_M = (0.06, 0.22)  # ours: a tuft's height, uniform range
TUFT_R_M = (0.1, 0.25)  # ours: a tuft's base radius, uniform range
TUFT_SIDES = 5  # ours: faces around a tuft (irregular: random angles and radii)
FENCE_BACK_M = 0.3  # ours: the fence line behind the sidewalk's outer edge
FENCE_H_M = 1.1  # ours: post height above the ground (a post-and-rail paddock fence is 1.0–1.3 m)
POST_M = 0.09  # ours: square post section (a 9 × 9 cm sawn post)
POST_PITCH_M = (1.9, 2.2)  # ours: post spacing, uniform range (rails come in 2 m lengths)
RAILS_M = (0.4, 0.88)  # ours: rail heights (centre) above the ground
RAIL_M = (0.1, 0.04)  # ours: rail section, height × thickness
RAIL_MISSING = 0.12  # ours: share of fence bays with no rails (broken or a gate left open)
HEDGE_BACK_M = 0.75  # ours: the hedge's road face behind the sidewalk's outer edge (0.45 m behind the fence)
HEDGE_DEPTH_M = 1.0  # ours: hedge thickness (a clipped privet or beech hedge: 0.6–1.2 m)
HEDGE_H_M = (1.25, 1.85)  # ours: the hedge top's smooth swing, min–max (1–2 m tall)
HEDGE_STEP_M = 0.8  # ours: hedge pieces along the road; each node has its own height and face offset
HEDGE_JITTER_M = (0.07, 0.05)  # ours: per-node sigma of the top height and of the face offset (uneven clipping)
RUN_M = (22.0, 45.0)  # ours: length of one stretch of fence and hedge, uniform range
GATE_M = (3.0, 4.5)  # ours: the gap (a gateway or driveway) between stretches, uniform range
BACK_M = 3.5  # ours: the side's lots (buildings, trees) move this far back to make room for fence and hedge


@dataclass(frozen=True)
class RoadsideLayout:
    """Lateral offsets (from the centreline, on the right) of the clutter in one scene."""

    curb: float  # the curb: the verge's road edge
    verge: float  # the verge's far edge (the footpath starts there)
    fence: float  # the fence line (posts' centre)
    hedge: float  # the hedge's road face (nominal, before the per-node jitter)
    hedge_back: float  # the hedge's far face


def layout(scene: Scene) -> RoadsideLayout:
    """Where the verge, fence and hedge stand across the road in ``scene`` (right side)."""
    front = scene.half + SIDEWALK_M
    return RoadsideLayout(scene.half, scene.half + VERGE_W_M, front + FENCE_BACK_M, front + HEDGE_BACK_M,
                          front + HEDGE_BACK_M + HEDGE_DEPTH_M)


class _Keyed:
    """A face list whose faces remember the arc length they belong to (for the view window)."""

    def __init__(self, scene: Scene):
        self.fl = FaceList(scene.atlas)
        self.spans: list[tuple[int, float]] = []  # (faces so far, arc length of the faces since the last)

    def key(self, s: float) -> None:
        """The faces added since the last call belong to arc length ``s``."""
        self.spans.append((len(self.fl.rows), s))

    def into(self, scene: Scene) -> None:
        v, r = self.fl.arrays()
        start = 0
        for stop, s in self.spans:
            r[start:stop, R_SKEY] = s
            start = stop
        keyed = FaceList(scene.atlas)
        keyed.extend(v, r)
        scene.add_static(keyed)


def _runs(rng: np.random.Generator, s_from: float, s_to: float) -> list[tuple[float, float]]:
    """Stretches [a, b) of fence and hedge, separated by gateways."""
    out, s = [], s_from
    while s < s_to:
        b = s + rng.uniform(*RUN_M)
        out.append((s, b))
        s = b + rng.uniform(*GATE_M)
    return out


def build_roadside(scene: Scene, rng: np.random.Generator, s_from: float, s_to: float) -> RoadsideLayout:
    """Verge, fence and hedge on the right side over arc lengths [s_from, s_to), added to the
    scene's static structure (the scenario sets ``right_setback_m`` so the lots stand clear)."""
    lay = layout(scene)
    k = _Keyed(scene)
    _verge(k, scene, rng, lay, s_from, s_to)
    for a, b in _runs(rng, s_from, s_to):
        _fence(k, scene, rng, lay, a, b)
        _hedge(k, scene, rng, lay, a, b)
    k.into(scene)
    return lay


def _verge(k: _Keyed, scene: Scene, rng, lay: RoadsideLayout, s_from: float, s_to: float) -> None:
    road = scene.road
    top = -(CURB_M + VERGE_RAISE_M)
    up = np.array([0.0, -1.0, 0.0])
    tint = tuple(rng.uniform(0.9, 1.05, 3))
    period = scene.atlas.tiles["lawn"].metres_w  # the texture's repeat: anchored to the arc length
    for a in np.arange(s_from, s_to, VERGE_STEP_M):
        b = a + VERGE_STEP_M
        pa0, pb0 = road.point(a, lay.curb, top), road.point(b, lay.curb, top)
        pa1, pb1 = road.point(a, lay.verge, top), road.point(b, lay.verge, top)
        chord = (pb0 - pa0) / np.linalg.norm(pb0 - pa0)
        right = np.array([chord[2], 0.0, -chord[0]])
        k.fl.add([pa0, pb0, pb1, pa1], up, pa0, chord, right, "lawn", tint, offset=(a % period, 0.0))
        lift = np.array([0.0, VERGE_RAISE_M, 0.0])  # the turf's edge above the curb
        k.fl.add([pa0 + lift, pb0 + lift, pb0, pa0], -right, pa0, chord, DOWN, "lawn", tint, offset=(a % period, 0.0))
        k.key(a + VERGE_STEP_M / 2)
        # tufts: low clumps of longer grass standing on the turf (irregular five-sided pyramids)
        n = rng.poisson(TUFTS_PER_M2 * VERGE_STEP_M * VERGE_W_M)
        if n == 0:
            continue
        ts, td = rng.uniform(a, b, n), rng.uniform(lay.curb + 0.15, lay.verge - 0.15, n)  # clear of the edges
        hgt, rad, rot = rng.uniform(*TUFT_H_M, n), rng.uniform(*TUFT_R_M, n), rng.uniform(0, 2 * np.pi, n)
        ang = rot[:, None] + np.sort(rng.uniform(0, 2 * np.pi, (n, TUFT_SIDES)), 1)
        r = rad[:, None] * rng.uniform(0.6, 1.0, (n, TUFT_SIDES))  # ragged: each corner its own reach
        lean = rng.normal(0, 0.3, (n, 2)) * rad[:, None]  # the top leans a little off the centre
        shade = np.array([0.0, 0.95, 0.7]) * rng.uniform(0.6, 0.95, (n, 1))  # darker than the turf: longer blades
        shade[:, 0] = rng.uniform(0.75, 1.0, n) * shade[:, 2] / 0.7  # some yellower than others
        base = road.point(ts, td, np.full(n, top + 0.005))  # just above the turf: no z-fight at its foot
        ring = base[:, None] + np.stack([r * np.cos(ang), np.zeros_like(r), r * np.sin(ang)], 2)
        apex = base + np.stack([lean[:, 0], -hgt, lean[:, 1]], 1)
        centre = (ring.mean(1) + apex) / 2
        nxt = np.roll(ring, -1, 1)
        out = (ring + nxt + apex[:, None]) / 3 - centre[:, None]
        for j in range(n):
            for i in range(TUFT_SIDES):
                k.fl.poly((ring[j, i], nxt[j, i], apex[j]), out[j, i], "lawn", tuple(shade[j]),
                          u_hint=nxt[j, i] - ring[j, i])
        k.key(a + VERGE_STEP_M / 2)


def _fence(k: _Keyed, scene: Scene, rng, lay: RoadsideLayout, a: float, b: float) -> None:
    road = scene.road
    ground = GROUND_DROP_M  # beyond the sidewalk the terrain lies here (y down)
    tint = tuple(rng.uniform(0.85, 1.0, 3))
    posts = [a]
    while posts[-1] + POST_PITCH_M[1] < b:
        posts.append(posts[-1] + rng.uniform(*POST_PITCH_M))
    for s in posts:
        th = float(road.frame(s)[1])
        c = road.point(s, lay.fence, ground - FENCE_H_M / 2)
        k.fl.box(c, (POST_M / 2, FENCE_H_M / 2, POST_M / 2), rot_y(th), {"all": "timber"}, tint, skip=("bottom",),
                 offset=tuple(rng.uniform(0, 0.5, 2)))
        k.key(s)
    rail_d = lay.fence - POST_M / 2 - RAIL_M[1] / 2  # nailed to the posts' road side
    for s0, s1 in zip(posts[:-1], posts[1:]):
        if rng.random() < RAIL_MISSING:
            continue
        for hgt in RAILS_M:
            p0, p1 = road.point(s0, rail_d, ground - hgt), road.point(s1, rail_d, ground - hgt)
            k.fl.tube(p0, p1, RAIL_M[0] / 2, "timber", tint, across=(0.0, 1.0, 0.0), half_d=RAIL_M[1] / 2)
        k.key((s0 + s1) / 2)


def _hedge(k: _Keyed, scene: Scene, rng, lay: RoadsideLayout, a: float, b: float) -> None:
    """One stretch of hedge: pieces between nodes, each node with its own clipped height and face
    offset (an uneven top, a face that bulges a little), closed by end faces at the gateways."""
    road = scene.road
    ground = GROUND_DROP_M
    n = max(2, int(round((b - a) / HEDGE_STEP_M)) + 1)
    ss = np.linspace(a, b, n)
    lo, hi = HEDGE_H_M
    phase, wave = rng.uniform(0, 2 * np.pi, 2), rng.uniform([9.0, 3.0], [16.0, 5.0])  # ours: swells 9–16 m and 3–5 m long
    # the long swell dominates, the short one roughens it; weights sum to 1 so the swing spans HEDGE_H_M
    swing = 0.65 * np.sin(2 * np.pi * ss / wave[0] + phase[0]) + 0.35 * np.sin(2 * np.pi * ss / wave[1] + phase[1])
    height = (lo + hi) / 2 + (hi - lo) / 2 * swing + rng.normal(0, HEDGE_JITTER_M[0], n)
    face = lay.hedge + rng.normal(0, HEDGE_JITTER_M[1], n)
    tint = tuple(rng.uniform(0.85, 1.05, 3))
    period = scene.atlas.tiles["hedge"].metres_w  # the texture's repeat: anchored to the arc length
    y0 = ground
    for i in range(n - 1):
        s0, s1 = ss[i], ss[i + 1]
        f0, f1 = road.point(s0, face[i], y0), road.point(s1, face[i + 1], y0)
        t0, t1 = road.point(s0, face[i], y0 - height[i]), road.point(s1, face[i + 1], y0 - height[i + 1])
        r0, r1 = road.point(s0, lay.hedge_back, y0 - height[i]), road.point(s1, lay.hedge_back, y0 - height[i + 1])
        chord = (f1 - f0) / np.linalg.norm(f1 - f0)
        right = np.array([chord[2], 0.0, -chord[0]])
        top_ref = road.point(s0, face[i], y0 - hi - 0.5)  # v runs down from a fixed height: no seam between pieces
        k.fl.add([f0, f1, t1, t0], -right, top_ref, chord, DOWN, "hedge", tint, offset=(s0 % period, 0.0))
        n_top = np.cross(t1 - t0, r0 - t0)
        n_top = n_top / np.linalg.norm(n_top) * (1 if n_top[1] < 0 else -1)  # up (y down)
        k.fl.add([t0, t1, r1, r0], n_top, t0, (t1 - t0) / np.linalg.norm(t1 - t0), right, "hedge", tint,
                 offset=(s0 % period, 0.0))
        k.fl.add([r0 + [0, height[i], 0], r1 + [0, height[i + 1], 0], r1, r0], right, r0, chord, DOWN, "hedge",
                 tint, offset=(s0 % period, 0.0))
        k.key((s0 + s1) / 2)
    for s, i, sign in ((a, 0, -1.0), (b, n - 1, 1.0)):  # the ends at the gateways
        tan = road.frame(s)[2]
        f, t = road.point(s, face[i], y0), road.point(s, face[i], y0 - height[i])
        r, rb = road.point(s, lay.hedge_back, y0 - height[i]), road.point(s, lay.hedge_back, y0)
        right = np.array([tan[2], 0.0, -tan[0]])
        k.fl.add([f, rb, r, t], sign * tan, t, right, DOWN, "hedge", tint)
        k.key(s)
