"""`mine export --format fiftyone | rerun` on the real KITTI 0005 catalogue, read back with the
formats' own readers: FiftyOne's importer for ``FiftyOneVideoLabelsDataset`` (no database:
the importer parses the files itself) and the Rerun SDK's ``RrdReader``."""

from __future__ import annotations

import shutil
import sys

import cv2
import numpy as np
import pyarrow as pa
import pytest
from pycocotools import mask as mask_utils

from _catalog_data import DATASET, N_FRAMES, SEQUENCE
from mining.catalog.schema import SCHEMAS
from mining.catalog.store import Store, write_sequence
from mining.catalog.views import connect
from mining.cli import main
from mining.export.selection import category_label

H, W = 375, 1242  # KITTI 0005's rectified frames
VIDEO = f"{DATASET}_{SEQUENCE}"


def _with_kinds(catalogue, tmp_path):
    """A copy of the catalogue whose selected tubes are called known, unknown, unclassified and clutter in turn."""
    out, tables = catalogue
    cat = tmp_path / "cat"
    shutil.copytree(out, cat)
    rows = tables["tubes"].to_pylist()
    for i, r in enumerate(r for r in rows if r["selected"]):
        r["call"] = ("known", "unknown", "unclassified", "clutter")[i % 4]
        r["known"] = {"known": True, "unknown": False, "clutter": False, "unclassified": None}[r["call"]]
        r["category"] = {True: "car", False: "unknown", None: None}[r["known"]]
        r["category_prob"] = None if r["known"] is None else r["category_prob"]
    write_sequence(Store(cat), "tubes", DATASET, SEQUENCE, pa.Table.from_pylist(rows, schema=SCHEMAS["tubes"]))
    return cat, rows


def _tracks(rows) -> list[dict]:
    """The selected tubes in the exports' track order (catalogue order: t_start, tube_id)."""
    return sorted((r for r in rows if r["selected"]), key=lambda t: (t["t_start"], t["tube_id"]))


def _observed(tables, tube_id: str) -> dict[int, dict]:
    return {f["frame"]: f for f in tables["tube_frames"].to_pylist() if f["tube_id"] == tube_id and f["observed"]}


def _rle(row) -> dict:
    return {"size": [row["rle_h"], row["rle_w"]], "counts": row["rle_counts"].encode()}


# -- FiftyOne ---------------------------------------------------------------------------------


def _fiftyone_samples(dest):
    """(video path, frames) of every sample, as FiftyOne's own importer for the type reads them."""
    import fiftyone.types as fot

    importer = fot.FiftyOneVideoLabelsDataset().get_dataset_importer_cls()(str(dest))
    with importer:
        return [(video, frames) for video, _, _, frames in importer]


def test_fiftyone_export_reads_back_with_fiftyones_importer(catalogue, tmp_path, capsys):
    """No --images (the frames need not be reachable): FiftyOne still imports every label.
    Each detection: index = the tube's track id, label by the call, confidence =
    category_prob, the tube id; its mask, placed by its box on the frame, is the catalogue's
    RLE mask pixel for pixel."""
    cat, rows = _with_kinds(catalogue, tmp_path)
    _, tables = catalogue
    dest = tmp_path / "fo"
    assert main(["export", "--out", str(cat), "--format", "fiftyone", str(dest)]) == 0
    assert "1 videos" in capsys.readouterr().out
    assert not (dest / "data").exists(), "no video without --images"
    [(video, frames)] = _fiftyone_samples(dest)
    assert video == str(dest / "data" / f"{VIDEO}.mp4")
    assert len(frames) == N_FRAMES, "every mined frame is a video frame"
    vw, vh = W, H + 1  # the video's even sides
    source_frame = {n: int(float(f["source_frame"].label)) for n, f in frames.items()}
    assert sorted(source_frame.values()) == list(range(N_FRAMES)) and source_frame[1] == 0

    tracks = _tracks(rows)
    want = {(fr, k) for k, t in enumerate(tracks) for fr in _observed(tables, t["tube_id"])}
    with_dets = {n: f["detections"].detections for n, f in frames.items() if "detections" in f}
    assert len(with_dets) == len({fr for fr, _ in want}) > 0, "frames with detections"
    got = set()
    for n, dets in with_dets.items():
        for d in dets:
            t = tracks[d.index]
            got.add((source_frame[n], d.index))
            assert d["tube_id"] == t["tube_id"] and d.label == category_label(t)
            assert d.confidence == (None if t["category_prob"] is None else pytest.approx(t["category_prob"]))
            row = _observed(tables, t["tube_id"])[source_frame[n]]
            full = mask_utils.decode(_rle(row)).astype(bool)
            x, y, w, h = d.bounding_box
            x0, y0, bw, bh = round(x * vw), round(y * vh), round(w * vw), round(h * vh)
            assert d.mask.shape == (bh, bw)
            assert int(d.mask.sum()) == int(mask_utils.area(_rle(row))) == int(full.sum())
            placed = np.zeros((H, W), bool)
            placed[y0:y0 + bh, x0:x0 + bw] = d.mask
            assert (placed == full).all(), f"frame {source_frame[n]} track {d.index}: the mask is not the catalogue's"
            b = row["bbox"]
            assert x0 <= b[0] + 1e-3 and y0 <= b[1] + 1e-3 and x0 + bw >= b[2] - 1e-3 and y0 + bh >= b[3] - 1e-3
    assert got == want
    labels = {d.label for dets in with_dets.values() for d in dets}
    assert labels == {category_label(t) for t in tracks} >= {"car", "unknown", "unclassified"}


