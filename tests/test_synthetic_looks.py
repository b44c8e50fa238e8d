"""The synthetic objects' meshes (planar faces, every category, limbs that walk and pedal), the
view culling, the unoccluded silhouettes, and ``mine bench looks`` on the shared ONNX model."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from conftest import MODEL

from mining.sources.synthetic import SyntheticSource
from mining.sources.synthetic.faces import R_N, R_NV, R_OBJ, R_PART
from mining.sources.synthetic.meshes import CAR_SHAPES, build_mesh, part_poses, rig
from mining.sources.synthetic.scene import KNOWN, Motion, frame_faces



@pytest.fixture(scope="module")
def scene():
    return SyntheticSource(n_frames=200).scene("0000")


def _objects(scene, category: str, **fields):
    rng = np.random.default_rng(5)
    out = []
    for k in range(3):
        o = scene._new(rng, category, Motion("lane", v=1.2), **fields)
        scene.objects.pop()  # built for the test only: not part of the world
        out.append(o)
    return out


def test_every_category_has_planar_outward_faces(scene):
    """Each category's mesh: faces planar (every vertex on the face's plane), normals unit, the
    object's own track id on every face but its shadow, and inside its truth box (± 0.15 m)."""
    for cat in KNOWN:
        for o in _objects(scene, cat):
            V, R = build_mesh(o, scene.atlas)
            assert len(V) >= 5, cat
            n = R[:, R_N : R_N + 3]
            assert np.allclose(np.linalg.norm(n, axis=1), 1, atol=1e-6), cat
            off = np.einsum("fkj,fj->fk", V - V[:, :1], n)
            assert np.abs(off).max() < 1e-6, (cat, np.abs(off).max())
            assert set(np.unique(R[:, R_OBJ])) <= {0, o.track_id} and (R[:, R_OBJ] == o.track_id).sum() >= 5, cat
            pts = np.concatenate([v[: int(r[R_NV])] for v, r in zip(V, R) if r[R_OBJ] == o.track_id])
            w, h, l = o.size
            slack = 0.15 if cat != "person" else 0.3  # arms and feet of the rest pose reach past the nominal box
            assert np.all(np.abs(pts[:, 0]) <= w / 2 + slack), (cat, np.abs(pts[:, 0]).max(), w)
            assert np.all(np.abs(pts[:, 2]) <= l / 2 + slack), (cat, np.abs(pts[:, 2]).max(), l)
            assert -pts[:, 1].max() > -0.02 and -pts[:, 1].min() <= h + 0.02, (cat, -pts[:, 1].min(), h)


def test_car_bodies_cover_every_type_and_look_different(scene):
    atlas = scene.atlas
    widths = {}
    rng = np.random.default_rng(2)
    seen = set()
    while seen != {c.name for c in CAR_SHAPES}:
        o = scene._new(rng, "car", Motion("static"))
        scene.objects.pop()
        seen.add(o.shape)
        V, R = build_mesh(o, atlas)
        ys = -V[R[:, R_OBJ] > 0][..., 1]
        widths.setdefault(o.shape, []).append(ys.max() / o.size[1])
        assert abs(ys.max() - o.size[1]) < 0.01  # the roof is the truth box's top
    assert len(seen) == 5


