"""The synthetic source: determinism, geometric truth (stereo, egomotion), instance truth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mining.errors import InputError
from mining.sources import open_source
from mining.sources.synthetic import SyntheticSource, bench_render


@pytest.fixture(scope="module")
def src() -> SyntheticSource:
    cv2.setNumThreads(1)
    return SyntheticSource(n_frames=200)


@pytest.fixture(scope="module")
def frame(src):
    return src.read_frame(src.plan("0000"), 40)


def test_plan_is_instant_and_kitti_like():
    s = open_source("synthetic", None, n_frames=30, hz=10.0)
    assert s.sequences() == ["0000", "0001", "0002", "0003"]
    p = s.plan("0007")
    assert len(p) == 30 and p.t_ns[1] - p.t_ns[0] == 100_000_000 and p.t_ns[0] == 0
    assert p.calib.width == 1242 and p.calib.height == 375 and abs(p.calib.bf - 721.5377 * 0.5327) < 1e-6
    assert 0.4 * 1242 < p.calib.cx < 0.6 * 1242 and 0.4 * 375 < p.calib.cy < 0.6 * 375
    assert s._scenes == {}  # planning rendered and generated nothing


def test_dropped_frames_are_a_recording_gap():
    s = SyntheticSource(n_frames=30, width=160, height=64, fx=90.0, drop_frames=[[10, 14], [20, 21]])
    p = s.plan("0000")
    assert p.frames == tuple(i for i in range(30) if not (10 <= i < 14 or i == 20))
    assert p.gaps == (10, 16) and p.frames[10] == 14 and p.frames[16] == 21
    assert p.t_ns[10] - p.t_ns[9] == 5 * 100_000_000  # time goes on through the gap
    f = s.read_frame(p, 10)
    g = SyntheticSource(n_frames=30, width=160, height=64, fx=90.0).read_frame(SyntheticSource(
        n_frames=30, width=160, height=64, fx=90.0).plan("0000"), 14)
    assert f.index == 14 and f.t_ns == g.t_ns and np.array_equal(f.left, g.left)  # the same world
    with pytest.raises(InputError):
        SyntheticSource(n_frames=30, drop_frames=[[5, 40]])


def test_bad_input_raises():
    s = SyntheticSource(n_frames=5)
    with pytest.raises(InputError):
        s.plan("city")
    with pytest.raises(InputError):
        s.read_frame(s.plan("0000"), 5)


def test_random_access_is_bit_identical():
    a = SyntheticSource(n_frames=50, width=400, height=150, fx=240.0)
    b = SyntheticSource(n_frames=50, width=400, height=150, fx=240.0)
    pa, pb = a.plan("0001"), b.plan("0001")
    fa = [a.read_frame(pa, i) for i in (3, 17)]
    fb = [b.read_frame(pb, i) for i in (17, 9, 3)]
    for x, y in ((fa[0], fb[2]), (fa[1], fb[0])):
        assert np.array_equal(x.left, y.left) and np.array_equal(x.right, y.right)
        assert np.array_equal(x.truth.depth, y.truth.depth, equal_nan=True)
        assert np.array_equal(x.truth.pose, y.truth.pose)
        assert [o.track_id for o in x.truth.objects] == [o.track_id for o in y.truth.objects]
        for o, q in zip(x.truth.objects, y.truth.objects):
            assert np.array_equal(o.mask, q.mask)
    assert not np.array_equal(fa[0].left, fa[1].left)


def test_frame_contents(frame):
    H, W = 375, 1242
    assert frame.left.shape == (H, W, 3) and frame.left.dtype == np.uint8 and frame.right.shape == (H, W, 3)
    d = frame.truth.depth
    assert d.dtype == np.float32 and d.shape == (H, W)
    assert np.isnan(d[:50]).mean() > 0.02  # some sky at the top
    assert np.isfinite(d[-60:]).all()  # road everywhere at the bottom, no cracks
    assert np.nanmin(d) > 0
    # the bottom rows see the road about camera-height / tan(angle) away
    z_bottom = np.nanmedian(d[-1, W // 3 : 2 * W // 3])
    expected = 1.65 * frame.calib.fy / (H - 1 - frame.calib.cy)
    assert abs(z_bottom - expected) < 0.15 * expected
    assert frame.left.std() > 20  # textured, not flat


def test_depth_agrees_with_stereo_block_matching(frame):
    """Block-match the left patch along the right row: best disparity = bf / z within 1 px."""
    gl = cv2.cvtColor(frame.left, cv2.COLOR_RGB2GRAY).astype(np.float32)
    gr = cv2.cvtColor(frame.right, cv2.COLOR_RGB2GRAY).astype(np.float32)
    z = frame.truth.depth
    bf = frame.calib.bf
    # a wide, short window: the road's disparity changes from row to row, not along a row
    r, ry = 10, 1
    zz = np.nan_to_num(z, nan=1e9)
    win = np.ones((2 * ry + 1, 2 * r + 1))
    smooth = (cv2.dilate(zz, win) / cv2.erode(zz, win)) < 1.03  # no depth edge in the window
    # "textured": enough horizontal gradient in the window for a match to be unambiguous
    gx = np.abs(cv2.Sobel(gl, cv2.CV_32F, 1, 0, ksize=3)) / 4
    texture = cv2.blur(gx, (2 * r + 1, 2 * ry + 1))
    disp = bf / zz
    H, W = z.shape
    ok = np.isfinite(z) & smooth & (texture > 4) & (disp < 120) & (disp > 2)
    ok[: r + 1], ok[-r - 1 :], ok[:, : 130], ok[:, -r - 1 :] = False, False, False, False
    ys, xs = np.nonzero(ok)
    rng = np.random.default_rng(0)
    pick = rng.choice(len(ys), 300, replace=False)
    good = 0
    for y, x in zip(ys[pick], xs[pick]):
        patch = gl[y - ry : y + ry + 1, x - r : x + r + 1]
        d_true = disp[y, x]
        cands = np.arange(max(0, int(d_true) - 20), int(d_true) + 21)
        cands = cands[x - cands - r >= 0]
        costs = [np.abs(gr[y - ry : y + ry + 1, x - c - r : x - c + r + 1] - patch).sum() for c in cands]
        good += abs(cands[int(np.argmin(costs))] - d_true) <= 1.0
    assert good / len(pick) >= 0.8, good


def test_pose_chain_is_consistent(src):
    """Static points seen at frame i, moved through the poses, land where frame j's depth says."""
    plan = src.plan("0000")
    fi, fj = src.read_frame(plan, 60), src.read_frame(plan, 63)
    assert np.allclose(src.read_frame(plan, 0).truth.pose, np.eye(4))
    c = fi.calib
    moving = np.zeros(fi.truth.depth.shape, bool)
    for o in fi.truth.objects:
        moving |= o.mask
    ok = np.isfinite(fi.truth.depth) & ~moving & (fi.truth.depth < 40)
    ys, xs = np.nonzero(ok)
    pick = np.random.default_rng(1).choice(len(ys), 500, replace=False)
    u, v = xs[pick], ys[pick]
    P = c.backproject(u, v, fi.truth.depth[v, u])
    T = np.linalg.inv(fj.truth.pose) @ fi.truth.pose
    Q = P @ T[:3, :3].T + T[:3, 3]
    assert np.linalg.norm(T[:3, 3]) > 0.5  # the ego really moved between the two frames
    uv = c.project(Q)
    iu, iv = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    inside = (iu >= 0) & (iu < c.width) & (iv >= 0) & (iv < c.height) & (Q[:, 2] > 1)
    zj = fj.truth.depth[iv[inside], iu[inside]]
    rel = np.abs(zj - Q[inside, 2]) / Q[inside, 2]
    assert inside.sum() > 200
    assert np.nanmean(rel < 0.02) > 0.85


