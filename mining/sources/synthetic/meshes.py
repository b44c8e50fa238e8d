"""Object meshes of the synthetic world: cars, trucks, buses, people, bicycles and the unknown kinds.

Each object is planar faces in its own frame (origin on the ground below its centre, x right,
y down, z forward), built once from its seed; body parts that move (legs, arms) carry a
part index and ``part_poses`` moves them rigidly each frame.

Cars follow a body type (``CAR_SHAPES``: hatchback, saloon, estate, SUV, van). The lower body
and the glasshouse are convex solids, each the intersection of half-spaces (``solid``): a
side profile (bumpers, nose, bonnet, deck, tailgate), a cross section (the side tucking in
below the waist, a rounded shoulder; the glasshouse narrowing to a roof with rounded edges)
and a plan outline with rounded corners. Each bounding plane is one face, so light falls on
each facet at its own angle and a curved panel shades smoothly in steps; paint also reflects
the sky, more where it faces up. Glass is dark and reflective with black pillars and a
painted roof rail; head and tail lamps wrap round the corners; plates, mirrors, a rear
bumper, wheels with rims in dark arches and a contact shadow complete it. A body type is
built once per atlas (three variants) and stretched to each car's size: planes stay planes
and textures follow (the texture axes take the inverse stretch).

People have a torso, neck, a head with hair, and two-segment arms and legs (hip, knee,
shoulder, elbow) that walk with the lowest foot on the ground, stand, or pedal a bicycle
(leg and arm angles solved for pedal and handlebar); clothing cut (sleeves, skirt, coat,
backpack), clothes, skin and hair vary per person, from templates scaled to the stature.

Shadows are faces of the object's mesh with track id 0: they move with it but are not
part of its truth mask (a detector's box does not include the shadow either).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from itertools import pairwise
from typing import TYPE_CHECKING

import numpy as np

from mining.sources.synthetic.faces import R_N, R_O, R_OBJ, R_TINT, R_U, R_V, FaceList, rot_x
from mining.sources.synthetic.textures import Atlas

if TYPE_CHECKING:
    from mining.sources.synthetic.scene import Obj

SHADOW_LIFT_M = 0.015  # ours: the contact shadow lies this far above the ground (clear of the road in depth)
BUMPER_M = 0.04  # ours: how far the rear bumper stands out of the tailgate
TUCK_M = 0.045  # ours: how far a car's side tucks in from its widest line down to the sill
OVERLAY_M = 0.005  # ours: lights, plates, arches and wheels sit this far in front of the panel they are on


# --------------------------------------------------------------------------- shapes (facts)


@dataclass(frozen=True)
class CarShape:
    """A car body type: size ranges and the side profile, metres (z from the bumpers)."""

    name: str
    weight: float  # share in traffic
    length: tuple[float, float]
    width: tuple[float, float]
    height: tuple[float, float]
    clearance: float  # body bottom above the ground
    wheel_d: float  # tyre outer diameter
    belt: float  # belt line (window bottom) as a share of the height
    overhang: tuple[float, float]  # front and rear bumper to axle
    bonnet: float  # front bumper to the windscreen base
    screen: float  # windscreen base to the roof's front, along the car
    roof_rear: float  # rear bumper to the roof's end
    glass_rear: float  # rear bumper to the rear window's base (a saloon's boot)
    tumble: float  # the glasshouse narrows by this much per side at the roof
    side_glass: float  # share of the glasshouse side that is glass (a van's is mostly panel)


# Shares in traffic (ours): German traffic around KITTI's recording (2011) — compact hatchbacks, saloons
# and estates dominate, SUVs are fewer; KITTI's labels hold about one Van per ten Car + Van.
CAR_SHAPES = (
    # ours: typical European compact hatchback (VW Golf VIII: 4.28 × 1.79 × 1.46 m, wheelbase 2.62 m, tyre 205/55 R16 ≈ 0.63 m)
    CarShape("hatchback", 0.32, (3.9, 4.3), (1.70, 1.80), (1.42, 1.52), 0.14, 0.63, 0.63, (0.86, 0.72), 1.02, 0.88,
             0.42, 0.10, 0.17, 1.0),
    # ours: mid-size saloon (VW Passat B8: 4.77 × 1.83 × 1.46 m, wheelbase 2.79 m, tyre 215/55 R17 ≈ 0.67 m)
    CarShape("sedan", 0.22, (4.5, 4.9), (1.78, 1.86), (1.42, 1.50), 0.14, 0.66, 0.62, (0.92, 1.04), 1.18, 0.82,
             1.22, 0.62, 0.17, 1.0),
    # ours: estate of the same (Passat Variant: 4.77 × 1.83 × 1.51 m)
    CarShape("estate", 0.21, (4.5, 4.9), (1.78, 1.86), (1.46, 1.54), 0.14, 0.66, 0.61, (0.92, 1.04), 1.15, 0.82,
             0.2, 0.08, 0.16, 1.0),
    # ours: compact SUV (VW Tiguan II: 4.51 × 1.84 × 1.67 m, wheelbase 2.68 m, tyre 235/55 R18 ≈ 0.72 m)
    CarShape("suv", 0.15, (4.3, 4.7), (1.82, 1.9), (1.6, 1.72), 0.19, 0.72, 0.6, (0.9, 0.93), 1.1, 0.78,
             0.36, 0.12, 0.19, 1.0),
    # ours: panel van (VW Transporter T6: 4.90 × 1.90 × 1.97 m, wheelbase 3.0 m, tyre 215/65 R16 ≈ 0.69 m)
    CarShape("van", 0.1, (4.8, 5.3), (1.88, 2.0), (1.9, 2.1), 0.18, 0.69, 0.5, (0.96, 0.96), 0.62, 0.62,
             0.06, 0.05, 0.06, 0.3),
)
CAR_WEIGHTS = np.array([c.weight for c in CAR_SHAPES]) / sum(c.weight for c in CAR_SHAPES)
# ours: body colours by their rough share in European traffic (white, greys, black, silver dominate)
CAR_COLOURS = (
    ((0.92, 0.92, 0.91), 0.2), ((0.08, 0.08, 0.09), 0.15), ((0.42, 0.43, 0.45), 0.15), ((0.68, 0.69, 0.71), 0.14),
    ((0.12, 0.2, 0.48), 0.09), ((0.6, 0.06, 0.06), 0.08), ((0.45, 0.58, 0.72), 0.04), ((0.12, 0.24, 0.15), 0.03),
    ((0.72, 0.64, 0.5), 0.03), ((0.32, 0.2, 0.12), 0.03), ((0.85, 0.68, 0.1), 0.03), ((0.8, 0.34, 0.08), 0.03),
)
RIM_TINTS = ((1.0, 1.0, 1.0), (0.85, 0.85, 0.88), (0.45, 0.45, 0.47), (0.25, 0.25, 0.26))  # ours: silver, grey, dark, black rims
PLATE_M = (0.52, 0.11)  # EU number plate, 520 × 110 mm
TRUCK_WHEEL_D = 1.07  # ours: 315/80 R22.5 truck tyre
BUS_WHEEL_D = 1.0  # ours: 275/70 R22.5 bus tyre

# People, as shares of the stature (ours, after Drillis & Contini 1966's segment proportions)
HIP_H, KNEE_H, ANKLE_H, SHOULDER_H, CHIN_H = 0.53, 0.285, 0.039, 0.818, 0.87
UPPER_ARM, FOREARM, HAND, FOOT = 0.186, 0.146, 0.09, 0.152
SHOULDER_X, HIP_X = 0.118, 0.05  # joint offsets from the midline
# bicycle (ours: a city bike with 28" wheels, ~0.70 m tyres, wheelbase 1.08 m, 170 mm cranks)
BIKE_WHEEL_R, BIKE_WHEELBASE, BIKE_BB_H, CRANK_M = 0.35, 1.08, 0.28, 0.17
SADDLE_Z, BAR_Z, BAR_H = -0.24, 0.36, 1.02  # saddle and handlebar along the bike, bar height
PEDAL_M_PER_TURN = 5.5  # ours: metres travelled per crank turn (a 2.5 gear ratio on 2.2 m wheels)

SKIN = ((0.95, 0.78, 0.65), (0.87, 0.66, 0.5), (0.7, 0.5, 0.36), (0.5, 0.34, 0.24), (0.33, 0.22, 0.15))
HAIR = ((0.08, 0.06, 0.05), (0.22, 0.14, 0.08), (0.4, 0.28, 0.16), (0.75, 0.62, 0.38), (0.6, 0.6, 0.6))
CLOTHES = ((0.1, 0.1, 0.12), (0.85, 0.85, 0.85), (0.15, 0.22, 0.45), (0.55, 0.1, 0.1), (0.3, 0.35, 0.25),
           (0.45, 0.45, 0.47), (0.75, 0.6, 0.4), (0.2, 0.45, 0.6), (0.85, 0.7, 0.2), (0.5, 0.25, 0.45))
TROUSERS = ((0.15, 0.2, 0.38), (0.1, 0.1, 0.11), (0.3, 0.3, 0.32), (0.55, 0.48, 0.36), (0.22, 0.25, 0.45))


def P(x: float, height: float, z: float) -> np.ndarray:
    """A point ``height`` above the ground (y points down)."""
    return np.array([x, -height, z], float)


def _shadow(fl: FaceList, half_w: float, half_l: float, lift: float = SHADOW_LIFT_M) -> None:
    y = -lift
    fl.poly([[-half_w, y, -half_l], [half_w, y, -half_l], [half_w, y, half_l], [-half_w, y, half_l]],
            (0, -1, 0), "shadow", obj=0, u_hint=(1, 0, 0), own=True)


def clip_z(pts: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """A convex polygon cut to lo ≤ z ≤ hi (Sutherland–Hodgman, two planes; plain floats: polygons are small)."""
    arr = np.asarray(pts, float)
    if len(arr) and lo <= arr[:, 2].min() and arr[:, 2].max() <= hi:
        return arr
    poly = arr.tolist()
    for sign, bound in ((1.0, lo), (-1.0, hi)):
        out = []
        n = len(poly)
        for i in range(n):
            a, b = poly[i], poly[(i + 1) % n]
            ina, inb = sign * (a[2] - bound) >= 0, sign * (b[2] - bound) >= 0
            if ina:
                out.append(a)
            if ina != inb:
                t = (bound - a[2]) / (b[2] - a[2])
                out.append([a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), bound])
        poly = out
        if len(poly) < 3:
            return np.zeros((0, 3))
    return np.array(poly)


def wheel(fl: FaceList, side: int, x_out: float, z: float, r: float, width: float, rim, obj: int, part: int = 0,
          arch_x: float | None = None, arch_bottom: float = 0.0, n: int = 8, tread: str = "lower") -> None:
    """A wheel on the ``side`` (±1) whose outer face lies at x = side·x_out: the side disc (tyre and
    rim), the tread (``tread``: "lower" — the rest is inside the arch —, "full" or "none"), and
    (``arch_x``) the dark wheel arch behind it on the body."""
    ang = (np.arange(n) + 0.5) * 2 * np.pi / n
    ring = np.stack([np.full(n, side * x_out), -r + r * np.cos(ang), z + r * np.sin(ang)], 1)
    fl.poly(ring, (side, 0, 0), "wheel", rim, obj, part, u_hint=(0, 0, 1))
    inner = ring - np.array([side * width, 0, 0])
    for i in range(n if tread != "none" else 0):
        j = (i + 1) % n
        mid = 0.5 * (ang[i] + ang[j]) if j else 0.5 * (ang[i] + ang[j] + 2 * np.pi)
        if tread == "lower" and np.cos(mid) < -0.4:  # the top of the tread is inside the arch
            continue
        fl.poly([ring[i], ring[j], inner[j], inner[i]], (0, np.cos(mid), np.sin(mid)), "rubber", (1, 1, 1), obj, part)
    if arch_x is not None:
        R = r + 0.05
        a = np.radians([0, 40, 90, 140, 180])
        pts = [P(side * arch_x, arch_bottom, z + R)]
        pts += [P(side * arch_x, r + R * np.sin(t), z + R * np.cos(t)) for t in a]
        pts += [P(side * arch_x, arch_bottom, z - R)]
        fl.poly(pts, (side, 0, 0), "rubber", (1, 1, 1), obj, part, u_hint=(0, 0, 1))


# --------------------------------------------------------------------------- vehicles


def solid(planes: list[tuple[np.ndarray, float]], inside: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """The faces of the convex solid {p : n·p ≤ d for every (n, d)}: for each plane that bounds it,
    its polygon (vertices in order). ``inside`` is a point strictly inside."""
    from scipy.spatial import HalfspaceIntersection

    N = np.array([n for n, _ in planes], float)
    norm = np.linalg.norm(N, axis=1)
    N, D = N / norm[:, None], np.array([d for _, d in planes], float) / norm
    verts = HalfspaceIntersection(np.column_stack([N, -D]), np.asarray(inside, float)).intersections
    verts = np.unique(np.round(verts, 7), axis=0)
    incident = np.abs(verts @ N.T - D) < 1e-6  # (V, K)
    faces = []
    for k in np.flatnonzero(incident.sum(0) >= 3):
        on = verts[incident[:, k]]
        c = on.mean(0)
        rel = on - c
        e1 = rel[np.argmax(np.einsum("ij,ij->i", rel, rel))]
        n = N[k]
        e2 = np.array([n[1] * e1[2] - n[2] * e1[1], n[2] * e1[0] - n[0] * e1[2], n[0] * e1[1] - n[1] * e1[0]])
        faces.append((int(k), on[np.argsort(np.arctan2(rel @ e2, rel @ e1))]))
    return faces


def clip_axis(pts: np.ndarray, axis: int, lo: float, hi: float) -> np.ndarray:
    """A convex polygon cut to lo ≤ coordinate ``axis`` ≤ hi."""
    order = [a for a in range(3) if a != axis] + [axis]
    q = clip_z(np.asarray(pts, float)[:, order], lo, hi)
    return q[:, np.argsort(order)] if len(q) else q


def clip_y(pts: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """A convex polygon cut to heights lo ≤ height ≤ hi."""
    p = np.asarray(pts, float)[:, [0, 2, 1]] * [1, 1, -1]  # height as the third axis
    q = clip_z(p, lo, hi)
    return q[:, [0, 2, 1]] * [1, -1, 1] if len(q) else q


def _line_plane(a: tuple[float, float], b: tuple[float, float], axes: str, sign: float = 1.0) -> tuple[np.ndarray, float]:
    """The plane through the 2D line a→b (coordinates on ``axes``: "zh" side profile, "xh" cross
    section, "xz" plan), extruded along the third axis, facing right of a→b (× ``sign``)."""
    (a0, a1), (b0, b1) = a, b
    n2 = np.array([b1 - a1, -(b0 - a0)]) * sign  # right-hand normal of the direction
    n = np.zeros(3)
    for coord, val in zip(axes, n2):
        if coord == "x":
            n[0] = val
        elif coord == "z":
            n[2] = val
        else:  # height: y points down
            n[1] = -val
    p = np.zeros(3)
    for coord, val in zip(axes, a):
        p[{"x": 0, "z": 2, "h": 1}[coord]] = val if coord != "h" else -val
    return n, float(n @ p)


def _bevel(a, corner, b, axes: str, sign: float, k: int) -> list[tuple[np.ndarray, float]]:
    """A rounded edge as ``k`` planes: chords of the quadratic Bézier from ``a`` (on one face)
    over ``corner`` to ``b`` (on the other), tangent to both faces (2D points on ``axes``)."""
    a, c, b = (np.asarray(x, float) for x in (a, corner, b))
    t = np.linspace(0, 1, k + 1)[:, None]
    pts = (1 - t) ** 2 * a + 2 * (1 - t) * t * c + t * t * b
    return [_line_plane(tuple(p), tuple(q), axes, sign) for p, q in pairwise(pts)]


SKY_SHEEN = np.array([0.78, 0.82, 0.9])  # ours: the colour a car's clear coat reflects from the sky


def _car_body(fl: FaceList, sh: CarShape, w: float, h: float, l: float, rng: np.random.Generator) -> float:
    """A car body of type ``sh`` and size (w, h, l): lower body and glasshouse as two convex solids
    (each the intersection of a side profile, a cross section and a plan outline) with lamps.
    Paint faces carry the tint PAINT_MARK, glass GLASS_MARK (``car_faces`` colours them);
    returns the windscreen base's z (the mirrors go there)."""
    k, paint = 0, PAINT_MARK
    hw, zf, zr = w / 2, l / 2, -l / 2

    def put(pts, n, mat, tint, *args, **kw):
        fl.poly(pts, n, mat, GLASS_MARK if mat == "glass" else tint, *args, **kw)
    clr = sh.clearance
    belt = sh.belt * h
    nose_low = clr + 0.1
    nose_top = belt - (0.25 if sh.name != "van" else 0.2)
    nose_mid = nose_low + 0.45 * (nose_top - nose_low)
    bonnet_front = belt - 0.11
    cowl = zf - sh.bonnet * rng.uniform(0.94, 1.06)
    roof_front = cowl - sh.screen * rng.uniform(0.92, 1.08)
    roof_rear, base_rear = zr + sh.roof_rear, zr + sh.glass_rear
    # ---- lower body
    lamp_top, lamp_low = belt - 0.01, belt - 0.2  # the tail-lamp band: the tailgate's top edge, leaning in
    prof = [(zf - 0.12, clr), (zf, nose_low), (zf, nose_top), (zf - 0.2, bonnet_front), (cowl, belt),
            (zr + 0.07, belt), (zr, lamp_low), (zr, nose_low), (zr + 0.12, clr)]  # (z, height) round the
    # outline: outward is to the right of each edge
    planes, kinds = [], []
    for a, b in zip(prof, prof[1:] + prof[:1]):
        planes.append(_line_plane(a, b, "zh"))
        kinds.append(("profile", a, b))
    cz_f, cx_f, cz_r, cx_r = 0.5, 0.3, 0.36, 0.24  # ours: plan-view corner rounding, front and rear (m)
    drop, inset = 0.14, 0.08  # ours: the shoulder's rounding under the belt line
    waist = (clr + belt) / 2 + 0.05  # ours: the side's widest line; below it the side tucks in by TUCK_M
    for s in (-1, 1):
        planes.append((np.array([s, 0.0, 0.0]), hw))
        kinds.append(("side", s))
        planes.append(_line_plane((s * (hw - TUCK_M), clr + 0.1), (s * hw, waist), "xh", s))
        kinds.append(("lower", s))
        for pl in _bevel((s * hw, belt - drop), (s * hw, belt), (s * (hw - inset), belt), "xh", s, 2):
            planes.append(pl)
            kinds.append(("shoulder", s))
        planes.append(_line_plane((s * (hw - TUCK_M - 0.04), clr), (s * (hw - TUCK_M), clr + 0.1), "xh", s))
        kinds.append(("sill", s))
        for pl in _bevel((s * hw, zf - cz_f), (s * hw, zf), (s * (hw - cx_f), zf), "xz", s, 3):
            planes.append(pl)
            kinds.append(("corner_front", s))
        for pl in _bevel((s * (hw - cx_r), zr), (s * hw, zr), (s * hw, zr + cz_r), "xz", s, 3):
            planes.append(pl)
            kinds.append(("corner_rear", s))
    inside = P(0, (clr + belt) / 2, 0)
    for idx, poly in solid(planes, inside):
        kind = kinds[idx]
        n = planes[idx][0]
        if kind[0] == "side":
            put(poly, n, "body_side", paint, k, u_hint=(0, 0, -1))
        elif kind[0] == "lower":
            put(poly, n, "body_lower", paint, k, u_hint=(0, 0, -1))
        elif kind[0] in ("shoulder",):
            put(poly, n, "paint", paint, k, u_hint=(0, 0, 1))
        elif kind[0] == "sill":
            put(poly, n, "trim", (1, 1, 1), k, u_hint=(0, 0, 1))
        elif kind[0].startswith("corner"):
            front = kind[0] == "corner_front"
            bands = ([(clr, nose_low, "trim", (1, 1, 1)), (nose_low, nose_mid, "paint", paint),
                      (nose_mid, nose_top, "lamp", (1, 1, 1)), (nose_top, belt + 0.01, "paint", paint)] if front else
                     [(clr, nose_low + 0.1, "trim", (1, 1, 1)), (nose_low + 0.1, lamp_low, "paint", paint),
                      (lamp_low, lamp_top, "tail_light", (1, 1, 1)), (lamp_top, belt + 0.01, "paint", paint)])
            for lo, hi, mat, tint in bands:
                piece = clip_y(poly, lo, hi)
                if len(piece) >= 3:
                    put(piece, n, mat, tint, k, u_hint=(1, 0, 0))
        else:
            (z0, y0), (z1, y1) = kind[1], kind[2]
            if z0 == z1 == zf:  # the front: air intake and bumper below, headlights and grille above
                for lo, hi, mat, tint in ((nose_low, nose_low + 0.07, "trim", (1, 1, 1)),
                                          (nose_low + 0.07, nose_mid, "paint", paint),
                                          (nose_mid, nose_top, "headlights", (1, 1, 1))):
                    piece = clip_y(poly, lo, hi)
                    if len(piece) >= 3:
                        put(piece, n, mat, tint, k, u_hint=(1, 0, 0))
            elif z0 == z1 == zr:  # the rear: black lower bumper, tailgate and bumper panel
                for lo, hi, mat, tint in ((nose_low, nose_low + 0.1, "trim", (1, 1, 1)),
                                          (nose_low + 0.1, lamp_low, "rear_panel", paint)):
                    piece = clip_y(poly, lo, hi)
                    if len(piece) >= 3:
                        put(piece, n, mat, tint, k, u_hint=(-1, 0, 0))
            elif (z0, y0) == (zr + 0.07, belt):  # the lamp band: tail lamps at the ends, paint between
                lw = min(0.32, 0.18 * w)
                for lo, hi, mat, tint in ((-hw, -hw + cx_r + lw, "tail_light", (1, 1, 1)),
                                          (-hw + cx_r + lw, hw - cx_r - lw, "paint", paint),
                                          (hw - cx_r - lw, hw, "tail_light", (1, 1, 1))):
                    piece = clip_axis(poly, 0, lo, hi)
                    if len(piece) >= 3:
                        put(piece, n, mat, tint, k, u_hint=(-1, 0, 0))
            elif y0 == clr or y1 == clr:
                put(poly, n, "trim", (1, 1, 1), k, u_hint=(1, 0, 0))
            else:
                put(poly, n, "paint", paint, k, u_hint=(1, 0, 0))
    # ---- rear bumper: a rounded block standing out of the tailgate, black below
    bt, bb = nose_low + 0.22, nose_low - 0.04
    planes = [(np.array([0, -1.0, 0]), bt), (np.array([0, 1.0, 0]), -bb), (np.array([0, 0, 1.0]), zr + 0.35),
              (np.array([0, 0, -1.0]), -(zr - BUMPER_M))]
    kinds = ["top", "bottom", "inner", "back"]
    for s in (-1, 1):
        planes.append((np.array([s, 0.0, 0.0]), hw - 0.01))
        kinds.append("side")
        for pl in _bevel((s * (hw - cx_r - 0.02), zr - BUMPER_M), (s * (hw - 0.01), zr - BUMPER_M),
                         (s * (hw - 0.01), zr + cz_r - 0.02), "xz", s, 3):
            planes.append(pl)
            kinds.append("corner")
    for pl in _bevel((zr + 0.02, bt), (zr - BUMPER_M, bt), (zr - BUMPER_M, bt - 0.05), "zh", 1.0, 1):
        planes.append(pl)
        kinds.append("edge")
    for idx, poly in solid(planes, P(0, (bt + bb) / 2, zr + 0.1)):
        kind, n = kinds[idx], planes[idx][0]
        if kind in ("inner",):
            continue
        if kind in ("back", "corner", "side"):
            for lo, hi, mat, tint in ((bb, bb + 0.09, "trim", (1, 1, 1)), (bb + 0.09, bt, "paint", paint)):
                piece = clip_y(poly, lo, hi)
                if len(piece) >= 3:
                    put(piece, n, mat, tint, k, u_hint=(-1, 0, 0))
        else:
            put(poly, n, "trim" if kind == "bottom" else "paint", (1, 1, 1) if kind == "bottom" else paint, k,
                u_hint=(1, 0, 0))
    # ---- glasshouse: base a little into the body, roof rounded at its edges
    gb, gt = hw - inset, hw - inset - sh.tumble
    A, B, C, D = (cowl - 0.04, belt), (roof_front, h), (roof_rear, h), (base_rear, belt)
    rr, rc = 0.1, 0.14  # ours: the roof's rounded edge, down and in (m)
    planes = [(np.array([0, 1.0, 0]), -(belt - 0.02)), (np.array([0, -1.0, 0]), h),
              _line_plane(A, B, "zh"), _line_plane(C, D, "zh")]
    kinds = ["base", "roof", "screen", "rear"]
    x_at = gb - (gb - gt) * (h - rr - belt) / (h - belt)  # the side glass at the rounding's start
    for s in (-1, 1):
        planes.append(_line_plane((s * gb, belt), (s * gt, h), "xh", s))
        kinds.append(("glass", s))
        for pl in _bevel((s * x_at, h - rr), (s * gt, h), (s * (gt - rc), h), "xh", s, 2):
            planes.append(pl)
            kinds.append(("roof_edge", s))
    fr, bk = 0.07, 0.16  # ours: the roof curving down into the windscreen and the rear window (m)
    on_ab = (B[0] + (A[0] - B[0]) * fr / (h - belt), h - fr)
    on_cd = (C[0] + (D[0] - C[0]) * fr / (h - belt), h - fr)
    for pl in _bevel(on_ab, B, (B[0] - bk, h), "zh", 1.0, 2) + _bevel((C[0] + bk, h), C, on_cd, "zh", 1.0, 2):
        planes.append(pl)
        kinds.append("roof_curve")
    z_lo, z_hi = min(A[0], B[0], C[0], D[0]), max(A[0], B[0], C[0], D[0])
    for idx, poly in solid(planes, P(0, (belt + h) / 2, (A[0] + D[0] + B[0] + C[0]) / 4)):
        kind, n = kinds[idx], planes[idx][0]
        if kind == "base":
            continue
        if kind in ("roof", "roof_curve") or kind[0] == "roof_edge":
            put(poly, n, "paint", paint, k, u_hint=(1, 0, 0))
        elif kind == "screen":
            put(poly, n, "glass", (1, 1, 1), k, u_hint=(1, 0, 0))
        elif kind == "rear":  # painted pillars round a glass panel
            put(poly, n, "paint", paint, k, u_hint=(1, 0, 0))
            c = poly.mean(0)
            pane = c + (poly - c) * [0.78, 0.84, 0.84] + n / np.linalg.norm(n) * OVERLAY_M
            put(pane, n, "glass", (1, 1, 1), k, u_hint=(-1, 0, 0))
        else:
            if sh.side_glass < 1:  # a van: glass in the cab doors, panel behind
                cut = z_hi - sh.side_glass * (z_hi - z_lo)
                segs = [(cut, z_hi, "glass", (1, 1, 1)), (z_lo, cut - 0.06, "paint", paint), (cut - 0.06, cut, "trim", (1, 1, 1))]
            else:
                bp = z_lo + 0.52 * (z_hi - z_lo)  # B pillar
                segs = [(bp + 0.04, z_hi, "glass", (1, 1, 1)), (bp - 0.04, bp + 0.04, "trim", (1, 1, 1))]
                c_pillar = 0.3 if sh.name == "sedan" else 0.12
                segs += [(z_lo + c_pillar, bp - 0.04, "glass", (1, 1, 1)), (z_lo, z_lo + c_pillar, "paint", paint)]
            rail = h - 0.09  # ours: the painted roof rail above the side windows
            for lo, hi, mat, tint in segs:
                piece = clip_z(poly, lo, hi)
                if len(piece) >= 3 and mat == "glass":
                    upper = clip_y(piece, rail, h + 1)
                    piece = clip_y(piece, belt - 1, rail)
                    if len(upper) >= 3:
                        put(upper, n, "paint", paint, k, u_hint=(0, 0, -1))
                if len(piece) >= 3:
                    put(piece, n, mat, tint, k, u_hint=(0, 0, -1))
    return cowl


