"""Proposal recall@N and the ground-truth readers it runs on (KITTI labels, RobotCar labels)."""

from __future__ import annotations

import json
from collections import Counter

import numpy as np
import pytest

from mining.errors import InputError
from mining.eval.recall import first_hit_rank, kitti_ground_truth, recall_at_n
from mining.formats.kitti_tracking import read_kitti_tracking
from mining.formats.oxford_labels import OXFORD_KNOWN, read_oxford_labels
from mining.types import Proposals


def _props(boxes, objectness) -> Proposals:
    boxes = np.asarray(boxes, np.float32).reshape(-1, 4)
    return Proposals(frame=0, rles=[{}] * len(boxes), boxes=boxes, objectness=np.asarray(objectness, np.float32))


# -- hand-worked cases --------------------------------------------------------------

GT = np.array([[0, 0, 10, 10], [100, 100, 120, 140]], np.float64)


def test_one_of_two_recalled():
    # IoU([0,0,10,10], [0,0,10,8]) = 0.8; nothing near the second box.
    r = recall_at_n([_props([[0, 0, 10, 8], [300, 300, 310, 310]], [0.9, 0.8])], [GT], [np.array([True, True])],
                    ns=(1, 2, 10))
    assert r["known"] == {1: 0.5, 2: 0.5, 10: 0.5}
    assert r["n_known"] == 2 and r["n_unknown"] == 0 and np.isnan(r["unknown"][1])


def test_n_cut_off_follows_objectness():
    # The hit for box 2 has the lowest objectness: rank 3 after sorting.
    hit2 = [100, 100, 120, 138]  # IoU 0.95
    props = _props([hit2, [0, 0, 10, 9], [500, 0, 510, 10], [600, 0, 610, 10]], [0.1, 0.9, 0.8, 0.7])
    r = recall_at_n([props], [GT], [np.array([True, True])], ns=(1, 2, 3, 4, 5))
    assert r["all"] == {1: 0.5, 2: 0.5, 3: 0.5, 4: 1.0, 5: 1.0}
    # A plain box array is taken in the given order.
    r = recall_at_n([props.boxes], [GT], [np.array([True, True])], ns=(1, 2))
    assert r["all"] == {1: 0.5, 2: 1.0}


def test_known_and_unknown_are_separate():
    props = _props([[0, 0, 10, 10]], [0.5])
    r = recall_at_n([props, props], [GT, GT[:1]], [np.array([True, False]), np.array([False])], ns=(1, 5))
    assert r["n_known"] == 1 and r["n_unknown"] == 2 and r["n_all"] == 3
    assert r["known"] == {1: 1.0, 5: 1.0}
    assert r["unknown"] == {1: 0.5, 5: 0.5}
    assert r["all"][1] == pytest.approx(2 / 3)


def test_iou_must_exceed_one_half():
    gt = np.array([[0, 0, 10, 10]], np.float64)
    exactly_half = np.array([[0, 0, 10, 5]], np.float64)  # IoU = 50 / 100
    assert np.isinf(first_hit_rank(exactly_half, gt)[0])
    assert first_hit_rank(np.array([[0, 0, 10, 5.01]]), gt)[0] == 0


def test_frame_without_proposals_recalls_nothing():
    r = recall_at_n([_props(np.zeros((0, 4)), []), _props(GT, [1, 1])], [GT, GT], [np.ones(2, bool)] * 2, ns=(10,))
    assert r["all"][10] == 0.5
    with pytest.raises(ValueError):
        recall_at_n([_props(GT, [1, 1])], [GT], [np.ones(3, bool)])


# -- KITTI ground truth -------------------------------------------------------------


def test_kitti_ground_truth(kitti_tracking_root):
    rows = read_kitti_tracking(kitti_tracking_root / "training" / "label_02" / "0005.txt")
    boxes, known = kitti_ground_truth(rows, range(16))
    assert sum(len(b) for b in boxes) == 52  # SOURCES.md §1.2: 52 Car boxes, DontCare left out
    assert all(k.all() for k in known)
    # A sequence with Misc objects: they are the unknown ground truth.
    rows = read_kitti_tracking(kitti_tracking_root / "training" / "label_02" / "0019.txt")
    frames = np.unique(rows.frame)
    boxes, known = kitti_ground_truth(rows, frames)
    n_unknown = sum(int((~k).sum()) for k in known)
    assert n_unknown == int((rows.type == "Misc").sum()) > 0
    assert sum(len(b) for b in boxes) == int((rows.type != "DontCare").sum())
    # Recall of the labels against themselves is 1 for both groups.
    r = recall_at_n(boxes, boxes, known, ns=(500,))
    assert r["known"][500] == 1.0 and r["unknown"][500] == 1.0


