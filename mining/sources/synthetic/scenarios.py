"""Staged scenarios of the synthetic source: one failure mode of tube mining each (issue 9).

A scenario replaces the random traffic of a world (``Scene._build_objects``) with objects
placed on purpose, each with a specific motion, and the ego's random drive with a fixed
speed profile; the rest stays the seed's (the road's gentle bends, buildings, trees, light,
exposure). The road keeps its gentle bends but has no sharp turns. Everything is a pure
function of (scenario, seed, length), so a scenario renders the same bits every time and any
length works: the builders repeat their event over the whole duration.

Every staged object has a ``Role``: ``moving`` (a target: what the scenario is about) or
``parked`` (a static reference seen at similar range, so moving and parked recall can be
compared in one scene). In the scenarios of static things (parkedpair, barriers, verge, debris,
farbarrier, spill)
every staged object is ``parked``; the note says which are the targets, and the known/unknown
split tells the barriers and debris from the cars. Staged background (``verge``'s hedge, fence
and grass, ``roadside.py``) is no object at all: static faces with no truth.

Map coordinates are road coordinates: arc length s (the ego starts at s = 0 and moves to +s)
and lateral offset d (right of the centreline > 0; traffic keeps right, so lanes with d > 0
drive to +s and lanes with d < 0 are oncoming).

Choose one with the source option ``scenario`` (e.g. ``--option scenario=border``):

========== ==================================================================================
alongside  cars in the right lane keeping pace with the ego (ego speed, ~8 and ~22 m ahead)
oncoming   oncoming cars in both oncoming lanes (closing at ~18 and ~21 m/s)
border     a car overtaking from behind-right at 14 m/s (ego 10 m/s): it enters at the right
           image border and passes 5–9 m ahead (the issue's KITTI failure)
crossing   pedestrians crossing the road, in the ego's lane 10–16 m ahead of it (1.2–1.6 m/s,
           across; the ego drives at 3 m/s), and people standing on the sidewalks
far        cars moving with the ego at 30–60 m and parked cars passing through 30–60 m
textureless uniformly coloured ("flat" material) cars moving slowly, and parked ones
stopgo     a car ahead that brakes to a stop, waits and pulls away again (every 10 s), and a
           pedestrian on the far sidewalk who stops and walks on
parkedpair pairs of parked cars nose to tail, ~1 m apart (the nearer hides part of the other),
           every 18 m on alternate sides; the ego at 6 m/s keeps a whole pair in 35–55 m ~80 %
           of the time
barriers   rows of 4–8 construction barriers (unknown: striped boards on trestles, or concrete
           kerb barriers) with small gaps in the right parking strip, a row every 40 m, seen at
           8–30 m (ego 6 m/s); parked cars on the left
verge      roadside clutter as background (no truth): a grass verge with tufts, a post-and-rail
           fence with gaps and a clipped hedge 1.2–1.9 m tall behind it, the right side's lots
           set back; a few ordinary parked cars as references (ego 8 m/s)
debris     small unknown debris (a box, a rock, a tyre and a branch, the last two just beyond a
           parked car) on the left of the road, each in view (≥ 100 px at full resolution)
           only 5–8 frames as the ego passes at 14 m/s, between ~25 and ~13 m
farbarrier pairs of rows of 6–8 construction barriers (unknown), concrete kerb barriers joined
           in the right strip and boards on trestles 0.8–1.5 m apart in the left one (2 lanes),
           a pair every 60 m, the first at ~31 m; scored at 30–40 m, the rows run on past 40 m
           (ego 4 m/s); issue 29
spill      a fallen load (unknown): a Euro pallet, three sacks and a crate strewn over ~6 m of
           the right lane, one every 55 m, the first ~36 m ahead; the ego passes in the left
           lane at 8 m/s; parked cars on the left; issue 29
animal     roe deer and wild boar (unknown: no COCO class) walking across the road, one every
           3 s at 1.0–1.6 m/s, 13–19 m ahead of the ego while in its lane (ego 5 m/s), the
           first already on the road; a deer standing at the right roadside; issue 29
trolley    wire shopping trolleys (unknown, see-through): two left standing (right strip, left
           sidewalk), one rolling slowly across the right strip, one pushed by a person along
           the right sidewalk towards the ego (ego 5 m/s); issue 29
========== ==================================================================================
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mining.errors import InputError
from mining.sources.synthetic.roadside import BACK_M, build_roadside
from mining.sources.synthetic.scene import SIDEWALK_M, VIEW_AHEAD_M, VIEW_BEHIND_M, Motion, Obj, Scene
from mining.sources.synthetic.textures import LANE_M, PARKING_M


@dataclass(frozen=True)
class Role:
    """What a staged object is for."""

    role: str  # "moving": a target of the scenario; "parked": a static object (a reference, or a static target)
    note: str  # how it was staged, in words
    textureless: bool = False  # drawn in the uniform "flat" material


@dataclass(frozen=True)
class Scenario:
    """How to stage one scenario (see the module docstring for the list)."""

    name: str
    summary: str
    lanes: int  # lanes per direction
    ego_lane: int  # 0: the inner lane of the ego's direction
    ego_speed: tuple[tuple[float, ...], tuple[float, ...]]  # knots (times s, speeds m/s), linear between
    build: Callable[[Scene, np.random.Generator], dict[int, Role]]  # places the objects, returns their roles
    n_frames: int = 80  # ours: the bench's default length (10 Hz)
    band_m: tuple[float, float] | None = None  # targets count only while their centre lies this deep (camera z)
    right_setback_m: float = 0.0  # the right side's lots stand this much further back (room for a staged roadside)


def lane_d(k: int, direction: int = 1) -> float:
    """Lateral offset of lane ``k`` (0 = inner) driving to +s (``direction`` 1) or oncoming (−1)."""
    return direction * (LANE_M / 2 + k * LANE_M)


def strip_d(scene: Scene, side: int) -> float:
    """Lateral offset of the parking strip on ``side`` (1 right, −1 left)."""
    return side * (scene.lanes * LANE_M + PARKING_M / 2)


class _Stage:
    """Adds objects to a scene and records their roles."""

    def __init__(self, scene: Scene, rng: np.random.Generator):
        self.scene, self.rng = scene, rng
        self.roles: dict[int, Role] = {}

    def add(self, category: str, motion: Motion, role: str, note: str, textureless: bool = False,
            shape: str | None = None, size: tuple[float, float, float] | None = None) -> Obj:
        o = self.scene.add_object(self.rng, category, motion, size, shape=shape)
        if textureless:
            o.material = "flat"
        self.roles[o.track_id] = Role(role, note, textureless)
        return o

    def parked_row(self, side: int, s_from: float, s_to: float, gap: tuple[float, float], skip=(),
                   skip_m: float = 4.0) -> None:
        """Parked cars along one parking strip, ``gap`` metres apart (uniform range); none
        within ``skip_m`` of an arc length in ``skip``."""
        s = s_from + self.rng.uniform(0, 2)
        while s < s_to:
            if all(abs(s - x) > skip_m for x in skip):
                yaw = (0.0 if side > 0 else np.pi) + self.rng.normal(0, 0.03)
                self.add("car", Motion("static", s0=s, d=strip_d(self.scene, side), yaw=yaw), "parked",
                         f"parked, {'right' if side > 0 else 'left'} strip")
            s += self.rng.uniform(*gap)

    @property
    def end_s(self) -> float:
        """The ego's arc length at the end of the scene."""
        return self.scene.ego_arc(self.scene.duration)