CAR_VARIANTS = 3  # ours: body templates per type (bonnet and windscreen lengths drawn once for each)
PAINT_MARK, GLASS_MARK = (-1.0, -1.0, -1.0), (-2.0, -2.0, -2.0)  # template tints: the car's paint, glass


def car_template(atlas: Atlas, material: str | None, shape: str, variant: int):
    """A body type's faces at its middle size (built once per atlas, material and variant)."""
    key = ("car", material, shape, variant)
    if key not in atlas.cache:
        sh = next(c for c in CAR_SHAPES if c.name == shape)
        size = tuple(float(np.mean(r)) for r in (sh.width, sh.height, sh.length))
        fl = FaceList(atlas, material)
        cowl = _car_body(fl, sh, *size, np.random.default_rng([variant, 17]))
        atlas.cache[key] = (fl.arrays(), np.array(size), cowl)
    return atlas.cache[key]


def car_faces(fl: FaceList, o: Obj, rng: np.random.Generator) -> None:
    """A car of body type ``o.shape``: its type's body template stretched to the car's size
    (planes stay planes and textures follow exactly: the texture axes take the inverse
    stretch), coloured; plates, mirrors, wheels in their arches and the contact shadow."""
    w, h, l = o.size
    sh = next(c for c in CAR_SHAPES if c.name == o.shape)
    k, paint = o.track_id, o.tint
    hw, zf, zr = w / 2, l / 2, -l / 2
    (V, R), size0, cowl0 = car_template(fl.atlas, fl.material, o.shape, int(rng.integers(CAR_VARIANTS)))
    S = np.array([w, h, l]) / size0
    R = R.copy()
    n = R[:, R_N : R_N + 3] / S
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    R[:, R_N : R_N + 3] = n
    R[:, R_O : R_O + 3] *= S
    R[:, R_U : R_U + 3] /= S
    R[:, R_V : R_V + 3] /= S
    R[:, R_OBJ] = k
    tint = R[:, R_TINT : R_TINT + 3]
    up = np.maximum(0.0, -n[:, 1])[:, None]
    is_paint, is_glass = tint[:, 0] == PAINT_MARK[0], tint[:, 0] == GLASS_MARK[0]
    sheen = 0.1 + 0.32 * up  # the sky in the clear coat: more on faces turned up, never darker than the paint
    p = np.asarray(paint, float)
    tint[is_paint] = (p * (1 - sheen) + sheen * np.maximum(SKY_SHEEN, p))[is_paint]
    tint[is_glass] = np.repeat(1.0 + 1.2 * up, 3, 1)[is_glass]  # glass reflects more where it faces up
    fl.extend(V * S, R)
    cowl = cowl0 * S[2]
    belt = sh.belt * h
    clr = sh.clearance
    nose_low = clr + 0.1
    # ---- plates just in front of their panels, mirrors, wheels, shadow
    pw, ph = PLATE_M
    for z, out, y0 in ((zf + OVERLAY_M, 1, nose_low + 0.1), (zr - OVERLAY_M, -1, nose_low + 0.27)):
        fl.poly([P(-pw / 2, y0 + ph, z), P(pw / 2, y0 + ph, z), P(pw / 2, y0, z), P(-pw / 2, y0, z)], (0, 0, out),
                "plate", (1, 1, 1), k, u_hint=(out, 0, 0))
    for sx in (-1, 1):
        fl.box([sx * (hw + 0.05), -(belt + 0.06), cowl - 0.18], (0.08, 0.055, 0.045), np.eye(3), {"all": "paint"},
               paint, k, skip=("bottom",))
    r = sh.wheel_d / 2
    rim = RIM_TINTS[int(rng.integers(len(RIM_TINTS)))]
    for z in (zf - sh.overhang[0], zr + sh.overhang[1]):
        for side in (-1, 1):
            wheel(fl, side, hw + 2 * OVERLAY_M, z, r, 0.2, rim, k, arch_x=hw + OVERLAY_M, arch_bottom=clr)
    _shadow(fl, hw + 0.12, zf + 0.15)


