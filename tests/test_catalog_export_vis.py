"""`mine export`: YouTube-VIS and TAO JSON, crops with context and per-frame index, and the
DEST rules (non-empty refused, --overwrite replaces what the last export recorded, nothing
matched exits 1), on the real KITTI 0005 catalogue."""

from __future__ import annotations

import json
import re

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from pycocotools import mask as mask_utils

from _catalog_data import DATASET, N_FRAMES, SEQUENCE
from mining.catalog.schema import SCHEMAS
from mining.catalog.store import Store, write_sequence
from mining.cli import main
from mining.errors import MiningError
from mining.export.crops import crop_box
from mining.export.dest import RECORD
from mining.export.json_annotations import CLUTTER_ID, UNCLASSIFIED_ID, UNKNOWN_ID
from mining.export.run import LABELS_FILE, run_export
from mining.export.selection import frame_digits
from mining.names import tube_folder
from mining.types import CALLS

H, W = 375, 1242
CAR = 3  # COCO's annotation id of "car"


def _selected(tables) -> list[dict]:
    return [t for t in tables["tubes"].to_pylist() if t["selected"]]


def _frames(tables) -> dict[str, dict[int, dict]]:
    out: dict[str, dict[int, dict]] = {}
    for f in tables["tube_frames"].to_pylist():
        out.setdefault(f["tube_id"], {})[f["frame"]] = f
    return out


def _decode(rle: dict) -> np.ndarray:
    return mask_utils.decode(rle)


def _xywh(b) -> list[float]:
    return [b[0], b[1], b[2] - b[0], b[3] - b[1]]


@pytest.fixture(scope="module")
def ytvis(catalogue, tmp_path_factory):
    out, _ = catalogue
    dest = tmp_path_factory.mktemp("ytvis") / "vis"
    assert run_export(str(out), "selected", "youtube-vis", str(dest), images=True) == 0
    return dest, json.loads((dest / "instances.json").read_text())


@pytest.fixture(scope="module")
def tao(catalogue, tmp_path_factory):
    out, _ = catalogue
    dest = tmp_path_factory.mktemp("tao") / "tao"
    assert run_export(str(out), "selected", "tao", str(dest)) == 0
    return dest, json.loads((dest / "tao.json").read_text())


def _with_kinds(catalogue, tmp_path):
    """A copy of the catalogue whose selected tubes are called known, unknown, clutter and unclassified in turn."""
    out, tables = catalogue
    rows = tables["tubes"].to_pylist()
    for i, r in enumerate(r for r in rows if r["selected"]):
        r["call"] = CALLS[i % 4]
        r["known"] = {"known": True, "unknown": False, "clutter": False, "unclassified": None}[r["call"]]
        r["category"] = {True: "car", False: "unknown", None: None}[r["known"]]
    cat = tmp_path / "cat"
    store = Store(cat)
    write_sequence(store, "tubes", DATASET, SEQUENCE, pa.Table.from_pylist(rows, schema=SCHEMAS["tubes"]))
    write_sequence(store, "tube_frames", DATASET, SEQUENCE, tables["tube_frames"])
    store.write_bytes("job.json", Store(out).read_bytes("job.json"))
    return cat, {r["tube_id"]: r["call"] for r in rows if r["selected"]}


def test_youtube_vis_one_video_of_the_mined_frames(ytvis):
    _, doc = ytvis
    assert len(doc["videos"]) == 1
    v = doc["videos"][0]
    assert (v["width"], v["height"], v["length"]) == (W, H, N_FRAMES) == (W, H, len(v["file_names"]))
    assert v["file_names"] == [f"{DATASET}_{SEQUENCE}/{k:06d}.jpg" for k in range(N_FRAMES)]
    assert doc["categories"] == [{"id": CAR, "name": "car", "supercategory": "coco"}], "only the categories used"