def _alongside(scene: Scene, rng: np.random.Generator) -> dict[int, Role]:
    st = _Stage(scene, rng)
    for gap, amp, rate in ((8.0, 0.6, 0.3), (22.0, 1.0, 0.2)):
        g = gap + rng.uniform(-0.5, 0.5)
        st.add("car", Motion("follow", d=lane_d(1) + rng.normal(0, 0.05), gap=(g, amp, rate)), "moving",
               f"alongside at ego speed, right lane, {g:.0f} ± {amp:.1f} m ahead")
    st.parked_row(-1, 12.0, st.end_s + 60.0, (16.0, 28.0))  # the left strip: the alongside cars hide the right one
    return st.roles


def _oncoming(scene: Scene, rng: np.random.Generator) -> dict[int, Role]:
    st = _Stage(scene, rng)
    T = scene.duration
    for k, v, first, gap in ((0, -10.0, 45.0, (35.0, 50.0)), (1, -13.0, 70.0, (50.0, 70.0))):
        s = first + rng.uniform(0, 5)
        while s < (abs(v) + 8.0) * T + 20.0:  # every car that meets the ego within the scene
            st.add("car", Motion("lane", s0=s, d=lane_d(k, -1) + rng.normal(0, 0.05), v=v, yaw=np.pi), "moving",
                   f"oncoming at {abs(v):.0f} m/s, oncoming lane {k}")
            s += rng.uniform(*gap)
    st.parked_row(1, 12.0, st.end_s + 60.0, (16.0, 28.0))
    return st.roles


