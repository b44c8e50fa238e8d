"""The batched paths of localisation and tube starts agree with one-at-a-time computations,
on real KITTI 0005 frames (stereo geometry + the shared 4D-GVT mask proposals) and real
PointRCNN detections."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import REPO

from mining.config import load_config
from mining.masks import mask_pixels
from mining.score.unary import score_tube
from mining.tubes.generate import TubeGenerator
from mining.tubes.kalman import TubeFilter, initial_states, predict_states, update_states
from mining.tubes.probe import probe_back
from mining.tubes.warp import predict_box, predict_boxes
from mining.tubes.world import WorldObservations
from mining.types import TrackingFrame

N_FRAMES = 8


@pytest.fixture(scope="module")
def kitti_geometry(shared_data):
    from mining.bench.tubes import _geometry

    cfg = load_config()
    return cfg, _geometry(shared_data, cfg, N_FRAMES)


@pytest.fixture(scope="module")
def mask_records(kitti_geometry, shared_data):
    """The pipeline's frame loop on the first 100 real mask proposals per frame."""
    from mining.pipeline.frames import FrameLoop
    from mining.proposals.precomputed import JsonProposals

    cfg, geoms = kitti_geometry
    reader = JsonProposals(shared_data / "proposals_4dgvt_format" / "kitti_tracking_0005" / "top500")
    loop, out = FrameLoop(cfg), []
    for frame, g, after_gap in geoms:
        assert not after_gap
        props = reader(frame.index)
        out.append(loop.step(frame, geometry=g, proposals=props.take(np.arange(min(100, len(props))))))
    return out


@pytest.fixture(scope="module")
def mask_frames(mask_records):
    """(proposals, geometry, frame, dt, observations before the geometric filter, pose) per frame."""
    out, prev_t = [], None
    for rec in mask_records:
        dt = None if prev_t is None else (rec.frame.t_ns - prev_t) / 1e9
        prev_t = rec.frame.t_ns
        out.append((rec.proposals, rec.geometry, rec.frame, dt, rec.localised, rec.tracking.pose))
    return out


def test_localise_matches_per_mask_statistics(mask_frames):
    """Median position, point count, robust size and flow velocity of each mask, computed
    here mask by mask from its own decoded pixels."""
    cfg = load_config().localise
    checked = with_velocity = 0
    for props, g, frame, dt, obs, _ in mask_frames[1:4]:
        h, w = g.depth.shape
        for i, rle in enumerate(props.rles):
            rows, cols = mask_pixels(rle)
            grid = int(np.ceil(np.sqrt(rows.size / cfg.max_points))) if rows.size > cfg.max_points else 1
            assert obs.grid[i] == grid
            sel = (rows % grid == 0) & (cols % grid == 0)
            z = g.depth[rows[sel], cols[sel]]
            ok = np.isfinite(z)
            assert obs.n_points[i] == ok.sum()
            if ok.sum() < cfg.min_points:
                assert np.isnan(obs.position[i]).all() and len(obs.points[i]) == 0
                continue
            pts = frame.calib.backproject(cols[sel][ok], rows[sel][ok], z[ok])
            np.testing.assert_array_equal(obs.position[i], np.median(pts, axis=0))
            m = len(pts) - 1
            srt = np.sort(pts, axis=0)
            lo, hi = cfg.size_percentiles
            extent = srt[int(round(hi / 100 * m))] - srt[int(round(lo / 100 * m))]
            np.testing.assert_array_equal(obs.size[i], np.minimum(extent, cfg.max_size_m))
            assert 0 < len(obs.points[i]) <= len(pts)
            # Velocity: the flow samples whose rounded pixel lies in the mask.
            fu = np.clip(np.round(g.flow.uv[:, 0]).astype(int), 0, w - 1)
            fv = np.clip(np.round(g.flow.uv[:, 1]).astype(int), 0, h - 1)
            inside = np.zeros((h, w), bool)
            inside[rows, cols] = True
            good = np.isfinite(g.flow.motion).all(axis=1) & inside[fv, fu]
            if dt and good.sum() >= cfg.min_flow_samples:
                np.testing.assert_allclose(obs.velocity[i], np.median(g.flow.motion[good], axis=0) / dt, rtol=1e-12)
                with_velocity += 1
            else:
                assert np.isnan(obs.velocity[i]).all()
            checked += 1
    assert checked > 100 and with_velocity > 10