def test_youtube_vis_masks_decode_to_the_catalogues(ytvis, catalogue):
    """One RLE or null per video frame, reading with pycocotools as YouTube-VIS's API reads its
    uncompressed RLE (``frPyObjects``) to h×w, equal to the catalogue's mask; boxes COCO xywh of
    the catalogue's x1y1x2y2; null where not observed. The results file: the same masks as
    compressed RLE (counts a string), with the tube's category and score."""
    dest, doc = ytvis
    _, tables = catalogue
    frames = _frames(tables)
    anns = doc["annotations"]
    results = json.loads((dest / "results" / "results.json").read_text())
    assert [r["tube_id"] for r in results] == [a["tube_id"] for a in anns]
    assert sorted(a["tube_id"] for a in anns) == sorted(t["tube_id"] for t in _selected(tables))
    for a, r in zip(anns, results):
        assert a["video_id"] == 1 and a["iscrowd"] == 0 and isinstance(a["score"], float)
        assert (r["video_id"], r["category_id"], r["score"]) == (a["video_id"], a["category_id"], a["score"])
        assert len(a["segmentations"]) == len(a["bboxes"]) == len(a["areas"]) == N_FRAMES == len(r["segmentations"])
        tf = frames[a["tube_id"]]
        for k, (seg, box, area) in enumerate(zip(a["segmentations"], a["bboxes"], a["areas"])):
            if k not in tf or not tf[k]["observed"]:
                assert seg is None and box is None and area is None and r["segmentations"][k] is None
                continue
            assert isinstance(seg["counts"], list) and seg["size"] == [H, W] and sum(seg["counts"]) == H * W
            m = _decode(mask_utils.frPyObjects(seg, H, W))
            assert isinstance(r["segmentations"][k]["counts"], str) and (_decode(r["segmentations"][k]) == m).all()
            assert m.shape == (H, W) and m.sum() == area > 0
            ref = _decode({"size": [H, W], "counts": tf[k]["rle_counts"].encode()})
            assert (m == ref).all()
            np.testing.assert_allclose(box, _xywh(tf[k]["bbox"]), atol=1e-3)


def test_youtube_vis_categories_follow_the_call(catalogue, tmp_path):
    cat, calls = _with_kinds(catalogue, tmp_path)
    assert run_export(str(cat), "selected", "youtube-vis", str(tmp_path / "v")) == 0
    doc = json.loads((tmp_path / "v" / "instances.json").read_text())
    want = {"known": CAR, "unknown": UNKNOWN_ID, "clutter": CLUTTER_ID, "unclassified": UNCLASSIFIED_ID}
    assert {a["tube_id"]: a["category_id"] for a in doc["annotations"]} == {t: want[k] for t, k in calls.items()}
    cats = {c["id"]: c["name"] for c in doc["categories"]}
    assert cats == {want[c]: "car" if c == "known" else c for c in calls.values()} and len(cats) >= 3
    own = (UNKNOWN_ID, CLUTTER_ID, UNCLASSIFIED_ID)
    assert max(c for c in cats if c not in own) <= 90 < min(own) and len(set(own)) == 3


def test_youtube_vis_images_are_the_source_frames(ytvis, kitti_tracking_root):
    dest, doc = ytvis
    names = doc["videos"][0]["file_names"]

    def src(k):
        return cv2.imread(str(kitti_tracking_root / "training" / "image_02" / SEQUENCE / f"{k:06d}.png")).astype(np.int32)

    for k, other in ((0, N_FRAMES - 1), (N_FRAMES - 1, 0)):
        got = cv2.imread(str(dest / "JPEGImages" / names[k])).astype(np.int32)
        own, theirs = np.abs(got - src(k)).mean(), np.abs(got - src(other)).mean()
        assert got.shape == (H, W, 3) and own < 6 and own < theirs / 3, "the frame, up to JPEG loss"