def _border(scene: Scene, rng: np.random.Generator) -> dict[int, Role]:
    st = _Stage(scene, rng)
    T, v, v_ego = scene.duration, 14.0, 10.0
    k = 0
    while (8.0 + 40.0 * k) / (v - v_ego) < T:  # one overtaking car every 10 s, the first level with the camera at 2 s
        s0 = -8.0 - 40.0 * k + rng.uniform(-0.5, 0.5)
        st.add("car", Motion("lane", s0=s0, d=lane_d(1) + rng.normal(0, 0.05), v=v), "moving",
               f"overtaking from behind-right at {v:.0f} m/s, right lane (ego {v_ego:.0f} m/s)")
        k += 1
    st.parked_row(-1, 12.0, st.end_s + 60.0, (16.0, 28.0))
    return st.roles


def _crossing(scene: Scene, rng: np.random.Generator) -> dict[int, Role]:
    st = _Stage(scene, rng)
    T, h = scene.duration, scene.half
    walk_in = 6.0  # ours: metres walked along the sidewalk before and after the crossing
    crossings = []
    t = 0.3
    while t < T:
        direction = int(rng.choice([-1, 1]))
        speed = rng.uniform(1.2, 1.6)
        d0, d1 = -direction * (h + 2.0), direction * (h + 2.0)
        t_lane = t + abs(scene.ego_d - d0) / speed  # in the ego's lane then: well ahead of the ego
        s_c = scene.ego_arc(t_lane) + rng.uniform(10.0, 16.0)
        sign = int(rng.choice([-1, 1]))
        t_cross = abs(d1 - d0) / speed
        times = np.array([t - walk_in / speed, t, t + t_cross, t + t_cross + walk_in / speed])
        ss = np.array([s_c - sign * walk_in, s_c, s_c, s_c + sign * walk_in])
        st.add("person", Motion("path", times=times, ss=ss, dd=np.array([d0, d0, d1, d1])), "moving",
               f"crossing {'left to right' if direction > 0 else 'right to left'} at {speed:.1f} m/s")
        crossings.append(s_c)
        t += 2.2
    for s, side in ((18.0, 1), (30.0, -1)):
        st.add("person", Motion("static", s0=s + rng.uniform(-1, 1), d=side * (h + 1.5), yaw=-side * np.pi / 2),
               "parked", "standing on the sidewalk, facing the road")
    st.parked_row(1, 10.0, st.end_s + 50.0, (10.0, 20.0), skip=crossings, skip_m=12.0)
    return st.roles