def test_batched_kalman_matches_tube_filter(mask_frames):
    """initial_states / predict_states / update_states against TubeFilter (filterpy) on
    real observations, with and without a velocity measurement."""
    kc = load_config().tubes.kalman
    _, _, frame, _, obs, _ = mask_frames[2]
    idx = np.flatnonzero(np.isfinite(obs.position).all(axis=1))[:30]
    nxt = mask_frames[3][4]
    later = np.flatnonzero(np.isfinite(nxt.position).all(axis=1))[:len(idx)]
    idx = idx[:len(later)]
    vel_of = (lambda o, j: (o.velocity[j], o.velocity_covariance[j]) if np.isfinite(o.velocity[j]).all() else (None, None))
    filters = [TubeFilter(obs.position[j], obs.covariance[j], obs.size[j], *vel_of(obs, j), kc) for j in idx]
    x, P = initial_states(obs.position[idx], obs.covariance[idx], obs.size[idx], obs.velocity[idx],
                          obs.velocity_covariance[idx], kc)
    for f, xi, Pi in zip(filters, x, P):
        np.testing.assert_array_equal(f.x, xi)
        np.testing.assert_array_equal(f.P, Pi)
    for f in filters:
        f.predict(-0.1)
        f.update(nxt.position[later[0]], nxt.covariance[later[0]], nxt.size[later[0]], *vel_of(nxt, later[0]))
    x, P = predict_states(x, P, -0.1, kc)
    j = np.full(len(idx), later[0])
    x, P = update_states(x, P, nxt.position[j], nxt.covariance[j], nxt.size[j], nxt.velocity[j],
                         nxt.velocity_covariance[j], kc)
    for f, xi, Pi in zip(filters, x, P):
        np.testing.assert_allclose(xi, f.x, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(Pi, f.P, rtol=1e-10, atol=1e-12)
    has_vel = np.isfinite(obs.velocity[idx]).all(axis=1)
    assert has_vel.any() and (~has_vel).any(), "both measurement models are exercised"


def test_predict_boxes_matches_predict_box(mask_frames):
    _, _, frame, _, obs, pose = mask_frames[2]
    world = WorldObservations.of(TrackingFrame(frame.index, frame.t_ns, frame.calib, pose, 0, obs, None))
    mps = [p for p in (world.points(j) for j in range(len(obs))) if p is not None]
    assert len(mps) > 20
    target = mask_frames[4]
    rng = np.random.default_rng(0)
    shifts = rng.normal(0, 1.5, (len(mps), 3))
    batched = predict_boxes(mps, shifts, target[5], target[2].calib)
    for mp, s, b in zip(mps, shifts, batched):
        one = predict_box(mp, s, target[5], target[2].calib)
        if one is None:
            assert np.isnan(b).all()
        else:
            np.testing.assert_allclose(b, one, rtol=0, atol=1e-9)


class _CheckedGenerator(TubeGenerator):
    """Runs the one-at-a-time box-only probe beside the batched one at every start."""

    compared = 0
    found = 0

    def _start(self, world, taken):
        if len(self.history) >= self.cfg.backward_required:
            cands = np.array([j for j in np.flatnonzero(world.usable) if int(j) not in taken], np.int64)
            cands = cands[self._may_step_back(world, cands, self.history[-1])]
            past = list(self.history)[::-1]
            batched = probe_back(world, cands, past, self.cfg)
            for j, b in zip(cands, batched):
                one = self._probe_one(world, int(j), past, box_only=True)
                assert (one is None) == (b is None)
                if one is not None:
                    assert (one[0].frame.index, one[1]) == (b[0].frame.index, b[1])
                    self.found += 1
                self.compared += 1
        super()._start(world, taken)


def test_batched_probe_agrees_on_real_masks(mask_records):
    cfg = load_config()
    gen = _CheckedGenerator(cfg.tubes, lambda t: score_tube(t, cfg.score).total)
    for rec in mask_records:
        gen.step(rec.tracking)
    assert gen.compared > 50 and gen.found > 5
    assert gen.finish()


def test_batched_probe_agrees_on_real_detections(kitti_tracking_root):
    from mining.pipeline.detections import detection_frames

    train = kitti_tracking_root / "training"
    cfg = load_config(REPO / "jobs" / "kitti-detections.toml")
    gen = _CheckedGenerator(cfg.tubes, lambda t: score_tube(t, cfg.score).total)
    frames = detection_frames(kitti_tracking_root, "0005", train / "det_pointrcnn",
                              train / "egoposes_orbslam3" / "0005.txt", cfg)
    for f in frames:
        gen.step(f)
    assert gen.compared > 30 and gen.found > 5


class _PlainGenerator(TubeGenerator):
    """Tube generation without its shortcuts: every start replayed, every NMS IoU computed anew."""

    def _known_replays(self):
        return {}

    def _pair_ious(self, a, b, ma, mb, common):
        from mining.masks import mask_iou

        return [float(mask_iou([ma[f].rle], [mb[f].rle])[0, 0]) for f in common]


def test_generation_shortcuts_change_no_tube(mask_records):
    """Skipping replays of live tubes' starts and caching tube NMS's IoUs give the same tubes."""
    cfg = load_config()
    score = lambda t: score_tube(t, cfg.score).total  # noqa: E731
    fast, plain = TubeGenerator(cfg.tubes, score), _PlainGenerator(cfg.tubes, score)
    skipped = 0
    for rec in mask_records:
        skipped += len(fast._known_replays())
        fast.step(rec.tracking)
        plain.step(rec.tracking)
    a, b = fast.finish(), plain.finish()
    assert skipped > 0 and len(a) > 10
    assert [t.inlier_key() for t in a] == [t.inlier_key() for t in b]
    assert [t.end_reason for t in a] == [t.end_reason for t in b]