def test_tao_tracks_images_and_annotations(tao, catalogue):
    """Every observed tube frame is one annotation on the image of its frame, in its tube's
    track; boxes xywh; RLE masks decode to the catalogue's; the results file holds the same
    detections."""
    dest, doc = tao
    _, tables = catalogue
    frames = _frames(tables)
    assert [v["name"] for v in doc["videos"]] == [f"{DATASET}_{SEQUENCE}"]
    images = {i["id"]: i for i in doc["images"]}
    assert sorted(i["frame"] for i in images.values()) == list(range(N_FRAMES))
    assert all(i["file_name"] == f"{DATASET}_{SEQUENCE}/{i['frame']:06d}.jpg" for i in images.values())
    tracks = {t["id"]: t for t in doc["tracks"]}
    assert sorted(t["tube_id"] for t in tracks.values()) == sorted(t["tube_id"] for t in _selected(tables))
    assert len({a["id"] for a in doc["annotations"]}) == len(doc["annotations"])
    assert len(doc["annotations"]) == sum(f["observed"] for t in _selected(tables) for f in frames[t["tube_id"]].values())
    for a in doc["annotations"]:
        track, image = tracks[a["track_id"]], images[a["image_id"]]
        assert a["video_id"] == track["video_id"] == image["video_id"] and a["category_id"] == track["category_id"] == CAR
        f = frames[track["tube_id"]][image["frame"]]
        np.testing.assert_allclose(a["bbox"], _xywh(f["bbox"]), atol=1e-3)
        m = _decode(a["segmentation"])
        assert m.shape == (H, W) and m.sum() == a["area"] > 0
    assert doc["categories"] == [{"id": CAR, "name": "car", "synset": "car.n.01"}], "only the categories used"
    results = json.loads((dest / "results" / "results.json").read_text())
    assert [(r["image_id"], r["track_id"], r["bbox"], r["segmentation"]) for r in results] == [
        (a["image_id"], a["track_id"], a["bbox"], a["segmentation"]) for a in doc["annotations"]]


def test_crops_margin_widens_the_context(catalogue, tmp_path):
    out, tables = catalogue
    tube = _selected(tables)[0]
    where = f"tube_id = '{tube['tube_id']}'"
    assert run_export(str(out), where, "crops", str(tmp_path / "wide"), margin=0.5) == 0
    assert run_export(str(out), where, "crops", str(tmp_path / "tight")) == 0
    f = min(_frames(tables)[tube["tube_id"]].values(), key=lambda f: f["frame"])
    name = f"crop_{f['frame']:06d}.png"
    wide = cv2.imread(str(tmp_path / "wide" / tube_folder(tube["tube_id"]) / name))
    tight = cv2.imread(str(tmp_path / "tight" / tube_folder(tube["tube_id"]) / name))
    x0, x1, y0, y1 = crop_box(f["bbox"], W, H, 0.5)
    assert wide.shape[:2] == (y1 - y0, x1 - x0)
    assert wide.shape[0] > tight.shape[0] and wide.shape[1] > tight.shape[1]
    with pytest.raises(MiningError, match="^--margin applies to --format crops only$"):
        run_export(str(out), where, "kitti", str(tmp_path / "k"), margin=0.5)


def test_crops_index_has_the_box_and_position_of_every_frame(catalogue, tmp_path):
    out, tables = catalogue
    dest = tmp_path / "crops"
    assert run_export(str(out), "selected", "crops", str(dest)) == 0
    frames = _frames(tables)
    for row in pq.read_table(dest / "index.parquet").to_pylist():
        tf = frames[row["tube_id"]]
        assert [e["frame"] for e in row["track"]] == sorted(tf)
        for e in row["track"]:
            f = tf[e["frame"]]
            np.testing.assert_allclose(e["bbox"], f["bbox"])
            np.testing.assert_allclose(e["bbox_xywh"], _xywh(f["bbox"]), atol=1e-4)
            np.testing.assert_allclose(e["position_cam"], f["position_cam"])
            np.testing.assert_allclose(e["position_world"], f["position_world"])
            assert e["crop"] == f"crop_{e['frame']:06d}.png" and e["mask"] == f"mask_{e['frame']:06d}.png"
            assert (dest / row["folder"] / e["crop"]).is_file() and (dest / row["folder"] / e["mask"]).is_file()
            x0, y0, x1, y1 = e["crop_box"]
            assert (x0, x1, y0, y1) == crop_box(f["bbox"], W, H)