def _far(scene: Scene, rng: np.random.Generator) -> dict[int, Role]:
    st = _Stage(scene, rng)
    for k, gap, amp, rate in ((0, 42.0, 5.0, 0.2), (1, 34.0, 2.0, 0.25), (1, 55.0, 3.0, 0.15)):
        g = gap + rng.uniform(-1, 1)
        st.add("car", Motion("follow", d=lane_d(k) + rng.normal(0, 0.05), gap=(g, amp, rate)), "moving",
               f"moving with the ego, lane {k}, {g - amp:.0f}–{g + amp:.0f} m ahead")
    st.parked_row(-1, 30.0, st.end_s + 62.0, (10.0, 16.0))
    return st.roles


def _textureless(scene: Scene, rng: np.random.Generator) -> dict[int, Role]:
    st = _Stage(scene, rng)
    st.add("car", Motion("lane", s0=36.0 + rng.uniform(-1, 1), d=lane_d(1), v=2.5), "moving",
           "textureless, 2.5 m/s, right lane (the ego overtakes it)", textureless=True)
    st.add("car", Motion("lane", s0=62.0 + rng.uniform(-1, 1), d=lane_d(0, -1), v=-3.0, yaw=np.pi), "moving",
           "textureless, oncoming at 3 m/s", textureless=True)
    for s in (28.0, 48.0):
        st.add("car", Motion("static", s0=s + rng.uniform(-1, 1), d=strip_d(scene, -1), yaw=np.pi), "parked",
               "textureless, parked, left strip", textureless=True)
    st.add("crate", Motion("static", s0=40.0 + rng.uniform(-1, 1), d=strip_d(scene, 1), yaw=rng.uniform(0, 3)),
           "parked", "textureless crate, right strip", textureless=True)
    st.parked_row(-1, 20.0, st.end_s + 60.0, (16.0, 24.0), skip=(28.0, 48.0))
    return st.roles


def _stop_and_go(times: tuple[float, ...], speeds: tuple[float, ...], period: float, T: float):
    """Knots of one stop-and-go cycle repeated every ``period`` seconds over [0, T]."""
    tt, vv = [], []
    c = 0.0
    while c <= T:
        tt += [c + x for x in times]
        vv += list(speeds)
        c += period
    return np.array(tt), np.array(vv)


def _stopgo(scene: Scene, rng: np.random.Generator) -> dict[int, Role]:
    st = _Stage(scene, rng)
    T = scene.duration
    times, speeds = _stop_and_go((0.0, 2.0, 3.5, 6.0, 7.5), (8.0, 8.0, 0.0, 0.0, 8.0), 10.0, T)
    st.add("car", Motion("speed", s0=16.0 + rng.uniform(-1, 1), d=lane_d(1), times=times, vs=speeds), "moving",
           "right lane: 8 m/s, brakes to a stop at 3.5 s, waits 2.5 s, pulls away (every 10 s)")
    times, speeds = _stop_and_go((0.0, 2.0, 2.5, 4.5, 5.0), (1.4, 1.4, 0.0, 0.0, 1.4), 8.0, T)
    st.add("person", Motion("speed", s0=28.0 + rng.uniform(-1, 1), d=-(scene.half + 2.3), times=times, vs=speeds),
           "moving", "walking on the left sidewalk at 1.4 m/s, stops 2 s (every 8 s)")
    st.parked_row(-1, 45.0, st.end_s + 60.0, (16.0, 24.0))
    return st.roles


PAIR_GAP_M = (0.8, 1.2)  # ours: bumper to bumper within a parked pair, uniform range (the "~1 m")
PAIR_PITCH_M = 18.0  # ours: a pair every 18 m, on alternate sides: at 6 m/s a whole pair lies in 35–55 m ~80 % of the time


