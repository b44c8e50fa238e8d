"""`mine export`: KITTI tracking txt, KITTI-MOTS txt and per-tube crops from a real catalogue."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from pycocotools import mask as mask_utils

from _catalog_data import DATASET, SEQUENCE
from mining.catalog.schema import SCHEMAS
from mining.catalog.store import Store, write_sequence
from mining.cli import main
from mining.export.crops import crop_box
from mining.export.kitti import disjoint_masks
from mining.errors import MiningError
from mining.export.run import run_export
from mining.formats.kitti_tracking import read_kitti_tracking
from mining.names import tube_folder
from mining.pipeline.kitti_export import write_tubes_kitti


def _sorted(rows):
    return np.lexsort((rows.box[:, 0], rows.frame))


def test_kitti_matches_the_tracker_export(catalogue, tmp_path, kitti_tracking_root):
    """Catalogue → KITTI txt gives the rows the in-memory exporter writes for the same tubes."""
    from mining.sources.kitti import KittiTrackingSource

    out, tables = catalogue
    assert run_export(str(out), "selected", "kitti", str(tmp_path / "kitti")) == 0
    got = read_kitti_tracking(tmp_path / "kitti" / f"{SEQUENCE}.txt", require_score=True)
    kcalib = KittiTrackingSource(str(kitti_tracking_root)).kitti_calib(SEQUENCE)
    write_tubes_kitti(tmp_path / "ref.txt", tables["mined"], rect0_from_cam2=kcalib.cam2_to_rect0)
    ref = read_kitti_tracking(tmp_path / "ref.txt", require_score=True)
    assert len(got) == len(ref) > 0
    g, r = _sorted(got), _sorted(ref)
    assert (got.frame[g] == ref.frame[r]).all() and (got.type[g] == ref.type[r]).all()
    np.testing.assert_allclose(got.box[g], ref.box[r], atol=1e-3)
    np.testing.assert_allclose(got.location[g], ref.location[r], atol=1e-3)
    np.testing.assert_allclose(got.dimensions[g], ref.dimensions[r], atol=1e-3)
    np.testing.assert_allclose(got.score[g], ref.score[r], rtol=1e-6)
    # Integer track ids, one per selected tube, consistent with the tubes' frames.
    selected = [m for m in tables["mined"] if m.selected]
    assert sorted(set(got.track_id)) == list(range(len(selected)))
    for tid in set(got.track_id):
        frames = got.frame[got.track_id == tid]
        assert len(frames) == len(set(frames))


def test_kitti_mots_lines_and_disjoint_masks(catalogue, tmp_path):
    out, tables = catalogue
    dest = tmp_path / "mots"
    assert run_export(str(out), "selected", "kitti-mots", str(dest)) == 0
    lines = (dest / f"{SEQUENCE}.txt").read_text().splitlines()
    tf = tables["tube_frames"].to_pylist()
    selected = {t["tube_id"] for t in tables["tubes"].to_pylist() if t["selected"]}
    assert len(lines) == sum(1 for f in tf if f["tube_id"] in selected and f["observed"])
    by_frame = {}
    for line in lines:
        frame, obj_id, cls, h, w, rle = line.split(" ")
        assert int(cls) in (1, 2, 10) and int(obj_id) // 1000 == int(cls) and (int(h), int(w)) == (375, 1242)
        by_frame.setdefault(int(frame), []).append({"size": [375, 1242], "counts": rle.encode()})
    assert {int(line.split()[2]) for line in lines} == {1}, "the PointRCNN cars of 0005 are class 1"
    for rles in by_frame.values():
        masks = mask_utils.decode(rles).astype(np.int32)
        assert masks.sum(axis=2).max() == 1, "masks of one frame overlap"


def test_kitti_mots_lower_score_loses_shared_pixels(catalogue, tmp_path):
    """A duplicate of a tube with a lower score loses every pixel: nothing of it is written."""
    out, tables = catalogue
    cat = tmp_path / "cat"
    tubes, tf = tables["tubes"], tables["tube_frames"]
    best = max(tubes.to_pylist(), key=lambda t: t["score"])
    dup = dict(best, tube_id=best["tube_id"] + "x", score=best["score"] - 1)
    dup_frames = [dict(f, tube_id=dup["tube_id"]) for f in tf.to_pylist() if f["tube_id"] == best["tube_id"]]
    store = Store(cat)
    write_sequence(store, "tubes", DATASET, SEQUENCE, pa.concat_tables(
        [tubes, pa.Table.from_pylist([dup], schema=SCHEMAS["tubes"])]))
    write_sequence(store, "tube_frames", DATASET, SEQUENCE, pa.concat_tables(
        [tf, pa.Table.from_pylist(dup_frames, schema=SCHEMAS["tube_frames"])]))
    assert run_export(str(cat), f"tube_id LIKE '{best['tube_id']}%'", "kitti-mots", str(tmp_path / "m")) == 0
    lines = (tmp_path / "m" / f"{SEQUENCE}.txt").read_text().splitlines()
    assert {line.split()[1] for line in lines} == {"1000"}
    assert len(lines) == sum(1 for f in dup_frames if f["observed"])


def test_disjoint_masks_on_real_overlapping_proposals(shared_data):
    props = json.loads((shared_data / "proposals_4dgvt_format" / "kitti_tracking_0005" / "top500" / "000000.json").read_text())
    rles = [dict(p["segmentation"], counts=p["segmentation"]["counts"].encode()) for p in props[:60]]
    iou = mask_utils.iou(rles, rles, [0] * len(rles))
    np.fill_diagonal(iou, 0)
    i, j = np.unravel_index(np.argmax(iou), iou.shape)
    assert iou[i, j] > 0.1, "real proposals overlap"
    scores = [0.3, 0.9]
    a, b = disjoint_masks([rles[i], rles[j]], scores)
    ma, mb = mask_utils.decode(rles[i]), mask_utils.decode(rles[j])
    da, db = (mask_utils.decode(dict(m, counts=m["counts"].encode())) for m in (a, b))
    assert (db == mb).all(), "the higher score keeps its mask"
    assert (da == (ma & (1 - mb))).all() and not (da & db).any()


def test_crops_are_real_image_content(catalogue, tmp_path, kitti_tracking_root):
    out, tables = catalogue
    dest = tmp_path / "crops"
    assert run_export(str(out), "selected AND n_frames >= 10", "crops", str(dest)) == 0
    tubes = [t for t in tables["tubes"].to_pylist() if t["selected"] and t["n_frames"] >= 10]
    assert tubes
    index = pq.read_table(dest / "index.parquet")
    assert set(SCHEMAS["tubes"].names) <= set(index.column_names) and {"folder", "track"} <= set(index.column_names)
    assert sorted(index["tube_id"].to_pylist()) == sorted(t["tube_id"] for t in tubes)
    assert [r["tube_id"] for r in json.loads((dest / "index.json").read_text())] == index["tube_id"].to_pylist()
    frames = {}
    for f in tables["tube_frames"].to_pylist():
        frames.setdefault(f["tube_id"], []).append(f)
    images = kitti_tracking_root / "training" / "image_02" / SEQUENCE
    for row in index.to_pylist():
        tf = sorted(frames[row["tube_id"]], key=lambda f: f["frame"])
        assert [p["frame"] for p in row["track"]] == [f["frame"] for f in tf]
        np.testing.assert_allclose([p["position_world"] for p in row["track"]], [f["position_world"] for f in tf])
        folder = dest / row["folder"]
        assert row["folder"] == tube_folder(row["tube_id"]) and "/" not in row["folder"]
        assert len(list(folder.glob("crop_*.png"))) == len(tf) == len(list(folder.glob("mask_*.png")))
        for f in tf[:: max(1, len(tf) // 4)]:
            full = cv2.imread(str(images / f"{f['frame']:06d}.png"))
            x0, x1, y0, y1 = crop_box(f["bbox"], full.shape[1], full.shape[0])
            crop = cv2.imread(str(folder / f"crop_{f['frame']:06d}.png"))
            assert crop.shape == (y1 - y0, x1 - x0, 3) and crop.shape[0] > 10 and crop.shape[1] > 10
            assert (crop == full[y0:y1, x0:x1]).all() and crop.std() > 5, "the frame's own pixels"
            mask = cv2.imread(str(folder / f"mask_{f['frame']:06d}.png"), cv2.IMREAD_GRAYSCALE)
            assert set(np.unique(mask)) <= {0, 255} and mask.shape == crop.shape[:2]
            area = int(mask_utils.area({"size": [f["rle_h"], f["rle_w"]], "counts": f["rle_counts"].encode()}))
            assert (mask == 255).sum() == area > 0, "the whole mask lies inside the crop"


def test_crops_of_frames_the_source_lacks_fail_clearly(catalogue, tmp_path):
    out, tables = catalogue
    cat = tmp_path / "cat"
    store = Store(cat)
    tf = tables["tube_frames"]
    late = tf.set_column(tf.schema.get_field_index("frame"), SCHEMAS["tube_frames"].field("frame"),
                         pa.array(np.asarray(tf["frame"]) + 400, pa.int32()))
    write_sequence(store, "tubes", DATASET, SEQUENCE, tables["tubes"])
    write_sequence(store, "tube_frames", DATASET, SEQUENCE, late)
    store.write_bytes("job.json", Store(out).read_bytes("job.json"))
    # refused before DEST is touched (export/frame_plan.py), naming the file, frame and sequence
    with pytest.raises(MiningError, match=r"tube_frames/kitti/0005/part-0\.parquet, frame 400: .* which the source's "
                                          "sequence kitti/0005"):
        run_export(str(cat), "selected", "crops", str(tmp_path / "c"))
    assert not (tmp_path / "c").exists()


HUGE = 5700  # a 5700 × 5700 mask: 32.5 MP, under the viewer's 8K bound, but not the size of KITTI's frames


def _huge_rle() -> tuple[str, int, int]:
    """(counts, h, w) of a well-formed 5700 × 5700 RLE: a 100 × 100 square in an empty frame."""
    runs = [0, 100] + [HUGE - 100, 100] * 99  # the top 100 pixels of the first 100 columns (column-major)
    runs.append(HUGE * HUGE - sum(runs))
    rle = mask_utils.frPyObjects({"size": [HUGE, HUGE], "counts": runs}, HUGE, HUGE)
    return rle["counts"].decode(), HUGE, HUGE


def _with_a_bad_mask(catalogue, cat, damage: str):
    """A copy of the catalogue at ``cat`` where one observed frame of a selected tube has a bad
    mask: ``malformed`` RLE counts whose runs do not cover the mask, or a well-formed ``5700²``
    mask on KITTI's 1242 × 375 frames; that tube's id."""
    out, tables = catalogue
    selected = sorted(t["tube_id"] for t in tables["tubes"].to_pylist() if t["selected"])
    rows = tables["tube_frames"].to_pylist()
    bad = next(r for r in rows if r["tube_id"] == selected[0] and r["observed"])
    if damage == "malformed":
        bad["rle_counts"] = "0" + bad["rle_counts"]  # one more run: the runs no longer add up to H × W
    else:
        bad["rle_counts"], bad["rle_h"], bad["rle_w"] = _huge_rle()
    store = Store(cat)
    write_sequence(store, "tubes", DATASET, SEQUENCE, tables["tubes"])
    write_sequence(store, "tube_frames", DATASET, SEQUENCE, pa.Table.from_pylist(rows, schema=SCHEMAS["tube_frames"]))
    store.write_bytes("job.json", Store(out).read_bytes("job.json"))
    return selected[0]


def _product(cat, fmt: str, dest, where: str = "selected") -> int:
    """The exit status of ``mine export`` (or ``mine render``) of ``where``; its lines on capsys."""
    if fmt == "render":
        return main(["render", str(dest), "--out", str(cat), "--sequence", SEQUENCE, "--where", where])
    return main(["export", str(dest), "--out", str(cat), "--where", where, "--format", fmt])


def _files(dest) -> dict[str, bytes]:
    """An export's files but its record (which names the predicate)."""
    return {str(p.relative_to(dest)): p.read_bytes() for p in sorted(dest.rglob("*"))
            if p.is_file() and p.name != ".mine-export.json"}