def test_instance_masks_match_depth_and_boxes(frame):
    objs = frame.truth.objects
    assert len(objs) >= 3
    for o in objs:
        assert o.mask.shape == frame.truth.depth.shape and o.mask.any()
        ys, xs = np.nonzero(o.mask)
        assert (o.box[0], o.box[1], o.box[2], o.box[3]) == (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)
        zmed = float(np.median(frame.truth.depth[o.mask]))
        assert abs(zmed - o.center_cam[2]) < 0.6 * max(o.size) + 0.3, (o.category, zmed, o.center_cam)
    ids = [o.track_id for o in objs]
    assert len(set(ids)) == len(ids)
    union = np.sum([o.mask for o in objs], axis=0)
    assert union.max() == 1  # masks are disjoint


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_known_and_unknown_objects_come_and_go():
    """Over 200 frames (sampled), both known and unknown kinds appear; tracks start and end."""
    s = SyntheticSource(n_frames=200, width=621, height=188, fx=360.77)
    plan = s.plan("0000")
    seen: dict[int, list[int]] = {}
    kinds = set()
    moving = False
    for i in range(0, 200, 8):
        for o in s.read_frame(plan, i).truth.objects:
            seen.setdefault(o.track_id, []).append(i)
            kinds.add((o.category, o.known))
            moving |= float(np.linalg.norm(o.velocity_world)) > 0.5
    assert any(k for _, k in kinds) and any(not k for _, k in kinds), kinds
    assert moving
    first, last = min(min(v) for v in seen.values()), max(max(v) for v in seen.values())
    assert any(min(v) > first for v in seen.values())  # tracks start after the first frame
    assert any(max(v) < last for v in seen.values())  # and end before the last


