"""Staged synthetic scenarios: each renders its targets as specified, deterministically by seed.

Real renderer output throughout (no hand-made observations). Motion is checked on the exact
world state over the whole scene where that is cheap, visibility and appearance on rendered
frames at half resolution. The mining results of the scenarios (the "before" numbers) are
``mine bench scenarios``'s, not asserted here.
"""

from __future__ import annotations

from functools import cache

import cv2
import numpy as np
import pytest
from conftest import REPO

from mining.errors import InputError
from mining.sources.synthetic import SyntheticSource
from mining.sources.synthetic.scenarios import SCENARIOS

HALF = {"width": 621, "height": 188, "fx": 360.77}
N = 80  # frames: the bench's default length
W = HALF["width"]


@cache
def source(name: str, n_frames: int = N, **kw) -> SyntheticSource:
    cv2.setNumThreads(1)
    return SyntheticSource(n_frames=n_frames, scenario=name, **(HALF | kw))


@cache
def frame(name: str, index: int):
    src = source(name)
    return src.read_frame(src.plan("0000"), index)


def roles(name: str, role: str = "moving") -> dict:
    return {t: r for t, r in source(name).scene("0000").roles.items() if r.role == role}


def seen(name: str, indices, role: str = "moving", min_px: int = 100) -> dict[int, dict[int, object]]:
    """track id → {frame: ObjectTruth} over rendered frames, objects of ``role`` with ≥ min_px pixels."""
    ids = roles(name, role)
    out: dict[int, dict[int, object]] = {}
    for i in indices:
        for o in frame(name, i).truth.objects:
            if o.track_id in ids and o.mask.sum() >= min_px:
                out.setdefault(o.track_id, {})[i] = o
    return out


def in_camera(name: str, track_id: int, t: float) -> np.ndarray | None:
    """Exact centre of a staged object in the camera frame at time t (None when absent)."""
    sc = source(name).scene("0000")
    o = obj(name, track_id)
    st = sc.state(o, t)
    if st is None:
        return None
    M = np.linalg.inv(sc.camera_map(t))
    return M[:3, :3] @ (st[0] + np.array([0.0, -o.size[1] / 2, 0.0])) + M[:3, 3]


def obj(name: str, track_id: int):
    return next(x for x in source(name).scene("0000").objects if x.track_id == track_id)


def speed(name: str, track_id: int, t: float) -> float | None:
    """Exact world speed (central difference over 2 ms), None when absent."""
    sc = source(name).scene("0000")
    a, b = (sc.state(obj(name, track_id), t + e) for e in (-1e-3, 1e-3))
    return None if a is None or b is None else float(np.linalg.norm(b[0] - a[0]) / 2e-3)


def ego_speed(name: str, t: float) -> float:
    sc = source(name).scene("0000")
    return float(np.linalg.norm(sc.camera_map(t + 0.01)[:3, 3] - sc.camera_map(t - 0.01)[:3, 3]) / 0.02)


TIMES = np.arange(0.1, N / 10, 0.1)  # every frame but the first (whose truth velocity is one-sided)


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_every_scenario_has_moving_targets_and_parked_references():
    assert set(SCENARIOS) == {"alongside", "oncoming", "border", "crossing", "far", "textureless", "stopgo",
                              "parkedpair", "barriers", "verge", "debris", "farbarrier", "spill", "animal", "trolley"}
    # scenarios of static things: every staged object is parked
    still = {"parkedpair", "barriers", "verge", "debris", "farbarrier", "spill"}
    for name in SCENARIOS:
        assert (roles(name, "moving") or name in still) and roles(name, "parked"), name
        sc = source(name).scene("0000")
        assert set(sc.roles) == {o.track_id for o in sc.objects}  # every staged object has a role
        assert np.abs(sc.road.kappa).max() < 0.004  # gentle bends only: no turn (radius > 250 m)