def truck_faces(fl: FaceList, o: Obj, rng: np.random.Generator) -> None:
    w, h, l = o.size
    k, paint = o.track_id, o.tint
    I = np.eye(3)
    hw, cab = w / 2, 2.0
    zc = l / 2 - cab / 2
    clr = 0.45
    fl.box([0, -(clr + 0.55), zc], (hw - 0.05, 0.55, cab / 2), I, {"all": "paint"}, paint, k, skip=("bottom",))
    top = min(h, 3.0)
    gh = top - (clr + 1.1)
    # cab: glass band above the lower cab, windscreen leaning back slightly
    zf = l / 2 - 0.08
    fl.poly([P(-hw + 0.05, clr + 1.1, l / 2), P(hw - 0.05, clr + 1.1, l / 2), P(hw - 0.08, top - 0.25, zf),
             P(-hw + 0.08, top - 0.25, zf)], (0, 0, 1), "glass", (1, 1, 1), k, u_hint=(1, 0, 0))
    fl.poly([P(-hw + 0.08, top - 0.25, zf), P(hw - 0.08, top - 0.25, zf), P(hw - 0.08, top, zf - 0.15),
             P(-hw + 0.08, top, zf - 0.15)], (0, -0.5, 1), "paint", paint, k, u_hint=(1, 0, 0))
    for side in (-1, 1):
        x = side * (hw - 0.05)
        zb = l / 2 - cab
        fl.poly([P(x, clr + 1.1, l / 2), P(x, top - 0.25, zf), P(x, top, zf - 0.15), P(x, top, zb), P(x, clr + 1.1, zb)],
                (side, 0, 0), "paint", paint, k, u_hint=(0, 0, -1))
        fl.poly([P(side * (hw - 0.05 + OVERLAY_M), clr + 1.15, l / 2 - 0.1), P(side * (hw - 0.05 + OVERLAY_M), clr + 1.1 + 0.8 * gh, l / 2 - 0.2),
                 P(side * (hw - 0.05 + OVERLAY_M), clr + 1.1 + 0.8 * gh, l / 2 - 1.1), P(side * (hw - 0.05 + OVERLAY_M), clr + 1.15, l / 2 - 1.1)],
                (side, 0, 0), "glass", (1, 1, 1), k, u_hint=(0, 0, -1))
    fl.poly([P(-hw + 0.08, top, zf - 0.15), P(hw - 0.08, top, zf - 0.15), P(hw - 0.05, top, l / 2 - cab),
             P(-hw + 0.05, top, l / 2 - cab)], (0, -1, 0), "paint", paint, k, u_hint=(1, 0, 0))
    fl.poly([P(-hw + 0.1, clr + 0.5, l / 2 + OVERLAY_M), P(hw - 0.1, clr + 0.5, l / 2 + OVERLAY_M),
             P(hw - 0.1, clr + 0.75, l / 2 + OVERLAY_M), P(-hw + 0.1, clr + 0.75, l / 2 + OVERLAY_M)], (0, 0, 1),
            "headlights", (1, 1, 1), k, u_hint=(1, 0, 0))
    # cargo box
    bl = l - cab - 0.15
    fl.box([0, -(clr + 0.15 + (h - clr - 0.15) / 2), -l / 2 + bl / 2], (hw, (h - clr - 0.15) / 2, bl / 2), I,
           {"all": "corrugated"}, o.tint2, k, skip=("bottom",))
    for sx in (-1, 1):
        fl.poly([P(sx * (hw - 0.05), clr + 0.35, -l / 2 - OVERLAY_M), P(sx * (hw - 0.3), clr + 0.35, -l / 2 - OVERLAY_M),
                 P(sx * (hw - 0.3), clr + 0.15, -l / 2 - OVERLAY_M), P(sx * (hw - 0.05), clr + 0.15, -l / 2 - OVERLAY_M)],
                (0, 0, -1), "tail_light", (1, 1, 1), k, u_hint=(-sx, 0, 0))
    fl.box([0, -(clr / 2 + 0.1), 0], (hw - 0.35, clr / 2, l / 2 - 0.3), I, {"all": "trim"}, (1, 1, 1), k, skip=("bottom", "top"))
    r = TRUCK_WHEEL_D / 2
    for z in (l / 2 - 1.2, -l / 2 + 2.2, -l / 2 + 1.1):
        for side in (-1, 1):
            wheel(fl, side, hw - 0.02, z, r, 0.3, (0.8, 0.8, 0.8), k)
    _shadow(fl, hw + 0.12, l / 2 + 0.2)