def test_bench_render_runs():
    assert bench_render(1, width=160, height=64, fx=90.0, n_frames=5) > 0


def _camera_faces(src: SyntheticSource, sequence: str, position: int):
    """The renderer's inputs for the left camera of one frame (real scene, no shortcuts)."""
    from mining.sources.synthetic import render
    from mining.sources.synthetic.scene import frame_faces

    plan = src.plan(sequence)
    sc = src.scene(sequence)
    t = plan.t_ns[position] / 1e9
    c = src.calib
    cam = render.Camera(c.fx, c.fy, c.cx, c.cy, c.width, c.height)
    verts, rows, _ = frame_faces(sc, t)
    M = sc.camera_map(t)
    R = M[:3, :3].T
    V, rows_cam = render.to_camera(verts, rows, R, -R @ M[:3, 3])
    C, dp = render.inverse_depth_planes(cam, rows_cam, V)
    return cam, V, rows_cam, C, dp, rows, M


def test_vectorised_small_faces_agree_with_the_per_face_raster(src):
    """The one-pass raster of small faces and the per-face loop give the same image up to edge pixels."""
    from mining.sources.synthetic import render

    from mining.sources.synthetic.scene import R_OBJ

    cam, V, rows_cam, C, dp, rows, _ = _camera_faces(src, "0002", 30)
    ids_fast, invz_fast = render.rasterize(cam, V, rows_cam, C, dp)
    ids_loop, invz_loop = render.rasterize(cam, V, rows_cam, C, dp, small_px=0)
    same = ids_fast == ids_loop
    assert same.mean() > 0.998, same.mean()  # edge pixels only (object meshes have many small faces)
    obj_of = np.r_[rows[:, R_OBJ].astype(int), -1]
    assert (obj_of[ids_fast] == obj_of[ids_loop]).mean() > 0.999  # the truth masks agree closer still
    assert np.allclose(invz_fast[same], invz_loop[same], rtol=1e-5)
    faces_fast, faces_loop = set(np.unique(ids_fast).tolist()), set(np.unique(ids_loop).tolist())
    lost = np.isin(ids_loop, sorted(faces_loop - faces_fast))  # only slivers may go: a few pixels each
    assert lost.mean() < 5e-4 and max(np.bincount(ids_loop[lost] + 1).max(initial=0), 0) <= 16
    # distant objects (made of small faces) keep their size
    obj = np.r_[rows[:, R_OBJ].astype(int), 0]
    o_fast, o_loop = obj[ids_fast], obj[ids_loop]
    counts = [((o_loop == o).sum(), (o_fast == o).sum()) for o in np.unique(o_loop[o_loop > 0])]
    small_objects = [(a, b) for a, b in counts if 10 <= a < 400]
    assert len(small_objects) >= 5
    ratios = [b / a for a, b in small_objects]
    assert 0.9 < np.median(ratios) < 1.12, ratios
    assert all(0.7 < r < 1.5 for r in ratios), ratios  # (a far person's sub-pixel limbs come out a little fat)