@pytest.mark.parametrize("damage", ["malformed", "5700²"])
@pytest.mark.parametrize("fmt", ["crops", "kitti-mots", "youtube-vis", "tao", "burst",
                                 pytest.param("render", marks=pytest.mark.slow)])  # render: an MP4 per tube, 5 s
def test_a_bad_mask_fails_only_its_tube_naming_it_and_the_table(catalogue, tmp_path, capsys, fmt, damage):
    """The catalogue's masks are checked as the viewer checks them, before anything decodes them
    (pycocotools trusts the runs): malformed runs, and the size against the sequence's frames
    (the old code: a traceback in pycocotools, or a KITTI-MOTS broadcast error, or a 5700²
    mask copied into the JSON). The bad tube is left out, named with the table in one line,
    exit 1; the rest is written exactly as an export of the other tubes."""
    cat = tmp_path / "cat"
    tube = _with_a_bad_mask(catalogue, cat, damage)
    name = (lambda k: f"{k}.webm") if fmt == "render" else (lambda k: k)
    code = _product(cat, fmt, tmp_path / name("dest"))
    out, err = capsys.readouterr()
    err = [ln for ln in err.strip().splitlines() if "frames/s" not in ln]  # not render's progress
    assert code == 1, (out, err)
    assert len(err) == 1 and tube in err[0] and "tube_frames" in err[0], err
    assert ("malformed" if damage == "malformed" else f"{HUGE}×{HUGE}") in err[0], err
    assert "Traceback" not in err[0] and "left out" in err[0], err
    # Written without the bad tube, as if it had not been asked for.
    others = f"selected AND tube_id <> '{tube}'"
    assert _product(cat, fmt, tmp_path / name("others"), others) == 0
    if fmt == "render":
        n = int(out.split(" tubes,")[0].rsplit(" ", 1)[1])
        assert f" {n} tubes," in capsys.readouterr().out and (tmp_path / "dest.webm").stat().st_size > 0
    else:
        assert _files(tmp_path / "dest") == _files(tmp_path / "others") and _files(tmp_path / "dest")
        assert tube.encode() not in b"".join(_files(tmp_path / "dest").values()) or fmt == "kitti-mots"
    # Only the bad tube asked for: nothing to write, exit 2, one line, nothing written.
    capsys.readouterr()
    assert _product(cat, fmt, tmp_path / name("only"), f"tube_id = '{tube}'") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and tube in err[0] and "tube_frames" in err[0] and "Traceback" not in err[0], err
    assert not (tmp_path / name("only")).exists() or not list((tmp_path / "only").iterdir()), "nothing written"


