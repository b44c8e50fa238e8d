"""Staged scenarios of the synthetic source: one failure mode of tube mining each (issue 9).

A scenario replaces the random traffic of a world (``Scene._build_objects``) with objects
placed on purpose, each with a specific motion, and the ego's random drive with a fixed
speed profile; the rest stays the seed's (the road's gentle bends, buildings, trees, light,
exposure). The road keeps its gentle bends but has no sharp turns. Everything is a pure
function of (scenario, seed, length), so a scenario renders the same bits every time and any
length works: the builders repeat their event over the whole duration.

Every staged object has a ``Role``: ``moving`` (a target: what the scenario is about) or
``parked`` (a static reference seen at similar range, so moving and parked recall can be
compared in one scene). Map coordinates are road coordinates: arc length s (the ego starts at
s = 0 and moves to +s) and lateral offset d (right of the centreline > 0; traffic keeps right,
so lanes with d > 0 drive to +s and lanes with d < 0 are oncoming).

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
========== ==================================================================================
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mining.errors import InputError
from mining.sources.synthetic.scene import Motion, Obj, Scene
from mining.sources.synthetic.textures import LANE_M, PARKING_M


@dataclass(frozen=True)
class Role:
    """What a staged object is for."""

    role: str  # "moving": a target of the scenario; "parked": a static reference
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

    def add(self, category: str, motion: Motion, role: str, note: str, textureless: bool = False) -> Obj:
        o = self.scene.add_object(self.rng, category, motion)
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
)}


def get_scenario(name: str) -> Scenario:
    try:
        return SCENARIOS[name]
    except KeyError:
        raise InputError(f"unknown synthetic scenario {name!r}; known: {sorted(SCENARIOS)}") from None


__all__ = ["SCENARIOS", "Role", "Scenario", "get_scenario", "lane_d", "strip_d"]