@pytest.mark.slow
def test_fiftyone_images_write_the_video_the_manifest_names(catalogue, tmp_path):
    """--images: DEST/data/<video>.mp4 holds the mined frames (even-sided), readable by OpenCV,
    and its first frame is the source's left image."""
    out, _ = catalogue
    dest = tmp_path / "fo"
    assert main(["export", "--out", str(out), "--format", "fiftyone", "--images", str(dest)]) == 0
    [(video, frames)] = _fiftyone_samples(dest)
    cap = cv2.VideoCapture(video)
    try:
        assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == len(frames) == N_FRAMES
        ok, first = cap.read()
    finally:
        cap.release()
    assert ok and first.shape == (H + 1, W, 3)
    from mining.sources.kitti import KittiTrackingSource
    from mining.export.selection import read_job

    src = read_job(out).source.open()
    assert isinstance(src, KittiTrackingSource)
    left = src.read_frame(src.plan(SEQUENCE, 0, 1), 0).left
    err = np.abs(first[:H].astype(int) - cv2.cvtColor(left, cv2.COLOR_RGB2BGR).astype(int)).mean()
    assert err < 6, f"the first video frame is not the source's frame 0 (mean error {err:.1f})"


# -- Rerun ------------------------------------------------------------------------------------


def _entities(path) -> dict[str, list[dict]]:
    """Every row of the recording per entity path, read with the Rerun SDK's own reader."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    [rec] = reader.recordings()
    assert (rec.application_id, rec.recording_id) == ("tube_miner", f"{DATASET}/{SEQUENCE}")
    out: dict[str, list[dict]] = {}
    for chunk in reader.stream():
        out.setdefault(chunk.entity_path, []).extend(chunk.to_record_batch().to_pylist())
    return out


def _at(rows: list[dict], column: str) -> dict[int, object]:
    return {r["frame"]: r[column] for r in rows if r.get(column) is not None}


def _check_recording(ents: dict, catalogue, rows) -> None:
    out, tables = catalogue
    con = connect(out)
    try:
        frames = [{"frame": f, "pose": p} for f, p in con.execute("SELECT frame, pose FROM frames ORDER BY frame").fetchall()]
    finally:
        con.close()
    cam = ents["/world/camera"]
    assert sorted(_at(cam, "Transform3D:translation")) == [f["frame"] for f in frames] == list(range(N_FRAMES))
    for f in frames:
        pose = np.asarray(f["pose"]).reshape(4, 4)
        np.testing.assert_allclose(_at(cam, "Transform3D:translation")[f["frame"]], [pose[:3, 3]], atol=1e-5)
        np.testing.assert_allclose(np.asarray(_at(cam, "Transform3D:mat3x3")[f["frame"]][0]).reshape(3, 3, order="F"),
                                   pose[:3, :3], atol=1e-6)
    tracks = _tracks(rows)
    assert len(tracks) >= 2
    seg = _at(ents["/world/camera/image/tubes"], "SegmentationImage:buffer")
    assert sorted(seg) == list(range(N_FRAMES))
    for k, t in enumerate(tracks):
        obs = _observed(tables, t["tube_id"])
        positions = _at(ents[f"/world/tubes/{k}"], "Points3D:positions")
        assert sorted(positions) == sorted(obs), f"track {k}: the frames of its 3D positions"
        for fr, row in obs.items():
            np.testing.assert_allclose(positions[fr], [row["position_world"]], atol=1e-6)
            ids = np.frombuffer(bytes(seg[fr][0]), np.uint16).reshape(H, W)
            mask = mask_utils.decode(_rle(row)).astype(bool)
            assert (ids == k + 1).sum() > 0 and not ((ids == k + 1) & ~mask).any(), "its pixels lie in its mask"
        [static] = [r for r in ents[f"/world/tubes/{k}"] if r.get("tube_id") is not None]
        assert static["tube_id"] == [t["tube_id"]]
    boxes = _at(ents["/world/camera/image/boxes"], "Boxes2D:class_ids")
    assert sum(len(v) for v in boxes.values()) == sum(len(_observed(tables, t["tube_id"])) for t in tracks)


def test_rerun_recording_holds_poses_tubes_and_masks_over_frames(catalogue, tmp_path, capsys):
    """Without --images (frames need not be reachable): poses, the tubes in 3D, masks and
    boxes over the frame timeline, read back with Rerun's RrdReader."""
    out, tables = catalogue
    dest = tmp_path / "rr"
    assert main(["export", "--out", str(out), "--format", "rerun", str(dest)]) == 0
    assert "1 recordings" in capsys.readouterr().out
    ents = _entities(dest / f"{VIDEO}.rrd")
    _check_recording(ents, catalogue, tables["tubes"].to_pylist())
    assert "/world/camera/image/rgb" not in ents and "/world/camera/image/depth" not in ents