def test_a_mask_larger_than_any_frame_is_refused_before_decoding():
    """A mask over an 8K frame's pixels is malformed whatever the frame (the viewer's bound)."""
    from mining.catalog.rows import BadMask, mask_rle

    n = 60000  # 3.6 · 10⁹ pixels: a 3.6 GB decode
    counts = mask_utils.frPyObjects({"size": [n, n], "counts": [n * n]}, n, n)["counts"].decode()
    row = {"tube_id": "t", "frame": 0, "rle_h": n, "rle_w": n, "rle_counts": counts}
    with pytest.raises(BadMask, match="MP"):
        mask_rle(row)


def test_bad_predicates(catalogue, tmp_path, capsys):
    out, _ = catalogue
    with pytest.raises(MiningError, match="no_such_column"):
        run_export(str(out), "no_such_column > 1", "kitti", str(tmp_path / "a"))
    with pytest.raises(MiningError, match="not one SQL expression"):
        run_export(str(out), f"selected) TO '{out}/x.csv'; COPY (SELECT 1", "kitti", str(tmp_path / "b"))
    assert not (out / "x.csv").exists()
    capsys.readouterr()
    # Nothing matched: exit 1 (cli.main maps NothingMatched), nothing written.
    assert main(["export", "--out", str(out), "--where", "false", "--format", "kitti", str(tmp_path / "c")]) == 1
    assert capsys.readouterr().err == "mine export: no tube matches --where 'false'; nothing written\n"
    assert not (tmp_path / "c").exists()