def bus_faces(fl: FaceList, o: Obj, rng: np.random.Generator) -> None:
    w, h, l = o.size
    k, paint = o.track_id, o.tint
    hw, clr = w / 2, 0.3
    I = np.eye(3)
    fl.box([0, -(clr + (h - clr) / 2), 0], (hw, (h - clr) / 2, l / 2), I,
           {"side": "bus_side", "front": "paint", "rear": "paint", "top": "paint"}, paint, k, skip=("bottom",))
    zf, zr = l / 2 + OVERLAY_M, -l / 2 - OVERLAY_M
    fl.poly([P(-hw + 0.08, 1.0, zf), P(hw - 0.08, 1.0, zf), P(hw - 0.08, h - 0.2, zf), P(-hw + 0.08, h - 0.2, zf)],
            (0, 0, 1), "glass", (1, 1, 1), k, u_hint=(1, 0, 0))
    fl.poly([P(-hw + 0.1, 0.45, zf), P(hw - 0.1, 0.45, zf), P(hw - 0.1, 0.7, zf), P(-hw + 0.1, 0.7, zf)],
            (0, 0, 1), "headlights", (1, 1, 1), k, u_hint=(1, 0, 0))
    fl.poly([P(-hw + 0.4, 2.05, zr), P(hw - 0.4, 2.05, zr), P(hw - 0.4, h - 0.3, zr), P(-hw + 0.4, h - 0.3, zr)],
            (0, 0, -1), "glass", (1, 1, 1), k, u_hint=(-1, 0, 0))  # a small rear window over the engine
    fl.poly([P(-hw + 0.3, 0.55, zr), P(hw - 0.3, 0.55, zr), P(hw - 0.3, 1.3, zr), P(-hw + 0.3, 1.3, zr)],
            (0, 0, -1), "trim", (1, 1, 1), k, u_hint=(-1, 0, 0))  # the engine grille
    for sx in (-1, 1):
        fl.poly([P(sx * (hw - 0.08), 0.5, zr), P(sx * (hw - 0.3), 0.5, zr), P(sx * (hw - 0.3), 1.0, zr),
                 P(sx * (hw - 0.08), 1.0, zr)], (0, 0, -1), "tail_light", (1, 1, 1), k, u_hint=(-sx, 0, 0))
    r = BUS_WHEEL_D / 2
    for z in (l / 2 - 2.5, -l / 2 + 3.0):
        for side in (-1, 1):
            wheel(fl, side, hw + 2 * OVERLAY_M, z, r, 0.3, (0.8, 0.8, 0.8), k, arch_x=hw + OVERLAY_M, arch_bottom=clr)
    _shadow(fl, hw + 0.12, l / 2 + 0.2)


# --------------------------------------------------------------------------- people and bicycles

# body parts (row R_PART): 0 torso and head; 1, 2 thighs; 3, 4 upper arms; 5, 6 shins and feet;
# 7, 8 forearms and hands (left, right). Each has its joint: hip, shoulder, knee, elbow.
N_PARTS = 9


@dataclass(frozen=True)
class Rig:
    """A person's joints in the rest pose (heights above the ground, metres) and gait."""

    stature: float
    hip: float
    knee: float
    ankle: float
    shoulder: float
    elbow: float
    wrist: float
    stride: float  # metres per walking cycle (two steps)
    swing: float  # hip swing amplitude, rad
    arm_swing: float  # shoulder swing amplitude, rad
    lean: float  # riding: the torso's forward lean, rad


def rig(o: Obj) -> Rig:
    """The person's joints and gait, a pure function of its stature and seed."""
    return _rig(o.stature, o.seed)


@lru_cache(maxsize=4096)
def _rig(H: float, seed: int) -> Rig:
    g = np.random.default_rng([seed, 5])
    return Rig(H, HIP_H * H, KNEE_H * H, ANKLE_H * H, SHOULDER_H * H, (SHOULDER_H - UPPER_ARM) * H,
               (SHOULDER_H - UPPER_ARM - FOREARM) * H,
               stride=H * g.uniform(0.78, 0.9), swing=g.uniform(0.32, 0.45), arm_swing=g.uniform(0.2, 0.45),
               lean=g.uniform(0.35, 0.6))


def rider_height(o: Obj) -> float:
    """Top of a rider's head above the ground (hip on the saddle, torso leaning forward)."""
    rg = rig(o)
    return float(_saddle_hip(rg.stature) + rg.stature * (1 - HIP_H) * np.cos(rg.lean))


def _saddle_hip(stature: float) -> float:
    """Hip height on the saddle: the leg nearly straight at the lowest pedal (ours: 96 % of its length)."""
    leg = (HIP_H - ANKLE_H) * stature
    dz = SADDLE_Z - (-0.05)
    return BIKE_BB_H - CRANK_M + 0.05 + np.sqrt(max((0.96 * leg) ** 2 - dz * dz, 0.1))


ROLES = ("top", "bottom", "skin", "hair", "shoes", "bag")  # a person template's tints: −1 … −6 by role