@pytest.mark.slow
def test_rerun_images_add_the_frames_depth_and_pinhole(catalogue, tmp_path):
    out, tables = catalogue
    dest = tmp_path / "rr"
    assert main(["export", "--out", str(out), "--format", "rerun", "--images", str(dest)]) == 0
    ents = _entities(dest / f"{VIDEO}.rrd")
    _check_recording(ents, catalogue, tables["tubes"].to_pylist())
    rgb = _at(ents["/world/camera/image/rgb"], "EncodedImage:blob")
    assert sorted(rgb) == list(range(N_FRAMES))
    first = cv2.imdecode(np.frombuffer(bytes(rgb[0][0]), np.uint8), cv2.IMREAD_COLOR)
    assert first.shape == (H, W, 3)
    depth = _at(ents["/world/camera/image/depth"], "DepthImage:buffer")
    assert sorted(depth) == list(range(N_FRAMES))
    z = np.frombuffer(bytes(depth[0][0]), np.uint16).reshape(H, W) / 256.0  # metres (the depth image's meter)
    assert (z > 0).mean() > 0.3 and np.median(z[z > 0]) < 90, "most pixels have a stereo depth, in metres"
    [meter] = [r["DepthImage:meter"] for r in ents["/world/camera/image/depth"] if r.get("DepthImage:meter")][:1]
    assert meter == [256.0]
    [pin] = [r for r in ents["/world/camera/image"] if r.get("Pinhole:image_from_camera") is not None]
    assert pin["Pinhole:resolution"] == [[W, H]]


def test_missing_extras_are_named(catalogue, tmp_path, capsys, monkeypatch):
    """Without the Rerun SDK the export says which extra brings it, writing nothing."""
    out, _ = catalogue
    monkeypatch.setitem(sys.modules, "rerun", None)  # `import rerun` raises ImportError, as when not installed
    dest = tmp_path / "rr"
    assert main(["export", "--out", str(out), "--format", "rerun", str(dest)]) == 2
    assert "pip install 'tube-miner[rerun]'" in capsys.readouterr().err
    assert not dest.exists() or not [p for p in dest.iterdir() if not p.name.startswith(".")]