def test_exports_type_tubes_by_the_known_flag(catalogue, tmp_path):
    """KITTI and KITTI-MOTS classes follow `known`: a known tube's category, Misc / ignore for unknown
    ones even when their best guess is car, the unclassified setting for unclassified ones."""
    out, tables = catalogue
    tubes, tf = tables["tubes"], tables["tube_frames"]
    rows = tubes.to_pylist()
    for i, r in enumerate(r for r in rows if r["selected"]):  # each kind gets selected tubes
        r["known"] = (True, False, None)[i % 3]
        r["category"] = {True: "car", False: "unknown", None: None}[r["known"]]
        assert r["best_known"] == "car"  # PointRCNN cars: the best guess is car for all three kinds
    assert sum(r["selected"] for r in rows) >= 3
    cat = tmp_path / "cat"
    store = Store(cat)
    write_sequence(store, "tubes", DATASET, SEQUENCE, pa.Table.from_pylist(rows, schema=SCHEMAS["tubes"]))
    write_sequence(store, "tube_frames", DATASET, SEQUENCE, tf)
    for where, want, mots in (("known = true", {"Car"}, {1}), ("known = false", {"Misc"}, {10}),
                              ("known IS NULL", {"Misc"}, {10})):
        dest = tmp_path / where.replace(" ", "_")
        assert run_export(str(cat), f"selected AND {where}", "kitti", str(dest)) == 0
        got = read_kitti_tracking(dest / f"{SEQUENCE}.txt", require_score=True)
        assert len(got) > 0 and set(got.type) == want, where
        assert run_export(str(cat), f"selected AND {where}", "kitti-mots", str(dest / "mots")) == 0
        classes = {int(line.split()[2]) for line in (dest / "mots" / f"{SEQUENCE}.txt").read_text().splitlines()}
        assert classes <= mots, where