def test_unknown_scenario_and_random_world():
    with pytest.raises(InputError, match="alongside"):
        SyntheticSource(n_frames=5, scenario="rush-hour")
    plain = SyntheticSource(n_frames=20, width=160, height=64, fx=90.0)
    assert plain.scenario is None and plain.scene("0000").roles == {}


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_deterministic_by_seed_and_any_length():
    a = SyntheticSource(n_frames=30, scenario="border", width=160, height=64, fx=90.0)
    b = SyntheticSource(n_frames=30, scenario="border", width=160, height=64, fx=90.0)
    fa, fb = a.read_frame(a.plan("0003"), 25), b.read_frame(b.plan("0003"), 25)
    assert np.array_equal(fa.left, fb.left) and np.array_equal(fa.right, fb.right)
    assert [(o.track_id, o.box) for o in fa.truth.objects] == [(o.track_id, o.box) for o in fb.truth.objects]
    other = a.read_frame(a.plan("0004"), 25)
    assert not np.array_equal(fa.left, other.left)  # the seed changes the world around the staging

    def moving(src: SyntheticSource, seq: str) -> list[str]:
        return [r.note for r in src.scene(seq).roles.values() if r.role == "moving"]

    assert moving(a, "0003") == moving(a, "0004")  # ... but not what is staged
    # any length: the events repeat over the scene (an overtaking car every 10 s)
    long = SyntheticSource(n_frames=300, scenario="border", width=160, height=64, fx=90.0)
    assert len(moving(long, "0000")) == 3 and len(moving(a, "0003")) == 1
    assert len(moving(SyntheticSource(n_frames=300, scenario="crossing"), "0000")) >= 12


def test_alongside_keeps_ego_speed_in_the_adjacent_lane():
    ids = roles("alongside")
    assert len(ids) == 2
    for tid in ids:
        for t in TIMES[::5]:
            assert abs(speed("alongside", tid, t) - ego_speed("alongside", t)) < 0.3
            p = in_camera("alongside", tid, t)
            assert 2.8 < p[0] < 4.2  # one lane to the right
    depth = {tid: [in_camera("alongside", tid, t)[2] for t in TIMES] for tid in ids}
    near, far = sorted(ids, key=lambda t: np.mean(depth[t]))
    assert 6.5 < min(depth[near]) and max(depth[near]) < 10 and 19 < min(depth[far]) and max(depth[far]) < 25
    frames = range(5, N, 15)
    vis = seen("alongside", frames)
    assert set(vis) == set(ids) and all(len(v) == len(frames) for v in vis.values())  # in view all the time


def test_oncoming_vehicles_close_in_from_the_left():
    vis = seen("oncoming", range(0, N, 4))
    assert len(vis) >= 4
    for frames in vis.values():
        for i, o in frames.items():
            if i:
                fwd = frame("oncoming", i).truth.pose[:3, 2]
                assert o.velocity_world @ fwd < -9  # 10 or 13 m/s towards the ego
                assert o.center_cam[0] < 0.5 or o.center_cam[2] > 60  # the oncoming lanes are on the left
        z = [o.center_cam[2] for _, o in sorted(frames.items())]
        assert all(np.diff(z) < 0)
    assert min(o.center_cam[2] for f in vis.values() for o in f.values()) < 15


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_border_car_enters_at_the_right_border_and_passes_5_to_9_m_ahead():
    (tid,) = roles("border")
    vis = seen("border", range(50))[tid]
    first = min(vis)
    assert 15 <= first <= 30  # behind the ego at first
    assert vis[first].box[2] >= W - 1  # enters at the right image border
    assert vis[first].center_cam[0] > 2.8  # one lane to the right
    near = [i for i, o in vis.items() if 5 <= o.center_cam[2] <= 9]
    assert len(near) >= 8 and all(abs(np.linalg.norm(vis[i].velocity_world) - 14) < 0.3 for i in near)
    assert all(np.diff([vis[i].center_cam[2] for i in sorted(vis)]) > 0)  # it overtakes


def test_pedestrians_cross_well_ahead_of_the_ego():
    ids = roles("crossing")
    assert len(ids) >= 3
    lateral_seen = 0
    for tid in ids:
        waypoints = obj("crossing", tid).motion.times
        for t in TIMES:
            p = in_camera("crossing", tid, t)
            if p is None or np.abs(waypoints - t).min() < 2e-3:  # (the speed is one-sided at a corner)
                continue
            if abs(p[0]) < 1.5:  # in front of the ego
                assert p[2] > 8
            assert 1.15 < speed("crossing", tid, t) < 1.65
    vis = seen("crossing", range(10, N, 10))
    assert len(vis) >= 3
    for frames in vis.values():
        for i, o in frames.items():
            right = frame("crossing", i).truth.pose[:3, 0]
            lateral_seen += abs(o.velocity_world @ right) > 1.1  # walking across the road
    assert lateral_seen >= 6
    standing = [t for t in roles("crossing", "parked") if obj("crossing", t).category == "person"]
    assert len(standing) == 2 and all(speed("crossing", t, 3.0) == 0 for t in standing)