def _person_body(fl: FaceList, long_sleeves: bool, skirt: bool, coat: bool, backpack: bool) -> None:
    """A person of stature 1 in the rest pose (standing straight, arms down); tints mark roles."""
    top, bottom, skin, hair_c, shoes, bag = ((-float(i + 1),) * 3 for i in range(len(ROLES)))
    H, k = 1.0, 0
    rg = Rig(1.0, HIP_H, KNEE_H, ANKLE_H, SHOULDER_H, SHOULDER_H - UPPER_ARM, SHOULDER_H - UPPER_ARM - FOREARM,
             0.0, 0.0, 0.0, 0.0)
    I = np.eye(3)
    # torso (part 0): hips to shoulders, a little wider and deeper at the chest
    fl.frustum(P(0, rg.hip - 0.04 * H, 0), P(0, rg.shoulder + 0.012 * H, 0), (0.09 * H, 0.058 * H), (0.1 * H, 0.062 * H),
               I, "fabric", top, k, caps=(True, True))
    if coat:
        fl.frustum(P(0, 0.33 * H, 0), P(0, rg.hip - 0.03 * H, 0), (0.11 * H, 0.075 * H), (0.095 * H, 0.064 * H), I,
                   "fabric", top, k, caps=(True, False))
    if skirt:
        fl.frustum(P(0, 0.34 * H, 0), P(0, rg.hip - 0.03 * H, 0), (0.12 * H, 0.09 * H), (0.09 * H, 0.06 * H), I,
                   "fabric", bottom, k, caps=(True, False))
    if backpack:
        fl.box([0, -(rg.shoulder - 0.13 * H), -(0.062 * H + 0.034)], (0.075 * H, 0.11 * H, 0.034), I, {"all": "fabric"},
               bag, k, skip=())
    # neck and head: a hexagonal head, skin in front, hair behind and on the crown
    fl.frustum(P(0, rg.shoulder, 0.004 * H), P(0, CHIN_H * H + 0.01 * H, 0.004 * H), (0.03 * H, 0.032 * H),
               (0.028 * H, 0.03 * H), I, "skin", skin, k, caps=(False, False))
    ang = np.arange(6) * np.pi / 3 + np.pi / 6
    rx, rz = 0.046 * H, 0.056 * H
    ring = np.stack([rx * np.cos(ang), np.full(6, -CHIN_H * H), rz * np.sin(ang) + 0.006 * H], 1)
    crown_h = 0.97 * H
    for i in range(6):
        j = (i + 1) % 6
        front = np.sin(0.5 * (ang[i] + ang[j])) > 0.1
        a0, a1 = ring[i], ring[j]
        b0, b1 = a0 + [0, -(crown_h - CHIN_H * H), 0], a1 + [0, -(crown_h - CHIN_H * H), 0]
        out = np.array([np.cos(0.5 * (ang[i] + ang[j])), 0, np.sin(0.5 * (ang[i] + ang[j]))])
        fl.poly([a0, a1, b1, b0], out, "skin" if front else "hair", skin if front else hair_c, k)
        c0 = b0 * [0.72, 1, 0.72] + [0, -(H - crown_h), 0.0017 * H]
        c1 = b1 * [0.72, 1, 0.72] + [0, -(H - crown_h), 0.0017 * H]
        fl.poly([b0, b1, c1, c0], out + [0, -0.8, 0], "hair", hair_c, k)
    crown = ring * [0.72, 1, 0.72] + [0, -(H - CHIN_H * H), 0.0017 * H]
    fl.poly(crown, (0, -1, 0), "hair", hair_c, k)
    fl.poly(ring, (0, 1, 0), "skin", skin, k)
    # legs: thighs (1, 2) and shins with feet (5, 6)
    for side, thigh, shin in ((-1, 1, 5), (1, 2, 6)):
        x = side * HIP_X * H
        leg_c = bottom if not skirt else skin
        fl.frustum(P(x, rg.knee, 0), P(x, rg.hip, 0), (0.032 * H, 0.036 * H), (0.045 * H, 0.05 * H), I, "fabric",
                   leg_c if not coat else top, k, thigh, caps=(False, False))
        fl.frustum(P(x, rg.ankle, 0), P(x, rg.knee, 0), (0.022 * H, 0.026 * H), (0.031 * H, 0.035 * H), I,
                   "fabric" if not skirt else "skin", bottom if not skirt else skin, k, shin, caps=(False, False))
        fl.box([x, -rg.ankle / 2, 0.045 * H], (0.03 * H, rg.ankle / 2, FOOT * H / 2), I, {"all": "trim"}, shoes, k,
               part=shin, skip=("bottom",))
    # arms: upper arms (3, 4) and forearms with hands (7, 8)
    for side, upper, fore in ((-1, 3, 7), (1, 4, 8)):
        x = side * SHOULDER_X * H
        fl.frustum(P(x, rg.elbow, 0), P(x, rg.shoulder, 0), (0.022 * H, 0.025 * H), (0.027 * H, 0.03 * H), I,
                   "fabric", top, k, upper, caps=(False, True))
        fl.frustum(P(x, rg.wrist, 0), P(x, rg.elbow, 0), (0.018 * H, 0.02 * H), (0.021 * H, 0.024 * H), I,
                   "fabric" if long_sleeves else "skin", top if long_sleeves else skin, k, fore, caps=(False, False))
        fl.box([x, -(rg.wrist - HAND * H / 2), 0], (0.014 * H, HAND * H / 2, 0.024 * H), I, {"all": "skin"}, skin, k,
               part=fore, skip=())


def person_template(atlas: Atlas, material: str | None, flags: tuple[bool, bool, bool, bool]):
    key = ("person", material, flags)
    if key not in atlas.cache:
        fl = FaceList(atlas, material)
        _person_body(fl, *flags)
        atlas.cache[key] = fl.arrays()
    return atlas.cache[key]


def person_faces(fl: FaceList, o: Obj, rng: np.random.Generator) -> None:
    """A person: the template of its clothing cut scaled to its stature, coloured from the seed."""
    H, k = o.stature, o.track_id
    colours = [o.tint, o.tint2, SKIN[int(rng.integers(len(SKIN)))], HAIR[int(rng.integers(len(HAIR)))],
               ((0.08, 0.08, 0.08), (0.3, 0.2, 0.12), (0.85, 0.85, 0.85))[int(rng.integers(3))]]
    long_sleeves = bool(rng.random() < 0.6)
    skirt = bool(not o.riding and rng.random() < 0.15)
    coat = bool(not o.riding and not skirt and rng.random() < 0.2)
    backpack = bool(rng.random() < 0.2)
    colours.append(CLOTHES[int(rng.integers(len(CLOTHES)))])
    V, R = person_template(fl.atlas, fl.material, (long_sleeves, skirt, coat, backpack))
    R = R.copy()
    R[:, R_O : R_O + 3] *= H
    R[:, R_U : R_U + 3] /= H
    R[:, R_V : R_V + 3] /= H
    R[:, R_OBJ] = k
    role = (-R[:, R_TINT]).astype(int) - 1
    R[:, R_TINT : R_TINT + 3] = np.array(colours, float)[role]
    fl.extend(V * H, R)
    _shadow(fl, 0.28, 0.3)


def _two_link(hip: np.ndarray, target: np.ndarray, l1: float, l2: float, bend: int) -> tuple[float, float]:
    """Angles (about x, from straight down, +: forward) of a two-segment limb from ``hip`` reaching
    ``target`` (both (y, z), y down); ``bend`` +1 bends the middle joint forward (knee), −1 back."""
    d = target - hip
    dist = float(np.clip(np.hypot(*d), abs(l1 - l2) + 1e-3, l1 + l2 - 1e-4))
    base = np.arctan2(d[1], d[0])  # angle of the hip→target line from straight down, forward +
    a1 = np.arccos(np.clip((l1 * l1 + dist * dist - l2 * l2) / (2 * l1 * dist), -1, 1))
    a2 = np.arccos(np.clip((l2 * l2 + dist * dist - l1 * l1) / (2 * l2 * dist), -1, 1))
    return base + bend * a1, base - bend * a2


def part_poses(o: Obj, walked: float) -> tuple[np.ndarray, np.ndarray]:
    """Rigid motion (R (9,3,3), t (9,3)) of each body part (row R_PART, see ``N_PARTS``) in the
    object's frame: a walking cycle by the distance travelled (standing people keep the rest
    pose, arms a little bent), or pedalling on a bicycle's saddle; a quadruped's walk
    (``quadruped_poses``)."""
    if o.category in QUADRUPEDS:
        return quadruped_poses(o, walked)
    R = np.repeat(np.eye(3)[None], N_PARTS, 0)
    t = np.zeros((N_PARTS, 3))
    if o.category != "person":
        return R, t
    rg = rig(o)
    H = rg.stature
    hip_y, sh_y = -rg.hip, -rg.shoulder
    lt, ls = rg.hip - rg.knee, rg.knee - rg.ankle
    lu, lf = rg.shoulder - rg.elbow, rg.elbow - rg.wrist

    def about(part: int, angle: float, pivot: np.ndarray, to: np.ndarray | None = None, base=None) -> None:
        """Part rotated by ``angle`` about x at its rest ``pivot``, the pivot moved to ``to``;
        ``base`` (R, t) of a parent part composes before."""
        Rl = rot_x(angle)
        tl = (pivot if to is None else to) - Rl @ pivot
        if base is not None:
            Rl, tl = base[0] @ Rl, base[0] @ tl + base[1]
        R[part], t[part] = Rl, tl

    if o.riding:
        hip = np.array([0.0, -_saddle_hip(H), SADDLE_Z])
        lean = -rg.lean  # forward
        about(0, lean, np.array([0, hip_y, 0]), hip)
        crank = 2 * np.pi * walked / PEDAL_M_PER_TURN
        for side, thigh, shin, phase in ((-1, 1, 5, 0.0), (1, 2, 6, np.pi)):
            x = side * HIP_X * H
            foot = np.array([-(BIKE_BB_H - CRANK_M * np.cos(crank + phase)) - 0.05, -0.05 + CRANK_M * np.sin(crank + phase)])
            a_t, a_s = _two_link(hip[1:], foot, lt, ls, +1)
            about(thigh, a_t, np.array([x, hip_y, 0]), np.array([x, hip[1], hip[2]]))
            about(shin, a_s - a_t, np.array([x, -rg.knee, 0]), base=(R[thigh].copy(), t[thigh].copy()))
        for side, upper, fore in ((-1, 3, 7), (1, 4, 8)):
            x = side * SHOULDER_X * H
            sh = R[0] @ np.array([x, sh_y, 0]) + t[0]
            grip = np.array([-BAR_H, BAR_Z])
            a_u, a_f = _two_link(sh[1:], grip, lu, lf + 0.5 * HAND * H, -1)
            about(upper, a_u, np.array([x, sh_y, 0]), sh)
            about(fore, a_f - a_u, np.array([x, -rg.elbow, 0]), base=(R[upper].copy(), t[upper].copy()))
        return R, t
    if o.motion.kind == "static":  # standing: arms hang a little bent
        for side, upper, fore in ((-1, 3, 7), (1, 4, 8)):
            x = side * SHOULDER_X * H
            about(upper, 0.08, np.array([x, sh_y, 0]))
            about(fore, 0.25, np.array([x, -rg.elbow, 0]), base=(R[upper].copy(), t[upper].copy()))
        return R, t
    phase = 2 * np.pi * walked / rg.stride
    ankle_h = []
    for side, thigh, shin, ph in ((-1, 1, 5, 0.0), (1, 2, 6, np.pi)):
        x = side * HIP_X * H
        p = phase + ph
        a_t = rg.swing * np.sin(p)
        knee = -(0.08 + 0.95 * max(0.0, np.cos(p + 0.25)) ** 2)  # flexes in the swing phase
        about(thigh, a_t, np.array([x, hip_y, 0]))
        about(shin, knee, np.array([x, -rg.knee, 0]), base=(R[thigh].copy(), t[thigh].copy()))
        for z in (0.045 * H - FOOT * H / 2, 0.045 * H + FOOT * H / 2):  # heel and toe, on the ground at rest
            ankle_h.append(-(R[shin] @ np.array([x, 0.0, z]) + t[shin])[1])
    for side, upper, fore, ph in ((-1, 3, 7, np.pi), (1, 4, 8, 0.0)):
        x = side * SHOULDER_X * H
        p = phase + ph
        a_u = rg.arm_swing * np.sin(p)
        about(upper, a_u, np.array([x, sh_y, 0]))
        about(fore, 0.2 + 0.25 * max(0.0, np.sin(p)), np.array([x, -rg.elbow, 0]), base=(R[upper].copy(), t[upper].copy()))
    t[:, 1] += min(ankle_h)  # the lowest heel or toe on the ground: the body bobs
    return R, t


def bicycle_faces(fl: FaceList, o: Obj, rng: np.random.Generator) -> None:
    """A bicycle: the one template (built once per atlas), its frame in the bicycle's paint."""
    key = ("bicycle", fl.material)
    if key not in fl.atlas.cache:
        t = FaceList(fl.atlas, fl.material)
        _bicycle_body(t)
        fl.atlas.cache[key] = t.arrays()
    V, R = fl.atlas.cache[key]
    R = R.copy()
    R[:, R_OBJ] = o.track_id
    paint = R[:, R_TINT] == PAINT_MARK[0]
    R[paint, R_TINT : R_TINT + 3] = o.tint
    fl.extend(V, R)
    _shadow(fl, 0.25, 0.75)