def _parkedpair(scene: Scene, rng: np.random.Generator) -> dict[int, Role]:
    st = _Stage(scene, rng)
    s, k = 37.0 + rng.uniform(0, 1), 0  # ours: the first pair starts inside the band
    while s < st.end_s + 60.0:
        side = -1 if k % 2 == 0 else 1  # the left strip first: seen at a wider angle, the rear car less hidden
        where = "left" if side < 0 else "right"
        yaw = 0.0 if side > 0 else np.pi
        near = st.add("car", Motion("static", s0=s, d=strip_d(scene, side), yaw=yaw + rng.normal(0, 0.02)), "parked",
                      f"parked pair {k}, nearer car, {where} strip")
        far = st.add("car", Motion("static", d=strip_d(scene, side) + rng.normal(0, 0.05), yaw=yaw + rng.normal(0, 0.02)),
                     "parked", f"parked pair {k}, farther car, {where} strip, ~1 m behind the nearer one")
        far.motion.s0 = s + near.size[2] / 2 + rng.uniform(*PAIR_GAP_M) + far.size[2] / 2  # nose to tail
        s += PAIR_PITCH_M + rng.uniform(-1, 1)
        k += 1
    return st.roles


BARRIER_GAP_M = (0.2, 0.5)  # ours: gaps within a row of construction barriers, uniform range
BARRIER_ROW_PITCH_M = 40.0  # ours: a row every 40 m (at 6 m/s: one row in 8–30 m most of the time)
BARRIERS_PER_ROW = (4, 8)  # the issue: 4–8 in a row


def _barriers(scene: Scene, rng: np.random.Generator) -> dict[int, Role]:
    st = _Stage(scene, rng)
    s_row, k = 18.0 + rng.uniform(0, 1), 0  # ours: the first row starts inside the band
    while s_row < st.end_s + 60.0:
        shape = "board" if k % 2 == 0 else "jersey"  # red-and-white boards on trestles; concrete kerb barriers
        n = int(rng.integers(BARRIERS_PER_ROW[0], BARRIERS_PER_ROW[1] + 1))
        d = strip_d(scene, 1) + 0.4  # ours: in the right parking strip, near the curb
        s = s_row
        for j in range(n):
            o = st.add("barrier", Motion("static", d=d + rng.normal(0, 0.04), yaw=rng.normal(0, 0.03)), "parked",
                       f"construction barrier row {k} ({shape}), {j + 1} of {n}, right strip", shape=shape)
            o.motion.s0 = s + o.size[2] / 2
            s += o.size[2] + rng.uniform(*BARRIER_GAP_M)
        s_row += BARRIER_ROW_PITCH_M + rng.uniform(-2, 2)
        k += 1
    st.parked_row(-1, 15.0, st.end_s + 60.0, (14.0, 24.0))
    return st.roles


# ours: the debris kinds, each (category, shape, size w × h × l m, lateral offset d m, behind a parked car);
# sizes fixed so each reaches 100 px (full resolution) at a known distance, and d so it leaves the image's
# left border at 13–17 m: in view (≥ 100 px) 5–8 frames at the ego's 14 m/s (tuned by rendering seeds
# 0000–0004). A tyre, and a branch with its leaves, would reach 100 px too far away for that: they lie
# just beyond a car parked in the left strip, which hides them until the ego is near.
DEBRIS_KINDS = (
    ("box", None, (0.26, 0.21, 0.26), -5.6, False),
    ("tyre", "lying1", None, -8.1, True),
    ("branch", None, (0.6, 0.21, 0.7), -8.1, True),  # (its mesh needs w ≥ 0.6, h > 0.2)
    ("debris", None, (0.55, 0.35, 0.62), -5.6, False),
)
DEBRIS_PITCH_M = 35.0  # ours: one piece every 35 m (2.5 s at 14 m/s): no two in view at once
DEBRIS_BEHIND_M = 1.5  # ours: from the hiding car's bumper to the piece beyond it (tuned with DEBRIS_KINDS)


