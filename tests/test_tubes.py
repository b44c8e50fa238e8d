"""Tube generation, scoring, co-selection and known/unknown: unit cases and real KITTI detections."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import REPO

from mining.config import load_config
from mining.localise.config import LocaliseConfig
from mining.localise.localise import localise, triangulation_covariance
from mining.masks import box_rle, mask_iou
from mining.score.config import ScoreConfig
from mining.score.unary import score_tube
from mining.select.config import SelectConfig
from mining.select.coselect import co_select, pairwise_overlap
from mining.score.category import tube_category
from mining.tubes.config import KalmanConfig, TubeConfig
from mining.tubes.generate import TubeGenerator
from mining.tubes.kalman import TubeFilter
from mining.tubes.warp import mask_points, predict_mask
from mining.types import UNKNOWN_CLASS, GroundPlane, Proposals, StereoCalib, TrackingFrame, Tube, TubeFrame

CALIB = StereoCalib(700.0, 700.0, 320.0, 120.0, 0.5, 640, 240)
GROUND = GroundPlane(np.array([0.0, -1.0, 0.0]), 1.65, 5000, True)


def _pose(z: float) -> np.ndarray:
    T = np.eye(4)
    T[2, 3] = z
    return T


def _scene_depth(box_z: float, box: tuple[int, int, int, int]) -> np.ndarray:
    """Depth of a flat road (camera 1.65 m above it) with one fronto-parallel box standing on it."""
    v = np.arange(CALIB.height, dtype=np.float32)[:, None]
    with np.errstate(divide="ignore"):
        road = np.where(v > CALIB.cy + 1, CALIB.fy * 1.65 / (v - CALIB.cy), np.nan)
    depth = np.broadcast_to(road, (CALIB.height, CALIB.width)).astype(np.float32).copy()
    x1, y1, x2, y2 = box
    depth[y1:y2, x1:x2] = box_z
    return depth


def _object_box(x: float, z: float, w: float = 1.8, h: float = 1.5) -> tuple[int, int, int, int]:
    """Image box of an object standing on the road at lateral x, depth z."""
    u1, u2 = CALIB.fx * (x - w / 2) / z + CALIB.cx, CALIB.fx * (x + w / 2) / z + CALIB.cx
    v1, v2 = CALIB.fy * (1.65 - h) / z + CALIB.cy, CALIB.fy * 1.65 / z + CALIB.cy
    return int(round(u1)), int(round(v1)), int(round(u2)), int(round(v2))


def _frame(index: int, ego_z: float, obj_world: list[tuple[float, float]], clutter: bool = False) -> TrackingFrame:
    """One frame: the camera at world z = ego_z looking at objects at world (x, z)."""
    rles, boxes, depth = [], [], None
    for x, zw in obj_world:
        z = zw - ego_z
        box = _object_box(x, z)
        depth = _scene_depth(z, box) if depth is None else depth
        if depth is not None:
            depth[box[1]:box[3], box[0]:box[2]] = z
        rles.append(box_rle(np.array(box, float), CALIB.height, CALIB.width))
        boxes.append(box)
    if clutter:  # a blob that jumps around: never consistent in 3D
        rng = np.random.default_rng(index)
        b = np.array([rng.integers(0, 500), rng.integers(100, 200)])
        box = (int(b[0]), int(b[1]), int(b[0] + 60), int(b[1] + 30))
        rles.append(box_rle(np.array(box, float), CALIB.height, CALIB.width))
        boxes.append(box)
    props = Proposals(index, rles, np.array(boxes, np.float32), np.full(len(rles), 0.9, np.float32),
                      posterior=_posterior(len(rles)), proposer=["test"] * len(rles))
    obs = localise(props, depth, CALIB, GROUND, None, None, index * 100_000_000, LocaliseConfig())
    return TrackingFrame(index, index * 100_000_000, CALIB, _pose(ego_z), 0, obs, depth)


def _posterior(n: int) -> np.ndarray:
    p = np.full((n, 81), 0.1 / 80)
    p[:, 2] = 0.9  # car
    return p / p.sum(axis=1, keepdims=True)


def test_kalman_constant_velocity_converges():
    cfg = KalmanConfig()
    kf = TubeFilter(np.zeros(3), np.eye(3) * 0.1, np.array([1.8, 1.5, 4.0]), None, None, cfg)
    rng = np.random.default_rng(0)
    for k in range(1, 30):
        kf.predict(0.1)
        pos = np.array([0.5 * 0.1 * k, 0.0, 8.0 * 0.1 * k]) + rng.normal(0, 0.05, 3)
        kf.update(pos, np.eye(3) * 0.01, np.array([1.8, 1.5, 4.0]), None, None)
    assert kf.x[3] == pytest.approx(0.5, abs=0.2) and kf.x[4] == pytest.approx(8.0, abs=0.3)
    # Backwards in time the same filter retraces its path.
    x_before = kf.x[2]
    kf.predict(-0.1)
    assert kf.x[2] == pytest.approx(x_before - 0.8, abs=0.05)


def test_covariance_grows_with_depth():
    cov = triangulation_covariance(np.array([[0.0, 0.0, 10.0], [0.0, 0.0, 40.0]]), CALIB, LocaliseConfig())
    assert cov[1, 2, 2] > 10 * cov[0, 2, 2]
    assert cov[0, 0, 0] >= LocaliseConfig().prior_var_x


def test_localise_median_footpoint_and_size():
    f = _frame(0, 0.0, [(2.0, 15.0)])
    o = f.observations
    assert o.position[0, 2] == pytest.approx(15.0, abs=1e-3)
    assert o.position[0, 0] == pytest.approx(2.0, abs=0.1)
    assert o.footpoint[0, 1] == pytest.approx(1.65, abs=1e-6)  # on the road plane
    assert o.size[0, 0] == pytest.approx(1.8 * 0.9, abs=0.3)  # 5–95 % extent of a 1.8 m wide box


def test_mask_warping_follows_egomotion():
    f0 = _frame(0, 0.0, [(2.0, 15.0)])
    f1 = _frame(1, 1.0, [(2.0, 15.0)])  # the camera drove 1 m towards the object
    o = f0.observations
    mp = mask_points(o.points[0], o.grid[0], o.proposals.boxes[0], o.position[0], CALIB, f0.pose)
    rle, box = predict_mask(mp, np.zeros(3), f1.pose, CALIB, 9)
    truth = f1.observations.proposals.rles[0]
    assert mask_iou([rle], [truth])[0, 0] > 0.8
    assert mask_iou([rle], [o.proposals.rles[0]])[0, 0] < mask_iou([rle], [truth])[0, 0]
    # Without depth (detections-only) the box corners carry the same motion.
    mp_box = mask_points(None, 1, o.proposals.boxes[0], o.position[0], CALIB, f0.pose)
    rle_b, _ = predict_mask(mp_box, np.zeros(3), f1.pose, CALIB, 9)
    assert mask_iou([rle_b], [truth])[0, 0] > 0.8


def test_generator_tracks_two_objects_and_rejects_clutter():
    gen = TubeGenerator(TubeConfig(), lambda t: score_tube(t, ScoreConfig()).total)
    for k in range(12):
        # A parked car, and a car driving ahead at 5 m/s, while the ego camera drives 1 m per frame.
        gen.step(_frame(k, 1.0 * k, [(3.0, 25.0), (-2.0, 20.0 + 0.5 * k)], clutter=True))
    tubes = gen.finish()
    long = [t for t in tubes if t.n_inliers >= 10]
    assert len(long) >= 2
    xs = sorted(round(float(np.median([f.footpoint_world[0] for f in t.frames]))) for t in long)
    assert xs[0] == -2 and xs[-1] == 3
    moving = min(long, key=lambda t: abs(t.frames[-1].footpoint_world[0] + 2))
    assert moving.frames[-1].velocity_world[2] == pytest.approx(5.0, abs=1.0)
    # Tubes start with the forward-backward enumeration: they cover the first frames too.
    assert min(t.first_frame for t in long) == 0
    # The jumping clutter never forms a tube.
    assert all(t.n_inliers < 4 or abs(t.frames[0].footpoint_world[0]) < 4 for t in tubes)


def _tube(tube_id: int, frames: list[int], box: tuple[float, float, float, float], iou=0.8, dens=0.5, obj=0.9,
          posterior=None) -> Tube:
    t = Tube(tube_id, 0)
    for k, fr in enumerate(frames):
        rle = box_rle(np.array(box), 240, 640)
        t.frames.append(TubeFrame(fr, fr * 100_000_000, True, 0, rle, np.array(box, float), np.zeros(3), np.zeros(3),
                                  np.ones(3), np.zeros(3), obj, np.nan if k == 0 else iou, np.nan if k == 0 else dens,
                                  posterior))
    return t


def test_score_is_the_sum_of_llrs():
    cfg = ScoreConfig()
    t = _tube(0, list(range(5)), (10, 10, 60, 40), iou=0.8, dens=0.5, obj=0.9)
    s = score_tube(t, cfg)
    assert s.motion == pytest.approx(4 * (np.log(0.5) + np.log(cfg.motion_k)))
    assert s.mask == pytest.approx(4 * (np.log(0.8) + np.log(cfg.mask_k)))
    assert s.objectness == pytest.approx(4 * (np.log(0.9) + np.log(cfg.objectness_k)))
    assert s.total == pytest.approx(0.5 * (0.5 * s.motion + 0.5 * s.mask) + 0.5 * s.objectness)
    longer = _tube(1, list(range(10)), (10, 10, 60, 40))
    assert score_tube(longer, cfg).total > s.total


def test_co_selection_keeps_one_of_duplicates():
    a = _tube(0, list(range(10)), (10, 10, 60, 40))
    b = _tube(1, list(range(10)), (12, 10, 62, 40))  # the same object, slightly shifted
    c = _tube(2, list(range(10)), (300, 10, 360, 40))  # elsewhere
    overlap = pairwise_overlap([a, b, c], 0.1)
    assert overlap[0, 1] == pytest.approx(10 * mask_iou([a.frames[0].rle], [b.frames[0].rle])[0, 0])
    assert overlap[0, 2] == 0 and overlap[0, 1] == overlap[1, 0]
    scores = np.array([50.0, 40.0, 30.0])
    sel = co_select([a, b, c], scores, SelectConfig())
    assert sel.tolist() == [True, False, True]


def test_known_and_unknown():
    car = np.full(81, 0.01 / 80)
    car[2] = 0.99
    t = _tube(0, [0, 1, 2], (0, 0, 10, 10), posterior=car / car.sum())
    c = tube_category(t)
    assert c.category == "car" and c.known is True and c.posterior.shape == (81,)
    assert c.classified_frames == 3 and c.evidence == pytest.approx(3.0)
    unsure = np.full(81, 0.0)
    unsure[UNKNOWN_CLASS], unsure[2] = 0.7, 0.3
    c = tube_category(_tube(1, [0, 1], (0, 0, 10, 10), posterior=unsure))
    assert c.category == "unknown" and c.known is False and c.best_known == "car"
    assert c.probability == pytest.approx(0.7)
    # the margin: ln(0.3 / 0.7) = −0.85, so a margin below that calls it car
    assert tube_category(_tube(1, [0, 1], (0, 0, 10, 10), posterior=unsure), log_margin=-1.0).known is True


def test_no_classifier_means_unclassified_not_unknown():
    c = tube_category(_tube(2, [0, 1], (0, 0, 10, 10)))
    assert c.known is None and c.category is None and c.best_known is None and c.posterior is None
    assert c.classified_frames == 0 and np.isnan(c.probability)


def test_posterior_is_the_evidence_weighted_mean():
    car = np.zeros(81)
    car[2] = 1.0
    unknown = np.zeros(81)
    unknown[UNKNOWN_CLASS] = 1.0
    t = _tube(3, [0, 1, 2, 3], (0, 0, 10, 10), posterior=car)
    # frames 2 and 3: a stereo proposal nobody covered, the detector would have seen it with p = 0.2
    for f in t.frames[2:]:
        f.posterior, f.class_weight = unknown, 0.2
    c = tube_category(t)
    assert c.classified_frames == 4 and c.evidence == pytest.approx(2.4)
    assert c.posterior[2] == pytest.approx(2 / 2.4) and c.posterior[UNKNOWN_CLASS] == pytest.approx(0.4 / 2.4)
    assert c.known is True
    # with full weight the same frames outvote nothing: a tie goes to unknown (ln 1 = 0 is not > 0)
    for f in t.frames[2:]:
        f.class_weight = 1.0
    assert tube_category(t).known is False
    # little evidence is still evidence: the call is what the posterior says (issue 39); unclassified is
    # only a tube no classifier looked at
    for f in t.frames:
        f.class_weight = 0.2
    assert tube_category(t).known is False and tube_category(t).evidence == pytest.approx(0.8)
    for f in t.frames:
        f.class_weight = 0.0
    c = tube_category(t)
    assert (c.known, c.call, c.classified_frames) == (None, "unclassified", 0)


def test_detections_only_kitti_0005(kitti_tracking_root, tmp_path):
    """PointRCNN + ORB-SLAM3 on a real sequence: tracks measured with the KITTI MOT protocol."""
    from mining.eval.kitti_mot import evaluate_kitti_mot
    from mining.pipeline.detections import track_detections

    train = kitti_tracking_root / "training"
    cfg = load_config(REPO / "jobs" / "kitti-detections.toml")
    out = tmp_path / "res"
    mined = track_detections(kitti_tracking_root, "0005", train / "det_pointrcnn",
                             train / "egoposes_orbslam3" / "0005.txt", cfg, out / "0005.txt")
    assert any(m.selected for m in mined)
    r = evaluate_kitti_mot(train / "label_02", out, ["0005"], seqmap=train / "seqmaps" / "train.seqmap")
    assert r["Car"]["HOTA"] > 0.65 and r["Car"]["MOTA"] > 0.6
    assert r["Car"]["IDSW"] <= 5


def test_tubes_never_cross_a_segment_border():
    """A failed egomotion starts a new pose segment; no tube may link the two sides."""
    gen = TubeGenerator(TubeConfig(), lambda t: score_tube(t, ScoreConfig()).total)
    for k in range(12):
        f = _frame(k, 1.0 * k, [(3.0, 25.0)])
        if k >= 6:  # egomotion failed between frames 5 and 6: new segment, new world frame
            f = TrackingFrame(f.index, f.t_ns, f.calib, _pose(1.0 * (k - 6)), 1, f.observations, f.depth)
        gen.step(f)
    tubes = gen.finish()
    assert tubes, "the parked car is tracked on both sides"
    for t in tubes:
        frames = [fr.frame for fr in t.frames]
        assert max(frames) < 6 or min(frames) >= 6
    assert {t.segment for t in tubes} == {0, 1}


def test_same_input_same_tubes(kitti_tracking_root, tmp_path):
    from mining.pipeline.detections import track_detections

    train = kitti_tracking_root / "training"
    cfg = load_config()
    outs = []
    for k in range(2):
        track_detections(kitti_tracking_root, "0012", train / "det_pointrcnn", train / "egoposes_orbslam3" / "0012.txt",
                         cfg, tmp_path / f"{k}.txt")
        outs.append((tmp_path / f"{k}.txt").read_text())
    assert outs[0] == outs[1] and outs[0].count("\n") > 50


def test_co_selection_group_by_group_equals_one_dense_qubo(kitti_tracking_root, monkeypatch):
    """Whole sequences are co-selected group by group of overlapping tubes (sparse); small
    batches as one dense QUBO. Both must choose the same tubes (real detections-only tubes)."""
    import mining.select.coselect as coselect
    from mining.pipeline.detections import track_detections

    train = kitti_tracking_root / "training"
    cfg = load_config(REPO / "jobs" / "kitti-detections.toml")
    mined = track_detections(kitti_tracking_root, "0005", train / "det_pointrcnn",
                             train / "egoposes_orbslam3" / "0005.txt", cfg)
    tubes = [m.tube for m in mined]
    scores = np.array([m.score.total for m in mined])
    assert len(tubes) > 20
    dense = coselect.co_select(tubes, scores, cfg.select)
    monkeypatch.setattr(coselect, "DENSE_MAX", 0)
    grouped = coselect.co_select(tubes, scores, cfg.select)
    np.testing.assert_array_equal(dense, grouped)
    assert dense.any() and not dense.all()


def test_a_fast_object_without_flow_starts_a_tube():
    """A car overtaking close by at 24 m/s (the ego drives 10 m/s): 1.4 m a frame relative to
    the camera, no scene flow. The prior cannot reach it; the displacement hypotheses do."""
    def run(hypotheses: int, association: str = TubeConfig.association):
        cfg = TubeConfig(start_hypotheses=hypotheses, association=association,
                         gate_jitter_px=0.0 if association == "reference" else TubeConfig.gate_jitter_px)
        gen = TubeGenerator(cfg, lambda t: score_tube(t, ScoreConfig()).total)
        for k in range(12):
            gen.step(_frame(k, 1.0 * k, [(3.0, 6.0 + 2.4 * k)]))
        return gen.finish()

    # the failure this guards, under the REFERENCE association: without the hypotheses no tube starts
    assert not run(0, "reference")
    # the innovation association's gate (prediction + observation covariance) reaches it only late
    late = run(0)
    tubes = run(3)
    assert len(tubes) == 1 and tubes[0].n_inliers >= 9
    assert all(t.first_frame > tubes[0].first_frame and t.n_inliers < tubes[0].n_inliers for t in late)
    assert tubes[0].frames[-1].velocity_world[2] == pytest.approx(24.0, abs=1.0)
    assert len(run(3, "reference")) == 1


def test_displacement_hypotheses_respect_the_speed_bound_and_the_interval():
    from mining.tubes.probe import displacement_hypotheses
    from mining.tubes.world import WorldObservations

    prev = WorldObservations.of(_frame(0, 0.0, [(3.0, 20.0), (-2.0, 20.0), (3.0, 40.0)]))
    cur = WorldObservations.of(_frame(1, 0.0, [(3.0, 22.0)]))
    cfg = TubeConfig(start_max_speed_mps=40.0)
    rows, vel, cov = displacement_hypotheses(cur, np.array([0]), prev, cfg)
    # 0.1 s: (3, 20) is 2 m away (20 m/s), (-2, 20) 5.4 m (54 m/s: out of reach), (3, 40) 18 m.
    assert rows.tolist() == [0] and vel[0, 2] == pytest.approx(20.0, abs=1.5) and abs(vel[0, 0]) < 1.5
    assert cov[0, 2, 2] > cov[0, 0, 0] > 0  # depth is the uncertain axis of stereo
    # The same displacement over a longer interval is a slower, reachable object.
    slow = TrackingFrame(1, 300_000_000, CALIB, _pose(0.0), 0, cur.frame.observations, None)
    rows, vel, _ = displacement_hypotheses(WorldObservations.of(slow), np.array([0]), prev, cfg)
    assert len(rows) == 2 and vel[0, 2] == pytest.approx(2.0 / 0.3, abs=0.5)


def test_no_displacement_hypotheses_for_parts_of_a_tracked_object():
    """A car overtaking at 24 m/s (no flow), proposed whole and, from frame 5 on, also as its
    lower half. The whole car's tube takes the whole-car proposal; the half is part of a
    tracked object and gets no velocity hypotheses (its tube would only compete with the
    car's own in co-selection)."""
    def frames():
        for k in range(14):
            f = _frame(k, 1.0 * k, [(3.0, 6.0 + 2.4 * k)])
            props = f.observations.proposals
            if k >= 5:
                x1, y1, x2, y2 = props.boxes[0]
                half = np.array([x1, (y1 + y2) / 2, x2, y2], np.float32)
                props = Proposals(k, props.rles + [box_rle(half.astype(float), CALIB.height, CALIB.width)],
                                  np.vstack([props.boxes, half[None]]), np.full(2, 0.9, np.float32),
                                  posterior=_posterior(2), proposer=["test"] * 2)
            obs = localise(props, f.depth, CALIB, GROUND, None, None, f.t_ns, LocaliseConfig())
            yield TrackingFrame(k, f.t_ns, CALIB, f.pose, 0, obs, f.depth)

    def n_tubes(part_ioa: float) -> int:
        gen = TubeGenerator(TubeConfig(start_part_ioa=part_ioa), lambda t: score_tube(t, ScoreConfig()).total)
        for f in frames():
            gen.step(f)
        return len([t for t in gen.finish() if t.n_inliers >= 4])

    assert n_tubes(0.5) == 1  # the car
    assert n_tubes(1.01) == 2  # 1.01: no mask is ever "part" of another, and the half gets its own tube