def _bicycle_body(fl: FaceList) -> None:
    k, paint = 0, PAINT_MARK
    r = BIKE_WHEEL_R
    zr, zf = -BIKE_WHEELBASE / 2, BIKE_WHEELBASE / 2
    n = 12
    ang = (np.arange(n) + 0.5) * 2 * np.pi / n
    for zc in (zr, zf):
        def ring(f, zc=zc):
            return np.stack([np.zeros(n), -r + f * r * np.cos(ang), zc + f * r * np.sin(ang)], 1)

        outer, inner, hub = ring(1.0), ring(0.9), ring(0.84)  # ours: a 35 mm tyre on a 22 mm rim
        for i in range(n):
            j = (i + 1) % n
            for sx in (-1, 1):
                dx = np.array([sx * 0.016, 0, 0])
                fl.poly([outer[i] + dx, outer[j] + dx, inner[j] + dx, inner[i] + dx], (sx, 0, 0), "rubber",
                        (1, 1, 1), k)
                fl.poly([inner[i] + dx * 0.6, inner[j] + dx * 0.6, hub[j] + dx * 0.6, hub[i] + dx * 0.6], (sx, 0, 0),
                        "metal", (0.85, 0.85, 0.85), k)
            mid = 0.5 * (ang[i] + ang[j])
            dx = np.array([0.016, 0, 0])
            fl.poly([outer[i] - dx, outer[j] - dx, outer[j] + dx, outer[i] + dx], (0, np.cos(mid), np.sin(mid)),
                    "rubber", (1, 1, 1), k)
        for a in (0.0, np.pi / 3, 2 * np.pi / 3):  # spokes
            d = np.array([0, np.cos(a), np.sin(a)]) * 0.84 * r
            c = np.array([0, -r, zc])
            fl.tube(c - d, c + d, 0.004, "metal", (0.8, 0.8, 0.8), k, across=(1, 0, 0))
    bb = P(0, BIKE_BB_H, -0.05)
    seat = P(0, 0.86, SADDLE_Z + 0.04)
    head_lo, head_hi = P(0, 0.68, 0.36), P(0, 0.86, 0.32)
    rear, front = P(0, r, zr), P(0, r, zf)
    for a, b, hw in ((bb, seat, 0.018), (seat, head_hi, 0.016), (bb, head_lo, 0.02), (bb, rear, 0.012),
                     (seat, rear, 0.011), (head_lo, head_hi, 0.02), (head_lo, front, 0.013)):
        fl.tube(a, b, hw, "paint", paint, k)
    fl.tube(head_hi, P(0, BAR_H, BAR_Z), 0.012, "metal", (0.5, 0.5, 0.5), k)
    fl.tube(P(-0.28, BAR_H, BAR_Z), P(0.28, BAR_H, BAR_Z), 0.013, "trim", (1, 1, 1), k, across=(0, 0, 1))
    fl.tube(seat, P(0, 0.92, SADDLE_Z), 0.012, "metal", (0.5, 0.5, 0.5), k)
    fl.box([0, -0.94, SADDLE_Z - 0.02], (0.07, 0.025, 0.13), np.eye(3), {"all": "trim"}, (1, 1, 1), k)
    fl.tube(bb + [0.05, 0, 0], bb + [0.05, 0.16, 0.05], 0.012, "metal", (0.6, 0.6, 0.6), k)


# --------------------------------------------------------------------------- the unknown kinds


def lump_faces(fl: FaceList, o: Obj, rng: np.random.Generator, material: str, n: int, roundness: float,
               off=(0.0, 0.0)) -> None:
    """Debris and blobs: the convex hull of jittered points on an ellipsoid, flat-bottomed."""
    w, h, l = o.size
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    rad = rng.uniform(roundness, 1.0, (n, 1))
    pts = dirs * rad * np.array([w / 2, h / 2, l / 2])
    pts[:, 1] = np.minimum(pts[:, 1], 0.3 * h / 2)  # flat bottom
    pts[:, 1] -= pts[:, 1].max()
    fl.convex(pts, material, o.tint, o.track_id, offset=off)


def tyre_faces(fl: FaceList, o: Obj, rng: np.random.Generator) -> None:
    """A loose car tyre: lying flat (a stack of one to three) or standing on its tread."""
    k = o.track_id
    r = 0.31
    dark = (0.2, 0.2, 0.2)
    if o.shape == "upright":
        wheel(fl, 1, 0.1, 0.0, r, 0.2, dark, k, tread="full")
        wheel(fl, -1, 0.1, 0.0, r, 0.2, dark, k, tread="none")
    else:
        n = 8
        ang = (np.arange(n) + 0.5) * 2 * np.pi / n
        for j in range(round(o.size[1] / 0.21)):
            y0 = -0.21 * j - 0.005 * j
            ring = np.stack([r * np.cos(ang), np.full(n, y0), r * np.sin(ang)], 1)
            fl.prism(ring, (0, -0.2, 0), "rubber", (1, 1, 1), k, caps=(False, False))
            fl.poly(ring + [0, -0.2, 0], (0, -1, 0), "wheel", dark, k, u_hint=(1, 0, 0))
    _shadow(fl, o.size[0] / 2 + 0.05, o.size[2] / 2 + 0.05)


def barrier_faces(fl: FaceList, o: Obj, rng: np.random.Generator) -> None:
    """A road barrier: a striped board on two A-frame trestles, or a concrete kerb barrier."""
    w, h, l = o.size
    k = o.track_id
    if o.shape == "jersey":
        prof = [(-w / 2, 0.0), (w / 2, 0.0), (w / 2 - 0.05, 0.25), (0.13, h), (-0.13, h), (-w / 2 + 0.05, 0.25)]
        ring = [P(x, y, l / 2) for x, y in prof]
        fl.prism(ring, (0, 0, -l), "concrete", (0.95, 0.95, 0.92), k, caps=(True, True), skip=lambda i: i == 0)
        for z0 in np.arange(-l / 2 + 0.2, l / 2 - 0.3, 0.8):  # red bands
            for side in (-1, 1):
                fl.poly([P(side * (w / 2 - 0.05 + OVERLAY_M), 0.25, z0), P(side * (0.13 + OVERLAY_M), h, z0),
                         P(side * (0.13 + OVERLAY_M), h, z0 + 0.35), P(side * (w / 2 - 0.05 + OVERLAY_M), 0.25, z0 + 0.35)],
                        (side, -0.3, 0), "paint", (0.75, 0.1, 0.08), k)
    else:
        fl.box([0, -(h - 0.14), 0], (0.02, 0.14, l / 2), np.eye(3), {"all": "barrier"}, (1, 1, 1), k, skip=())
        for z in (-l / 2 + 0.1, l / 2 - 0.1):
            for sx in (-1, 1):
                fl.tube(P(0, h - 0.1, z), P(sx * w / 2, 0, z), 0.02, "paint", (0.85, 0.85, 0.85), k, across=(0, 0, 1))
    _shadow(fl, w / 2 + 0.05, l / 2 + 0.05)


def box_faces(fl: FaceList, o: Obj, rng: np.random.Generator) -> None:
    w, h, l = o.size
    fl.box([0, -h / 2, 0], (w / 2, h / 2, l / 2), np.eye(3), {"all": "cardboard"}, tuple(np.array(o.tint) * 0.25 + 0.75),
           o.track_id)
    _shadow(fl, w / 2 + 0.04, l / 2 + 0.04)


def branch_faces(fl: FaceList, o: Obj, rng: np.random.Generator) -> None:
    """A fallen branch: a tapering limb along z with side twigs and a few clumps of leaves."""
    w, h, l = o.size
    k = o.track_id
    bark = tuple(np.array(o.tint) * 0.3 + 0.7)
    base, tip = P(0, 0.07, -l / 2), P(rng.uniform(-0.2, 0.2), 0.05, l / 2)
    pts = [base + (tip - base) * f for f in (0.0, 0.35, 0.7, 1.0)]
    for (a, b), hw in zip(pairwise(pts), (0.07, 0.05, 0.03)):
        fl.tube(a, b, hw, "bark", bark, k)
    for f in rng.uniform(0.25, 0.9, int(rng.integers(2, 5))):
        a = base + (tip - base) * f
        side = rng.choice([-1, 1])
        b = a + np.array([side * rng.uniform(0.3, w / 2), -rng.uniform(0.05, h - 0.15), rng.uniform(0.1, 0.5)])
        b = np.clip(b, [-w / 2 + 0.2, -(h - 0.12), -l / 2 + 0.2], [w / 2 - 0.2, 0.0, l / 2 - 0.2])  # in the truth box
        fl.tube(a, b, 0.022, "bark", bark, k)
        if rng.random() < 0.7:
            c = rng.normal(size=(9, 3)) * [0.22, 0.12, 0.22] + b
            c = np.clip(c, [-w / 2, -h, -l / 2], [w / 2, -0.02, l / 2])
            fl.convex(c, "foliage", (0.9, 1.0, 0.85), k)


def cart_faces(fl: FaceList, o: Obj, rng: np.random.Generator) -> None:
    """A two-wheeled hand cart: a wooden bed on two wheels, handles behind, sometimes a load."""
    w, _, l = o.size
    k = o.track_id
    I = np.eye(3)
    bed_h = 0.42
    fl.box([0, -(bed_h + 0.12), 0.1], (w / 2 - 0.08, 0.12, l / 2 - 0.35), I, {"all": "crate"}, (0.9, 0.8, 0.7), k, skip=())
    for side in (-1, 1):
        wheel(fl, side, w / 2, 0.15, 0.22, 0.06, (0.6, 0.6, 0.6), k, n=8)
        fl.tube(P(side * (w / 2 - 0.12), bed_h + 0.05, -l / 2 + 0.4), P(side * (w / 2 - 0.12), 0.85, -l / 2), 0.018,
                "metal", (0.7, 0.7, 0.7), k)
    fl.tube(P(-(w / 2 - 0.12), 0.85, -l / 2 + 0.02), P(w / 2 - 0.12, 0.85, -l / 2 + 0.02), 0.018, "trim", (1, 1, 1), k,
            across=(0, 0, 1))
    fl.tube(P(0, bed_h, l / 2 - 0.3), P(0, 0.0, l / 2 - 0.2), 0.025, "metal", (0.7, 0.7, 0.7), k)  # stand
    if rng.random() < 0.6:
        fl.box([0, -(bed_h + 0.24 + 0.15), 0.1], (w / 2 - 0.15, 0.15, l / 4), I, {"all": "cardboard"}, (1, 1, 1), k)
    _shadow(fl, w / 2 + 0.05, l / 2)


def tortoise_faces(fl: FaceList, o: Obj, rng: np.random.Generator) -> None:
    """A giant tortoise: a domed shell on four stumpy legs, head and neck forward (no COCO class)."""
    w, h, l = o.size
    k = o.track_id
    legs_h = 0.12 * h / 0.45
    ang = rng.uniform(0, 2 * np.pi, 40)
    el = np.arccos(rng.uniform(0, 1, 40))
    dome = np.stack([np.sin(el) * np.cos(ang) * w / 2, -legs_h - np.cos(el) * (h - legs_h), np.sin(el) * np.sin(ang) * l * 0.42], 1)
    rim = np.stack([np.cos(np.arange(10) * np.pi / 5) * w / 2, np.full(10, -legs_h), np.sin(np.arange(10) * np.pi / 5) * l * 0.42], 1)
    fl.convex(np.concatenate([dome, rim]), "shell", o.tint, k)
    limb = (0.45, 0.42, 0.36)
    for sx in (-1, 1):
        for sz in (-1, 1):
            fl.frustum(P(sx * w * 0.32, 0.0, sz * l * 0.28), P(sx * w * 0.3, legs_h + 0.06, sz * l * 0.26), (0.06, 0.06),
                       (0.05, 0.05), np.eye(3), "mottled", limb, k, caps=(False, False))
    fl.tube(P(0, legs_h + 0.08, l * 0.35), P(0, legs_h + 0.14, l * 0.46), 0.05, "mottled", limb, k)
    fl.box([0, -(legs_h + 0.16), l * 0.46], (0.06, 0.05, 0.05), np.eye(3), {"all": "mottled"}, limb, k, skip=())
    _shadow(fl, w / 2 + 0.05, l / 2)