def _debris(scene: Scene, rng: np.random.Generator) -> dict[int, Role]:
    st = _Stage(scene, rng)
    s, k = 32.0 + rng.uniform(0, 1), 0  # ours: the first piece comes into view within the first second
    while s < st.end_s + 60.0:
        kind, shape, size, d, hidden = DEBRIS_KINDS[k % len(DEBRIS_KINDS)]
        o = st.add(kind, Motion("static", s0=s, d=d, yaw=rng.normal(0, 0.1)), "parked",
                   f"{kind} lying on the road, left{', beyond a parked car' if hidden else ''}: in view only briefly",
                   shape=shape, size=size)
        if hidden:
            car = st.add("car", Motion("static", d=strip_d(scene, -1), yaw=np.pi + rng.normal(0, 0.02)), "parked",
                         f"parked, left strip: hides the {kind} beyond it until the ego is near")
            car.motion.s0 = s - o.size[2] / 2 - DEBRIS_BEHIND_M - car.size[2] / 2
        s += DEBRIS_PITCH_M + rng.uniform(-1, 1)
        k += 1
    return st.roles


def _verge(scene: Scene, rng: np.random.Generator) -> dict[int, Role]:
    st = _Stage(scene, rng)
    build_roadside(scene, rng, -VIEW_BEHIND_M - 5.0, st.end_s + VIEW_AHEAD_M + 10.0)
    st.parked_row(1, 20.0, st.end_s + 60.0, (30.0, 45.0))  # a couple of ordinary cars in front of the clutter
    st.parked_row(-1, 30.0, st.end_s + 60.0, (25.0, 40.0))
    return st.roles


# ---- issue 29: unknown kinds the random worlds lack, each staged on its own

FAR_BARRIER_PITCH_M = 60.0  # ours: a pair of rows every 60 m (a row of 6–8 is 10–25 m long): rows in 30–40 m most of the time
FAR_BARRIERS_PER_ROW = (6, 8)  # ours: longer rows than ``barriers``', so a row reaches out past 40 m
BOARD_GAP_M = (0.8, 1.5)  # ours: boards on trestles stand apart (concrete kerb barriers join: BARRIER_GAP_M)


def _farbarrier(scene: Scene, rng: np.random.Generator) -> dict[int, Role]:
    st = _Stage(scene, rng)
    s_row, k = 31.0 + rng.uniform(0, 1), 0  # ours: the first rows start at the band's near end
    while s_row < st.end_s + 80.0:
        # a pair of rows: concrete kerb barriers in the right strip, boards on trestles in the left one
        # (seen across the oncoming lanes, at a wider angle: less hidden by each other)
        for side, shape, gap, start in ((1, "jersey", BARRIER_GAP_M, s_row), (-1, "board", BOARD_GAP_M,
                                                                          s_row + rng.uniform(0, 4))):
            n = int(rng.integers(FAR_BARRIERS_PER_ROW[0], FAR_BARRIERS_PER_ROW[1] + 1))
            d = strip_d(scene, side) + side * 0.4  # ours: near the curb
            s = start
            for j in range(n):
                o = st.add("barrier", Motion("static", d=d + rng.normal(0, 0.04), yaw=rng.normal(0, 0.03)), "parked",
                           f"construction barrier row {k} ({shape}), {j + 1} of {n}, "
                           f"{'right' if side > 0 else 'left'} strip, seen out to 40 m and beyond", shape=shape)
                o.motion.s0 = s + o.size[2] / 2
                s += o.size[2] + rng.uniform(*gap)
            k += 1
        s_row += FAR_BARRIER_PITCH_M + rng.uniform(-2, 2)
    return st.roles


SPILL_PITCH_M = 55.0  # ours: a spilled load every 55 m (at 8 m/s one in 15–40 m most of the time)