def test_frame_numbers_pad_to_the_largest_frame():
    assert frame_digits([0, 15]) == 6 and frame_digits(range(1_234_568)) == 7
    names = [f"crop_{k:0{frame_digits([0, 150])}d}.png" for k in (0, 1, 10, 100)]
    assert names == sorted(names)


def test_non_empty_dest_is_refused(catalogue, tmp_path, capsys):
    out, _ = catalogue
    dest = tmp_path / "d"
    dest.mkdir()
    (dest / "notes.txt").write_text("mine")
    with pytest.raises(MiningError, match="not empty"):
        run_export(str(out), "selected", "kitti", str(dest))
    assert [p.name for p in dest.iterdir()] == ["notes.txt"]


def test_overwrite_replaces_exactly_what_the_last_export_wrote(catalogue, tmp_path):
    """An export of three tubes, then one of one tube with --overwrite: the old tube folders
    go, a file the user put beside them and a file outside DEST stay."""
    out, tables = catalogue
    dest = tmp_path / "crops"
    assert run_export(str(out), "selected", "crops", str(dest)) == 0
    assert len([p for p in dest.iterdir() if p.is_dir()]) == 3
    (dest / "notes.txt").write_text("mine")
    (tmp_path / "outside.txt").write_text("outside")
    one = _selected(tables)[0]["tube_id"]
    assert run_export(str(out), f"tube_id = '{one}'", "crops", str(dest), overwrite=True) == 0
    assert sorted(p.name for p in dest.iterdir()) == sorted([RECORD, "index.json", "index.parquet", "notes.txt",
                                                             LABELS_FILE, tube_folder(one)])
    assert (tmp_path / "outside.txt").read_text() == "outside"
    assert json.loads((dest / RECORD).read_text())["written"] == sorted(["index.json", "index.parquet", LABELS_FILE,
                                                                         tube_folder(one)])


def test_overwrite_needs_an_export_record(catalogue, tmp_path, capsys):
    out, _ = catalogue
    dest = tmp_path / "d"
    dest.mkdir()
    (dest / "photo.png").write_bytes(b"x")
    with pytest.raises(MiningError, match=re.escape(RECORD)):
        run_export(str(out), "selected", "kitti", str(dest), overwrite=True)
    assert [p.name for p in dest.iterdir()] == ["photo.png"]


def test_nothing_matched_exits_1_and_keeps_the_old_export(catalogue, tmp_path, capsys):
    out, _ = catalogue
    dest = tmp_path / "k"
    assert run_export(str(out), "selected", "kitti", str(dest)) == 0
    before = sorted(p.name for p in dest.iterdir())
    assert main(["export", "--out", str(out), "--where", "n_frames > 10000", "--format", "kitti", "--overwrite",
                 str(dest)]) == 1
    assert "no tube matches" in capsys.readouterr().err
    assert sorted(p.name for p in dest.iterdir()) == before


def test_cli_export_options(catalogue, tmp_path):
    out, _ = catalogue
    dest = tmp_path / "c"
    assert main(["export", "--out", str(out), "--format", "crops", "--margin", "0.3", str(dest)]) == 0
    assert json.loads((dest / RECORD).read_text())["options"] == {"margin": 0.3}
    assert main(["export", "--out", str(out), "--format", "tao", "--images", str(tmp_path / "t")]) == 0
    assert len(list((tmp_path / "t" / "frames" / f"{DATASET}_{SEQUENCE}").glob("*.jpg"))) == N_FRAMES