# ---- issue 29: more unknown kinds (an animal no COCO class names, a trolley, a fallen load)


@dataclass(frozen=True)
class Quadruped:
    """A four-legged animal's build at its nominal size: metres, heights above the ground, z
    forward from the truth box's centre. Legs are two segments (upper, lower) that swing."""

    name: str
    size: tuple[float, float, float]  # nominal truth box w, h, l (head and ears included)
    back: tuple[float, float]  # back line height at the rump and at the withers
    belly: float  # underside of the trunk
    trunk: tuple[float, float]  # trunk z from the rump to the chest
    trunk_w: float  # trunk width
    legs_z: tuple[float, float]  # hind and fore leg joints' z (hip, shoulder)
    legs_x: float  # the legs' lateral offset
    joint_h: float  # the legs' top joint height (hip and shoulder)
    knee_h: float  # the middle joint's height (stifle/hock, elbow/carpus: one joint here)
    leg_w: tuple[float, float]  # half widths of the upper and lower leg
    neck: tuple[tuple[float, float], tuple[float, float], float]  # (z, h) at the base and the top, half width
    head: tuple[tuple[float, float], tuple[float, float, float], float]  # centre (z, h), half sizes, pitch down (rad)
    stride: float  # metres travelled per gait cycle (four steps)
    swing: float  # upper-leg swing amplitude, rad
    coats: tuple[tuple[float, float, float], ...]  # coat colours, one drawn per animal


# Two animals COCO's ten (bird, cat, dog, horse, sheep, cow, elephant, bear, zebra, giraffe) do not
# name, so the truth calls them unknown although a detector may mistake them for a dog or a horse.
QUADRUPEDS = {
    # ours, after roe deer (Capreolus capreolus): 0.65–0.75 m at the shoulder, head and body 0.95–1.35 m,
    # 15–30 kg, slender legs; summer coat red-brown, winter grey-brown; a walk of ~0.9 m a cycle
    "deer": Quadruped("deer", (0.34, 1.1, 1.25), (0.7, 0.74), 0.44, (-0.58, 0.3), 0.26, (-0.4, 0.18), 0.085,
                      0.6, 0.31, (0.035, 0.017), ((0.22, 0.66), (0.4, 0.93), 0.05),
                      ((0.5, 0.97), (0.055, 0.06, 0.11), 0.5), 0.9, 0.35,
                      ((0.55, 0.36, 0.22), (0.5, 0.33, 0.2), (0.42, 0.36, 0.3))),
    # ours, after wild boar (Sus scrofa): 0.55–1.1 m at the shoulder, head and body 0.9–1.8 m, 50–150 kg,
    # a deep trunk high at the withers, short legs, a long wedge head; dark grey-brown bristles
    "boar": Quadruped("boar", (0.5, 0.82, 1.45), (0.66, 0.8), 0.33, (-0.64, 0.34), 0.44, (-0.44, 0.2), 0.13,
                      0.44, 0.22, (0.05, 0.03), ((0.26, 0.56), (0.4, 0.56), 0.16),
                      ((0.5, 0.48), (0.11, 0.13, 0.2), 0.35), 0.8, 0.3,
                      ((0.28, 0.24, 0.2), (0.22, 0.19, 0.16), (0.35, 0.29, 0.22))),
}
HOOF = (0.22, 0.2, 0.18)  # ours: hooves, dark horn
RUMP_PATCH = (0.92, 0.9, 0.84)  # ours: a roe deer's white rump patch
ANIMATED = ("person", *QUADRUPEDS)  # categories whose parts move (``part_poses``)


def quadruped_scale(o: Obj) -> np.ndarray:
    """The animal's size relative to its species' nominal build, per axis (x, y, z)."""
    return np.asarray(o.size, float) / np.asarray(QUADRUPEDS[o.category].size, float)


def quadruped_faces(fl: FaceList, o: Obj, rng: np.random.Generator) -> None:
    """A quadruped: a trunk (the hull of elliptic rings along it), neck and head, ears, a tail,
    and four two-segment legs (parts 1–4 upper, 5–8 lower, as a person's) that walk."""
    q = QUADRUPEDS[o.category]
    sx, sy, sz = quadruped_scale(o)
    k = o.track_id
    coat = o.tint

    def Q(x: float, h: float, z: float) -> np.ndarray:
        return P(x * sx, h * sy, z * sz)

    # trunk: rings from rump to chest, their height following the back line, ends rounded
    zs = np.linspace(q.trunk[0], q.trunk[1], 7)
    ang = np.arange(8) * np.pi / 4 + np.pi / 8
    pts = []
    for z in zs:
        f = (z - q.trunk[0]) / (q.trunk[1] - q.trunk[0])
        top = q.back[0] + f * (q.back[1] - q.back[0])
        end = max(0.55, np.sqrt(max(0.0, 1 - (2 * f - 1) ** 8)))  # blunt ends
        mid, half = (top + q.belly) / 2, (top - q.belly) / 2 * end
        for a in ang:
            pts.append(Q(np.cos(a) * q.trunk_w / 2 * end, mid + np.sin(a) * half, z))
    fl.convex(np.array(pts) * rng.uniform(0.985, 1.015, (len(pts), 3)), "hair", coat, k)
    (nz0, nh0), (nz1, nh1), nw = q.neck
    fl.tube(Q(0, nh0, nz0), Q(0, nh1, nz1), nw * sx, "hair", coat, k, half_d=nw * 1.2 * sz)
    (hz, hh), (hx, hy, hl), pitch = q.head
    d = rng.normal(size=(16, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    head = d * [hx, hy, hl]
    head[:, 0] *= np.where(head[:, 2] > 0, 0.7, 1.0)  # the muzzle narrows
    c, s = np.cos(pitch), np.sin(pitch)
    head = head @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]]).T  # nose down
    fl.convex(head * [sx, sy, sz] + Q(0, hh, hz), "hair", coat, k)
    for side in (-1, 1):  # ears
        base = Q(side * hx * 0.6, hh + hy * 0.7, hz - hl * 0.55)
        fl.tube(base, base + np.array([side * 0.05 * sx, -0.075 * sy, -0.03 * sz]), 0.025 * sx, "hair", coat, k,
                half_d=0.008)
    if o.category == "deer":  # the white rump patch, a stub of a tail
        fl.box(Q(0, (q.back[0] + q.belly) / 2 + 0.05, q.trunk[0] + 0.015), (0.08 * sx, 0.08 * sy, 0.02 * sz),
               np.eye(3), {"all": "fabric"}, RUMP_PATCH, k, skip=())
    else:  # a thin tail hanging from the rump
        fl.tube(Q(0, q.back[0] - 0.03, q.trunk[0] + 0.02), Q(0, q.back[0] - 0.3, q.trunk[0] - 0.02), 0.012 * sx,
                "hair", coat, k)
    # legs: hind (−z) and fore (+z), left and right; upper legs are parts 1–4, lower legs 5–8
    for i, (z, side) in enumerate(((q.legs_z[0], -1), (q.legs_z[0], 1), (q.legs_z[1], -1), (q.legs_z[1], 1))):
        x = side * q.legs_x
        uw, lw = q.leg_w
        fl.frustum(Q(x, q.knee_h, z), Q(x, q.joint_h + 0.06, z), (uw * 0.7 * sx, uw * 0.8 * sz),
                   (uw * sx, uw * 1.4 * sz), np.eye(3), "hair", coat, k, 1 + i, caps=(False, False))
        fl.frustum(Q(x, 0.05, z), Q(x, q.knee_h + 0.02, z), (lw * sx, lw * sz), (lw * 1.2 * sx, lw * 1.3 * sz),
                   np.eye(3), "hair", coat, k, 5 + i, caps=(False, False))
        fl.box(Q(x, 0.025, z + 0.01), (lw * 1.1 * sx, 0.025 * sy, lw * 1.5 * sz), np.eye(3), {"all": "rubber"},
               HOOF, k, part=5 + i, skip=("bottom",))
    _shadow(fl, o.size[0] / 2 + 0.05, 0.45 * o.size[2])


def quadruped_poses(o: Obj, walked: float) -> tuple[np.ndarray, np.ndarray]:
    """Rigid motion (R (9,3,3), t (9,3)) of a quadruped's parts: a lateral-sequence walk (hind
    left, fore left, hind right, fore right, a quarter cycle apart) by the distance travelled,
    the middle joint flexing in the swing, the body bobbing so the lowest hoof is on the ground;
    a static animal stands in the rest pose."""
    R = np.repeat(np.eye(3)[None], N_PARTS, 0)
    t = np.zeros((N_PARTS, 3))
    if o.motion.kind == "static":
        return R, t
    q = QUADRUPEDS[o.category]
    sx, sy, sz = quadruped_scale(o)
    phase = 2 * np.pi * walked / (q.stride * sz)
    low = []
    for i, (z, side, off) in enumerate(((q.legs_z[0], -1, 0.0), (q.legs_z[1], -1, 0.25), (q.legs_z[0], 1, 0.5),
                                        (q.legs_z[1], 1, 0.75))):
        upper, lower = (1, 5) if i == 0 else (3, 7) if i == 1 else (2, 6) if i == 2 else (4, 8)
        x, p = side * q.legs_x * sx, phase + 2 * np.pi * off
        hip, knee = np.array([x, -q.joint_h * sy, z * sz]), np.array([x, -q.knee_h * sy, z * sz])
        Ru = rot_x(q.swing * np.sin(p))
        R[upper], t[upper] = Ru, hip - Ru @ hip
        Rl = rot_x(-(0.05 + 0.8 * max(0.0, np.cos(p + 0.25)) ** 2))  # flexes while the leg swings forward
        R[lower], t[lower] = Ru @ Rl, Ru @ (knee - Rl @ knee) + t[upper]
        for dz in (-0.03, 0.03):  # heel and toe of the hoof
            low.append(-(R[lower] @ np.array([x, 0.0, z * sz + dz]) + t[lower])[1])
    t[:, 1] += min(low)  # the lowest hoof on the ground: the body bobs
    return R, t