def _spill(scene: Scene, rng: np.random.Generator) -> dict[int, Role]:
    st = _Stage(scene, rng)
    s, k = 36.0 + rng.uniform(0, 1), 0  # ours: the first load ~36 m ahead at the start
    d0 = lane_d(1)  # the right lane: the ego passes it one lane to the left
    while s < st.end_s + 60.0:
        st.add("pallet", Motion("static", s0=s, d=d0 + rng.uniform(-0.4, 0.4), yaw=rng.uniform(-0.6, 0.6)),
               "parked", f"load {k}: a Euro pallet lying flat in the right lane")
        for j in range(3):  # sacks burst off it, strewn behind and beside (ours: within 3 m)
            st.add("sack", Motion("static", s0=s + rng.uniform(-3.0, -0.9) if j else s + rng.uniform(0.9, 2.5),
                                  d=d0 + rng.uniform(-1.2, 1.2), yaw=rng.uniform(0, np.pi)),
                   "parked", f"load {k}: a sack spilled in the right lane, {j + 1} of 3")
        st.add("crate", Motion("static", s0=s + rng.uniform(2.6, 3.6), d=d0 + rng.uniform(-0.8, 0.8),
                               yaw=rng.uniform(0, np.pi)), "parked", f"load {k}: a crate fallen with it",
               size=(0.5, 0.35, 0.6))
        s += SPILL_PITCH_M + rng.uniform(-2, 2)
        k += 1
    st.parked_row(-1, 15.0, st.end_s + 60.0, (14.0, 24.0))
    return st.roles


ANIMAL_SPEED_MS = {"deer": (1.2, 1.6), "boar": (1.0, 1.4)}  # ours: a walk (roe deer ~1.4 m/s, wild boar ~1.2 m/s)
ANIMAL_EVERY_S = 3.0  # ours: one animal starts to cross every 3 s
ANIMAL_AHEAD_M = (13.0, 19.0)  # ours: how far ahead of the ego an animal is while in the ego's lane


def _animal(scene: Scene, rng: np.random.Generator) -> dict[int, Role]:
    st = _Stage(scene, rng)
    T, h = scene.duration, scene.half
    t, k = -4.0, 0  # ours: the first animal is on the road at the start, in the ego's lane ~2 s in
    while t < T:
        kind = "deer" if k % 2 == 0 else "boar"
        direction = 1 if k % 4 < 2 else -1
        speed = rng.uniform(*ANIMAL_SPEED_MS[kind])
        d0, d1 = -direction * (h + 2.0), direction * (h + 2.0)
        t_lane = t + abs(scene.ego_d - d0) / speed
        s_c = scene.ego_arc(max(t_lane, 0.0)) + rng.uniform(*ANIMAL_AHEAD_M)
        drift = rng.uniform(-2.0, 2.0)  # ours: not quite straight across
        t_cross = abs(d1 - d0) / speed
        st.add(kind, Motion("path", times=np.array([t, t + t_cross]), ss=np.array([s_c - drift, s_c + drift]),
                            dd=np.array([d0, d1])), "moving",
               f"a {'roe deer' if kind == 'deer' else 'wild boar'} walking across the road "
               f"{'left to right' if direction > 0 else 'right to left'} at {speed:.1f} m/s")
        t += ANIMAL_EVERY_S
        k += 1
    st.add("deer", Motion("static", s0=30.0 + rng.uniform(0, 2), d=h + SIDEWALK_M - 1.0, yaw=rng.uniform(2.0, 2.6)),
           "parked", "a roe deer standing at the right roadside, looking across")
    st.parked_row(-1, 25.0, st.end_s + 60.0, (16.0, 26.0))
    return st.roles