def test_walking_feet_stay_on_the_ground_and_riders_sit_on_the_saddle(scene):
    walker = _objects(scene, "person")[0]
    V, R = build_mesh(walker, scene.atlas)
    lows = []
    for walked in np.linspace(0, 2 * rig(walker).stride, 17):
        Rp, tp = part_poses(walker, walked)
        parts = R[:, R_PART].astype(int)
        P = np.einsum("fij,fkj->fki", Rp[parts], V) + tp[parts][:, None]
        own = R[:, R_OBJ] > 0
        lows.append(P[own][..., 1].max())  # y down: the lowest point
    assert np.all(np.abs(np.array(lows)) < 0.02), lows  # the lower foot on the ground all through the cycle
    Rp, _ = part_poses(walker, rig(walker).stride / 4)
    assert np.degrees(np.arccos(np.clip(Rp[1][1, 1], -1, 1))) > 15  # the legs swing
    rider = _objects(scene, "person", riding=True)[0]
    V, R = build_mesh(rider, scene.atlas)
    Rp, tp = part_poses(rider, 1.0)
    parts = R[:, R_PART].astype(int)
    P = np.einsum("fij,fkj->fki", Rp[parts], V) + tp[parts][:, None]
    top = -P[R[:, R_OBJ] > 0][..., 1].min()
    assert abs(top - rider.size[1]) < 0.08  # the seated height is the rider's truth box
    assert -P[R[:, R_OBJ] > 0][..., 1].max() > 0.05  # feet on the pedals, off the ground


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_view_culling_changes_no_bit():
    a, b = SyntheticSource(n_frames=120), SyntheticSource(n_frames=120)
    b._view = lambda: None  # no culling
    for seq, pos in (("0001", 40), ("0003", 100)):
        fa, fb = a.read_frame(a.plan(seq), pos), b.read_frame(b.plan(seq), pos)
        assert np.array_equal(fa.left, fb.left) and np.array_equal(fa.right, fb.right)
        assert [o.track_id for o in fa.truth.objects] == [o.track_id for o in fb.truth.objects]
    sc = a.scene("0001")
    t = a.plan("0001").t_ns[40] / 1e9
    assert len(frame_faces(sc, t, a._view())[0]) < 0.8 * len(frame_faces(sc, t)[0])  # and it leaves faces out


def test_unoccluded_silhouettes_contain_the_visible_masks():
    src = SyntheticSource(n_frames=120)
    plan = src.plan("0002")
    fr = src.read_frame(plan, 60)
    full = src.unoccluded(plan, 60)
    hidden = 0
    for o in fr.truth.objects:
        px, box = full[o.track_id]
        assert px >= o.mask.sum()
        hidden += px > 1.5 * o.mask.sum()
        if box is not None and 0 < o.box[0] and o.box[2] < 1242 and 0 < o.box[1] and o.box[3] < 375:
            # (sub-pixel parts are drawn a pixel wide: masks reach up to ~1.5 px past the vertices)
            assert box[0] <= o.box[0] + 2 and box[1] <= o.box[1] + 2 and box[2] >= o.box[2] - 2 and box[3] >= o.box[3] - 2
    assert hidden >= 1  # some objects are partly hidden by others


def test_new_unknown_kinds_appear_outside_coco():
    assert {"tyre", "barrier", "box", "branch", "cart", "tortoise"} <= {c for c, k in KNOWN.items() if not k}
    cats = {o.category for seq in ("0000", "0001") for o in SyntheticSource(n_frames=300).scene(seq).objects}
    assert {"tyre", "barrier", "box", "branch", "cart", "tortoise"} <= cats, cats


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_bench_looks_on_kitti_and_synthetic(tmp_path, shared_data):
    """The real frames give the reference (cars found with their class), and a few synthetic
    frames run through the same counting, with the drawn frames written."""
    from mining.bench.looks import kitti_recall, synthetic_recall
    from mining.proposals.config import OnnxConfig
    from mining.proposals.onnx_yolo import OnnxProposer

    if not MODEL.is_file():
        pytest.skip(f"shared model not present at {MODEL}")
    cv2.setNumThreads(1)
    proposer = OnnxProposer(OnnxConfig(model_path=str(MODEL)), (375, 1242))
    real = kitti_recall(shared_data, proposer, tmp_path)
    assert real["car"].objects >= 30 and real["car"].recalled / real["car"].objects >= 0.9
    syn, ms = synthetic_recall(proposer, ["0000"], 3, 20, 100, tmp_path)
    assert len(ms) == 3 and syn["car"].objects >= 5 and syn["car"].located >= 0.8 * syn["car"].objects
    assert syn["car"].recalled >= 0.5 * syn["car"].objects
    assert list(tmp_path.glob("looks_kitti_*.png")) and list(tmp_path.glob("looks_synthetic_*.png"))