def trolley_faces(fl: FaceList, o: Obj, rng: np.random.Generator) -> None:
    """A shopping trolley: a wire basket tapering to the front over a wire floor, a plastic handle
    behind, a U-shaped chassis on four castors with a wire tray. Nearly all of it is wire, so the
    trolley is see-through: most of its box shows what lies behind it."""
    w, h, l = o.size
    sx, sy, sz = w / 0.58, h / 1.0, l / 0.95  # ours: a 100–125 l supermarket trolley, ~0.58 × 1.0 × 0.95 m
    k = o.track_id
    chrome = (0.92, 0.92, 0.95)

    def Q(x, hh, z):
        return P(x * sx, hh * sy, z * sz)

    def wire(a, b, r=0.0045):  # ours: 4–6 mm steel wire (drawn ~9 mm: a pixel where it matters)
        fl.tube(a, b, r, "metal", chrome, k, half_d=r)

    # the basket's corners: rear top, front top, front bottom, rear bottom (x at +: mirrored)
    rt, ft, fb, rb = (0.28, 0.93, -0.41), (0.24, 0.93, 0.46), (0.2, 0.53, 0.4), (0.24, 0.56, -0.33)
    for side in (-1, 1):
        c = [Q(side * x, hh, z) for x, hh, z in (rt, ft, fb, rb)]
        for f in np.linspace(0, 1, 4):  # rails, the top one the rim
            wire(c[3] + f * (c[0] - c[3]), c[2] + f * (c[1] - c[2]), 0.007 if f == 1 else 0.0045)
        for f in np.linspace(0, 1, 9):  # uprights ~10 cm apart (ours: real ones ~4–5 cm; sparser, as a camera
            # beyond 10 m blurs them into one: each wire here is drawn at least a pixel wide)
            wire(c[3] + f * (c[2] - c[3]), c[0] + f * (c[1] - c[0]))
    for (xa, ha, za), (xb, hb, zb), n in ((fb, ft, 5), (rb, rt, 6)):  # front panel, rear gate
        for f in np.linspace(-1, 1, n):
            wire(Q(f * xa, ha, za), Q(f * xb, hb, zb))
        for g in np.linspace(0, 1, 3):
            a = np.array([xa + g * (xb - xa), ha + g * (hb - ha), za + g * (zb - za)])
            wire(Q(-a[0], a[1], a[2]), Q(a[0], a[1], a[2]), 0.007 if g == 1 else 0.0045)
    for f in np.linspace(-1, 1, 5):  # the floor: wires along, and across
        wire(Q(f * rb[0], rb[1], rb[2]), Q(f * fb[0], fb[1], fb[2]))
    for g in np.linspace(0.25, 0.75, 2):
        a = np.array(rb) + g * (np.array(fb) - np.array(rb))
        wire(Q(-a[0], a[1], a[2]), Q(a[0], a[1], a[2]))
    # handle: a plastic bar behind the rim on two arms
    hx, hh, hz = 0.27, 1.0, -0.47
    fl.tube(Q(-hx, hh, hz), Q(hx, hh, hz), 0.016, "trim", o.tint, k, across=(0, 0, 1))
    # chassis: a U of tube near the ground, uprights to the basket's rear, struts to its floor, a wire tray
    base_h, (bx_r, bz_r), (bx_f, bz_f) = 0.13, (0.25, -0.4), (0.17, 0.42)
    for side in (-1, 1):
        wire(Q(side * hx, hh, hz), Q(side * rt[0], rt[1], rt[2]), 0.01)
        wire(Q(side * bx_r, base_h, bz_r), Q(side * bx_f, base_h, bz_f), 0.011)
        wire(Q(side * bx_r, base_h, bz_r), Q(side * hx, hh, hz), 0.011)
        wire(Q(side * bx_f, base_h, bz_f), Q(side * fb[0], fb[1], fb[2]), 0.008)
    wire(Q(-bx_f, base_h, bz_f), Q(bx_f, base_h, bz_f), 0.011)
    for g in np.linspace(0.2, 0.8, 4):  # the lower tray
        x, z = bx_r + g * (bx_f - bx_r), bz_r + g * (bz_f - bz_r)
        wire(Q(-x, base_h + 0.04, z), Q(x, base_h + 0.04, z))
    r = 0.0625 * sy  # ours: 125 mm castors
    for x, z in ((bx_r, bz_r + 0.04), (bx_f, bz_f - 0.04)):
        for side in (-1, 1):
            wheel(fl, side, x * sx + 0.015, z * sz, r, 0.03, (0.5, 0.5, 0.52), k, n=8, tread="full")
            fl.tube(Q(side * x, base_h, z), P(side * x * sx, r, z * sz), 0.008, "metal", chrome, k)
    _shadow(fl, 0.2 * sx, 0.4 * sz)


EURO_PALLET_M = (0.8, 0.144, 1.2)  # EPAL / EN 13698-1: 800 × 1200 mm, 144 mm high


def pallet_faces(fl: FaceList, o: Obj, rng: np.random.Generator) -> None:
    """A Euro pallet lying flat: five deck boards (lengthwise, with gaps), three cross boards
    under them on nine blocks, three bottom boards (EN 13698-1's layout, 22 + 22 + 78 + 22 mm)."""
    w, h, l = o.size
    k = o.track_id
    wood = tuple(np.array(o.tint))
    I = np.eye(3)
    sx, sy, sz = w / EURO_PALLET_M[0], h / EURO_PALLET_M[1], l / EURO_PALLET_M[2]
    wood_mats = {"all": "timber"}

    def board(x, y0, z, hx, hy, hz):  # a box of half sizes (hx, hy, hz), bottom at height y0
        fl.box([x * sx, -(y0 + hy) * sy, z * sz], (hx * sx, hy * sy, hz * sz), I, wood_mats,
               tuple(np.clip(np.array(wood) * rng.uniform(0.85, 1.1), 0, 1)), k, skip=("bottom",))

    widths = (0.145, 0.1, 0.145, 0.1, 0.145)  # deck boards, mm / 1000
    gap = (0.8 - sum(widths)) / 4
    x = -0.4
    for bw in widths:
        board(x + bw / 2, 0.122, 0.0, bw / 2, 0.011, 0.6)
        x += bw + gap
    for z in (-0.5275, 0.0, 0.5275):
        board(0.0, 0.1, z, 0.4, 0.011, 0.0725)
        for xb in (-0.3275, 0.0, 0.3275):
            board(xb, 0.022, z, 0.0725 if xb == 0.0 else 0.05, 0.039, 0.0725)
    for xb in (-0.3275, 0.0, 0.3275):
        board(xb, 0.0, 0.0, 0.0725 if xb == 0.0 else 0.05, 0.011, 0.6)
    _shadow(fl, w / 2 + 0.04, l / 2 + 0.04)


def sack_faces(fl: FaceList, o: Obj, rng: np.random.Generator) -> None:
    """A filled sack lying flat (cement, feed, grain: 25–50 kg): a pillow, the hull of a rounded
    slab, its ends pinched."""
    w, h, l = o.size
    u = np.linspace(-1, 1, 7)
    pts = []
    for a in u:
        for b in u:
            edge = max(abs(a), abs(b))
            if edge < 0.99 and abs(a) > 1e-9 and abs(b) > 1e-9 and rng.random() < 0.6:
                continue  # the inside of the grid adds nothing to the hull but its top
            pinch = 1 - 0.25 * abs(b) ** 3  # the ends are pinched (sewn or folded)
            top = h * (1 - a * a) ** 0.5 * (1 - b ** 4) ** 0.5 * rng.uniform(0.93, 1.0)
            pts.append([a * w / 2 * pinch, -max(top, 0.02 * h), b * l / 2])
            pts.append([a * w / 2 * pinch * 1.02, 0.0, b * l / 2])
    fl.convex(np.array(pts), "fabric", o.tint, o.track_id)
    _shadow(fl, w / 2 + 0.03, l / 2 + 0.03)


def build_mesh(o: Obj, atlas: Atlas) -> tuple[np.ndarray, np.ndarray]:
    """The object's faces in its own frame (built once; pure function of the object)."""
    fl = FaceList(atlas, o.material)
    rng = np.random.default_rng(o.seed)
    w, h, l = o.size
    I = np.eye(3)
    k = o.track_id
    off = tuple(rng.uniform(0, 2, 2))
    cat = o.category
    if cat == "car":
        car_faces(fl, o, rng)
    elif cat == "truck":
        truck_faces(fl, o, rng)
    elif cat == "bus":
        bus_faces(fl, o, rng)
    elif cat == "person":
        person_faces(fl, o, rng)
    elif cat == "bicycle":
        bicycle_faces(fl, o, rng)
    elif cat == "cone":
        ang = np.arange(8) * np.pi / 4
        rb, rt = 0.16, 0.03
        for i in range(8):
            a0, a1 = ang[i], ang[(i + 1) % 8]
            p = np.array([[rb * np.cos(a0), -0.04, rb * np.sin(a0)], [rb * np.cos(a1), -0.04, rb * np.sin(a1)],
                          [rt * np.cos(a1), -h, rt * np.sin(a1)], [rt * np.cos(a0), -h, rt * np.sin(a0)]])
            am = 0.5 * (a0 + a1)
            fl.poly(p[[3, 2, 1, 0]], (np.cos(am), -0.2, np.sin(am)), "cone", (1, 1, 1), k)
        fl.box([0, -0.02, 0], (0.2, 0.02, 0.2), I, {"all": "paint"}, (0.1, 0.1, 0.1), k)
    elif cat == "bin":
        fl.box([0, -(h - 0.08) / 2, 0], (w / 2 - 0.03, (h - 0.08) / 2, l / 2 - 0.03), I, {"all": "bin"}, o.tint, k, offset=off)
        fl.box([0, -(h - 0.04), 0], (w / 2, 0.04, l / 2), I, {"all": "paint"}, o.tint, k, skip=())
        for sx in (-1, 1):
            wheel(fl, sx, w / 2 - 0.02, -l / 2 + 0.1, 0.1, 0.05, (0.3, 0.3, 0.3), k, n=8)
    elif cat == "crate":
        fl.box([0, -h / 2, 0], (w / 2, h / 2, l / 2), I, {"all": "crate"}, tuple(np.array(o.tint) * 0.3 + 0.7), k)
    elif cat == "debris":
        lump_faces(fl, o, rng, "stone", 14, 0.8, off)
    elif cat == "blob":
        lump_faces(fl, o, rng, "mottled", 22, 0.92, off)
    elif cat == "tyre":
        tyre_faces(fl, o, rng)
    elif cat == "barrier":
        barrier_faces(fl, o, rng)
    elif cat == "box":
        box_faces(fl, o, rng)
    elif cat == "branch":
        branch_faces(fl, o, rng)
    elif cat == "cart":
        cart_faces(fl, o, rng)
    elif cat == "tortoise":
        tortoise_faces(fl, o, rng)
    elif cat in QUADRUPEDS:
        quadruped_faces(fl, o, rng)
    elif cat == "trolley":
        trolley_faces(fl, o, rng)
    elif cat == "pallet":
        pallet_faces(fl, o, rng)
    elif cat == "sack":
        sack_faces(fl, o, rng)
    else:
        raise KeyError(f"no mesh for category {cat!r}")
    V, R = fl.arrays()
    if o.material:  # one material: one colour too (a textureless object is uniform but for its shading)
        R[R[:, R_OBJ] == k, R_TINT : R_TINT + 3] = o.tint
    return V, R