def _trolley(scene: Scene, rng: np.random.Generator) -> dict[int, Role]:
    st = _Stage(scene, rng)
    T, h = scene.duration, scene.half
    st.add("trolley", Motion("static", s0=22.0 + rng.uniform(0, 1), d=strip_d(scene, 1), yaw=rng.uniform(0.3, 1.2)),
           "parked", "a shopping trolley left in the right parking strip")
    st.add("trolley", Motion("static", s0=38.0 + rng.uniform(0, 1), d=-(h + 1.2), yaw=rng.uniform(-0.5, 0.5)),
           "parked", "a shopping trolley left on the left sidewalk")
    # ours: one rolling slowly across the right parking strip towards the lane (a camber), at most 2 m
    s_r = 30.0 + rng.uniform(0, 1)
    st.add("trolley", Motion("path", times=np.array([0.0, T]), ss=np.array([s_r - 0.3, s_r + 0.3]),
                             dd=np.array([h - 0.3, h - 0.3 - min(0.25 * T, 2.0)])), "moving",
           "a shopping trolley rolling slowly across the right parking strip (≤ 0.25 m/s)")
    # ours: one pushed along the right sidewalk towards the ego at 1.1 m/s, its pusher behind it
    s_p = 34.0 + rng.uniform(0, 1)
    cart = st.add("trolley", Motion("lane", s0=s_p, d=h + 2.0, v=-1.1, yaw=np.pi), "moving",
                  "a shopping trolley pushed along the right sidewalk towards the ego (1.1 m/s)")
    st.add("person", Motion("lane", s0=s_p + cart.size[2] / 2 + 0.45, d=h + 2.0, v=-1.1, yaw=np.pi), "moving",
           "pushing the trolley (a person: known, the reference beside the unknown)")
    st.parked_row(-1, 20.0, st.end_s + 60.0, (16.0, 26.0))
    return st.roles


SCENARIOS: dict[str, Scenario] = {s.name: s for s in (
    Scenario("alongside", "a vehicle driving alongside at ego speed (adjacent lane)", 2, 0, ((0.0,), (10.0,)),
             _alongside),
    Scenario("oncoming", "oncoming vehicles", 2, 0, ((0.0,), (8.0,)), _oncoming),
    Scenario("border", "a car entering at the image border (overtaking from behind-right, 5–9 m, 14 m/s)", 2, 0,
             ((0.0,), (10.0,)), _border),
    Scenario("crossing", "pedestrians crossing", 1, 0, ((0.0,), (3.0,)), _crossing),
    Scenario("far", "cars parked and moving at 30–60 m", 2, 0, ((0.0,), (8.0,)), _far, band_m=(30.0, 60.0)),
    Scenario("textureless", "textureless objects (uniform material), moving slowly and parked", 2, 0,
             ((0.0,), (6.0,)), _textureless),
    Scenario("stopgo", "objects that stop and restart", 2, 0, ((0.0,), (4.0,)), _stopgo),
    Scenario("parkedpair", "two parked cars nose to tail, ~1 m apart, at 35–55 m", 2, 0, ((0.0,), (6.0,)), _parkedpair,
             band_m=(35.0, 55.0)),
    Scenario("barriers", "rows of 4–8 construction barriers (unknown) at the roadside, 8–30 m", 1, 0, ((0.0,), (6.0,)),
             _barriers, band_m=(8.0, 30.0)),
    Scenario("verge", "a grass verge, a fence with gaps and a hedge (background, no truth), parked cars", 1, 0,
             ((0.0,), (8.0,)), _verge, right_setback_m=BACK_M),
    Scenario("debris", "small debris (unknown) on the road, each in view 5–8 frames as the ego passes", 2, 1,
             ((0.0,), (14.0,)), _debris, band_m=(10.0, 30.0)),
    Scenario("farbarrier", "rows of 6–8 construction barriers (unknown) on both sides, scored at 30–40 m", 2, 0,
             ((0.0,), (4.0,)), _farbarrier, band_m=(30.0, 40.0)),
    Scenario("spill", "a fallen load (unknown: a pallet, sacks, a crate) lying in the lane beside the ego", 2, 0,
             ((0.0,), (8.0,)), _spill),
    Scenario("animal", "deer and wild boar (unknown: no COCO class) walking across the road ahead", 1, 0,
             ((0.0,), (5.0,)), _animal),
    Scenario("trolley", "shopping trolleys (unknown, see-through): standing, rolling, and pushed", 1, 0,
             ((0.0,), (5.0,)), _trolley),
)}


def get_scenario(name: str) -> Scenario:
    try:
        return SCENARIOS[name]
    except KeyError:
        raise InputError(f"unknown synthetic scenario {name!r}; known: {sorted(SCENARIOS)}") from None


__all__ = ["SCENARIOS", "Role", "Scenario", "get_scenario", "lane_d", "strip_d"]