def test_texture_coordinates_follow_the_surface(src):
    """Per-face homographies give the texture coordinate of the 3D point each pixel sees."""
    from mining.sources.synthetic import render
    from mining.sources.synthetic.scene import R_O, R_TILE, R_U

    cam, V, rows_cam, C, dp, rows, M = _camera_faces(src, "0002", 30)
    ids, invz = render.rasterize(cam, V, rows_cam, C, dp)
    tab = render.texture_tables(cam, src.scene("0002").atlas, V, rows_cam, C)
    ys, xs = np.nonzero(ids >= 0)
    pick = np.random.default_rng(2).choice(len(ys), 2000, replace=False)
    v, u, f = ys[pick], xs[pick], ids[ys[pick], xs[pick]]
    z = 1.0 / invz[v, u].astype(np.float64)
    X = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], 1)  # camera frame
    s_true = np.einsum("ij,ij->i", rows_cam[f, R_U : R_U + 3], X - rows_cam[f, R_O : R_O + 3]) / rows_cam[f, R_TILE + 2]
    s_hom = (tab[0, f] * u + tab[1, f] * v + tab[2, f]) / invz[v, u]
    wrap = (s_hom - s_true) - np.round(s_hom - s_true)  # the tables may shift by whole repeats
    texels = np.abs(wrap) * rows_cam[f, R_TILE + 2]
    assert np.percentile(texels, 99) < 0.05, np.percentile(texels, 99)
    assert np.allclose(np.round(s_hom - s_true), np.round(s_hom - s_true).astype(int))


def test_shading_band_height_changes_no_bit(src):
    from mining.sources.synthetic import render
    from mining.sources.synthetic.scene import R_TINT

    cam, V, rows_cam, C, dp, rows, M = _camera_faces(src, "0000", 40)
    ids, invz = render.rasterize(cam, V, rows_cam, C, dp)
    atlas = src.scene("0000").atlas
    tab = render.texture_tables(cam, atlas, V, rows_cam, C)
    light = rows[:, R_TINT : R_TINT + 3].astype(np.float32)
    sky = np.full((cam.h, cam.w, 3), 200.0, np.float32)
    a = render.shade(cam, atlas, ids, invz, tab, light, sky, strip=7)
    b = render.shade(cam, atlas, ids, invz, tab, light, sky, strip=cam.h)
    assert np.array_equal(a, b)
    assert np.array_equal(a[ids < 0], sky[ids < 0]) and a[ids >= 0].std() > 10


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_module_writes_frames_for_a_look(tmp_path):
    from mining.sources.synthetic.__main__ import main

    main(["--seq", "0000", "--frames", "3:4", "--n-frames", "10", "--out", str(tmp_path)])
    stem = tmp_path / "0000_000003"
    left = cv2.imread(f"{stem}_left.png")
    expect = SyntheticSource(n_frames=10).read_frame(SyntheticSource(n_frames=10).plan("0000"), 3)
    assert np.array_equal(left[:, :, ::-1], expect.left)  # the rendered frame, bit for bit
    for kind in ("right", "depth", "inst"):
        img = cv2.imread(f"{stem}_{kind}.png")
        assert img.shape == expect.left.shape and img.any()


def test_module_times_the_renderer(capsys):
    from mining.sources.synthetic.__main__ import main

    main(["--seq", "0001", "--bench", "2", "--n-frames", "5"])
    out = capsys.readouterr().out
    assert "2 frames 1242x375" in out and "frames/s" in out