def test_kitti_mots_keeps_unknowns_as_a_class_and_maps_ids_to_tubes(catalogue, tmp_path):
    """--unknown-class N writes unknown tubes as class N (not 10, which MOTS tools drop); the id
    map beside each txt names the tube of every object id written."""
    out, tables = catalogue
    rows = tables["tubes"].to_pylist()
    for r in rows:
        if r["selected"]:
            r["known"], r["category"] = False, "unknown"
    cat = tmp_path / "cat"
    store = Store(cat)
    write_sequence(store, "tubes", DATASET, SEQUENCE, pa.Table.from_pylist(rows, schema=SCHEMAS["tubes"]))
    write_sequence(store, "tube_frames", DATASET, SEQUENCE, tables["tube_frames"])
    assert main(["export", str(tmp_path / "m"), "--out", str(cat), "--format", "kitti-mots",
                 "--unknown-class", "3"]) == 0
    lines = (tmp_path / "m" / f"{SEQUENCE}.txt").read_text().splitlines()
    assert lines and {int(x.split()[2]) for x in lines} == {3}
    ids = json.loads((tmp_path / "m" / f"{SEQUENCE}.ids.json").read_text())
    selected = {r["tube_id"] for r in rows if r["selected"]}
    assert {v["tube_id"] for v in ids.values()} == selected
    assert {int(x.split()[1]) for x in lines} <= {int(k) for k in ids}
    assert main(["export", str(tmp_path / "k"), "--out", str(cat), "--format", "kitti"]) == 0
    kids = json.loads((tmp_path / "k" / f"{SEQUENCE}.ids.json").read_text())
    got = read_kitti_tracking(tmp_path / "k" / f"{SEQUENCE}.txt", require_score=True)
    assert {int(i) for i in set(got.track_id)} <= {int(k) for k in kids}
    assert {v["tube_id"] for v in kids.values()} == selected
    assert main(["export", str(tmp_path / "x"), "--out", str(cat), "--format", "kitti-mots",
                 "--unknown-class", "2"]) == 2