def test_far_cars_stay_at_30_to_60_m():
    ids = roles("far")
    assert len(ids) == 3
    for tid in ids:
        z = [in_camera("far", tid, t)[2] for t in TIMES]
        assert 30 < min(z) and max(z) < 60
        assert all(abs(speed("far", tid, t) - ego_speed("far", t)) < 1.2 for t in TIMES[::7])
    vis = seen("far", range(5, N, 15), min_px=30)  # (at half resolution the 55 m car has ~60 px)
    assert set(vis) == set(ids)
    parked = seen("far", range(5, N, 15), "parked", min_px=30)
    in_band = {t for t, f in parked.items() if any(30 <= o.center_cam[2] <= 60 for o in f.values())}
    assert len(in_band) >= 4
    assert SCENARIOS["far"].band_m == (30.0, 60.0)


def _gradient(img: np.ndarray) -> np.ndarray:
    g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float32)
    return np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))


def test_textureless_objects_are_flat_and_move_slowly():
    sc = source("textureless").scene("0000")
    flat = {t for t, r in sc.roles.items() if r.textureless}
    assert len(flat) == 5 and all(obj("textureless", t).material == "flat" for t in flat)
    moving = roles("textureless")
    assert set(moving) <= flat and len(moving) == 2
    for tid in moving:
        assert all(2.4 < speed("textureless", tid, t) < 3.1 for t in TIMES[::8])
    grad = {True: [], False: []}
    for i in (20, 40, 60):
        f = frame("textureless", i)
        g = _gradient(f.left)
        for o in f.truth.objects:
            inner = cv2.erode(o.mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
            if o.category == "car" and inner.sum() >= 30:
                grad[o.track_id in flat].append(np.median(g[inner]))
    assert grad[True] and grad[False]
    assert max(grad[True]) < 0.25 * np.median(grad[False])  # inside: sensor noise only


def test_stop_and_go():
    car = next(t for t in roles("stopgo") if obj("stopgo", t).category == "car")
    person = next(t for t in roles("stopgo") if obj("stopgo", t).category == "person")
    v = np.array([speed("stopgo", car, t) for t in TIMES])
    stopped = np.flatnonzero(v < 0.05)
    assert 20 <= len(stopped) <= 27 and np.all(np.diff(stopped) == 1)  # one stop of 2.5 s
    assert v[: stopped[0] - 16].min() > 7.9 and v[stopped[-1] + 16 :].min() > 7.9  # 8 m/s before and after
    w = np.array([speed("stopgo", person, t) for t in TIMES])
    assert (w < 0.05).sum() >= 15 and w[:15].min() > 1.35 and w[55:60].min() > 1.35
    vis = seen("stopgo", range(10, N, 10))
    assert car in vis and len(vis[car]) == 7  # in view all the time, 10–25 m ahead
    assert all(10 < o.center_cam[2] < 26 for o in vis[car].values())
    vis = seen("stopgo", (30, 40), min_px=40)  # at 40 it nears the left border: ~55 px of a slim person at half size
    assert person in vis and {30, 40} <= set(vis[person])  # in view while it stands


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_bench_harness_on_a_short_scenario():
    """The harness end to end on 30 half-resolution frames of ``border`` (plumbing, not targets)."""
    from mining.bench.scenarios import (
        FLOW_OFF_SAMPLES,
        flow_configs,
        format_scenarios,
        run_scenario,
    )
    from mining.cli import build_parser
    from mining.config import load_config

    cfg = load_config(REPO / "jobs" / "synthetic.toml")
    cfgs = flow_configs(cfg)
    assert cfgs["off"].localise.min_flow_samples == FLOW_OFF_SAMPLES and cfgs["on"] is cfg
    assert cfg.localise.min_flow_samples != FLOW_OFF_SAMPLES
    r = run_scenario("border", cfg, n_frames=30, half=True)
    assert r["resolution"] == "621x188" and r["frames"] == 30 and r["egomotion_failures"] == 0
    (tid,) = roles("border")  # the same world at any resolution
    assert r["targets"][tid]["role"] == "moving" and 13 < r["targets"][tid]["speed"] < 15
    for m in ("on", "off"):
        x = r["modes"][m]
        assert x["roles"]["moving"]["tracks"] == 1 and x["roles"]["parked"]["tracks"] >= 1
        assert 0 <= x["HOTA"] <= 1 and x["tubes"] >= x["clutter"]
    assert r["flow"]["moving"]["frames"] > 0 and 0 <= r["flow"]["moving"]["flow_enough"] <= 1
    text = format_scenarios([r])
    assert "border" in text and "overtaking" in text
    args = build_parser().parse_args(["bench", "scenarios", "--half", "--scenarios", "border", "stopgo"])
    assert args.half and args.scenarios == ["border", "stopgo"] and args.config.endswith("jobs/synthetic.toml")