def test_kitti_unexpected_type(kitti_tracking_root, tmp_path):
    lines = (kitti_tracking_root / "training" / "label_02" / "0005.txt").read_text().splitlines()[:20]
    i = next(k for k, line in enumerate(lines) if " Car " in line)
    lines[i] = lines[i].replace(" Car ", " Boat ")
    path = tmp_path / "0005.txt"
    path.write_text("\n".join(lines))
    with pytest.raises(InputError, match="Boat") as e:
        kitti_ground_truth(read_kitti_tracking(path), range(16))
    assert e.value.path == str(path) and e.value.frame == int(lines[i].split()[0])


# -- RobotCar labels ----------------------------------------------------------------


@pytest.fixture(scope="module")
def oxford(oxford_data):
    return read_oxford_labels(oxford_data / "labels_4dgvt")


def test_oxford_label_counts(oxford, oxford_data):
    assert len(oxford) == 150
    assert sum(len(f) for f in oxford) == 1494
    cats = Counter(c for f in oxford for c in f.categories)
    assert cats == {"car": 599, "person": 354, "bike": 78, "bus": 50, "other": 413}  # SOURCES.md §4
    per_traversal = Counter(f.traversal for f in oxford)
    folders = Counter(t for t, _ in {(f.traversal, f.sub) for f in oxford})
    expected = {"2015-05-29-09-36-29": (24, 29), "2015-07-21-08-26-57": (30, 35), "2015-10-28-14-13-51": (38, 47),
                "2015-11-06-11-21-12": (28, 36), "2015-11-12-13-27-51": (3, 3)}
    assert {t: (folders[t], per_traversal[t]) for t in expected} == expected
    # The parent folder works too.
    assert len(read_oxford_labels(oxford_data)) == 150


def test_oxford_boxes_and_flags(oxford):
    for f in oxford:
        assert f.path.name == f"postproc_{f.frame:010d}.json"
        assert f.boxes.shape == (len(f), 4) and f.positions.shape == (len(f), 3)
        assert (f.boxes[:, 2] > f.boxes[:, 0]).all() and (f.boxes[:, 3] > f.boxes[:, 1]).all()
        np.testing.assert_array_equal(f.known, [c in OXFORD_KNOWN for c in f.categories])
        z = f.positions[:, 2]
        assert (z[np.isfinite(z)] > 0).all()  # in front of the camera
    assert sum(int(np.isnan(f.positions[:, 0]).sum()) for f in oxford) == 31  # objects whose pos3d is null
    # Extreme points lie on the object's outline: the box is their min/max, checked on one file.
    first = oxford[0]
    raw = json.loads(first.path.read_text())
    pts = np.array(raw[0]["extreme_points"])
    np.testing.assert_allclose(first.boxes[0], [*pts.min(axis=0), *pts.max(axis=0)])
    allb = np.concatenate([f.boxes for f in oxford])
    assert allb[:, 0].min() >= -5 and allb[:, 2].max() <= 1285 and allb[:, 3].max() <= 965  # 1280×960 pixels


def test_oxford_recall_separates_known_and_unknown(oxford):
    # Proposals = the known boxes only: known recall is 1, unknown recall is what known boxes
    # happen to cover (little: "other" objects are signs, poles, bins beside the cars).
    props = [f.boxes[f.known] for f in oxford]
    r = recall_at_n(props, [f.boxes for f in oxford], [f.known for f in oxford], ns=(100,))
    assert r["n_known"] == 1081 and r["n_unknown"] == 413
    assert r["known"][100] == 1.0
    assert r["unknown"][100] < 0.1


def test_oxford_bad_input(oxford_data, tmp_path):
    src = oxford_data / "labels_4dgvt" / "2015-05-29-09-36-29_sub_0006" / "postproc_0000000080.json"
    folder = tmp_path / "2015-05-29-09-36-29_sub_0006"
    folder.mkdir()
    raw = json.loads(src.read_text())
    raw[0]["category"] = "tree"
    (folder / src.name).write_text(json.dumps(raw))
    with pytest.raises(InputError, match="tree") as e:
        read_oxford_labels(tmp_path)
    assert e.value.frame == 80 and e.value.path == str(folder / src.name)
    (folder / src.name).write_text(src.read_text()[:-40])
    with pytest.raises(InputError, match="not valid JSON"):
        read_oxford_labels(tmp_path)
