"""The recall funnel: hand-built truths and tubes for the arithmetic, the real pipeline for the invariants."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from conftest import coco_rle

from mining.bench.synthetic import run_synthetic
from mining.config import load_config
from mining.errors import InputError
from mining.eval.funnel import SPLITS, StageFrame, evaluate_funnel, format_funnel
from mining.eval.synthetic import GtFrame
from mining.types import MinedTube, Tube, TubeCategory, TubeFrame, TubeScore

H, W = 40, 60
ALPHA, BETA = 0.5, 0.5


def rect(x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    m = np.zeros((H, W), bool)
    m[y0:y1, x0:x1] = True
    return m


def box(mask: np.ndarray) -> list[float]:
    ys, xs = np.nonzero(mask)
    return [float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1)]


def gt(*objects: tuple[int, str, bool, np.ndarray, float]) -> GtFrame:
    """objects: (track id, category, known, mask, depth in metres)."""
    return GtFrame(
        track_ids=np.array([o[0] for o in objects], np.int64),
        known=np.array([o[2] for o in objects], bool),
        categories=[o[1] for o in objects],
        rles=[coco_rle(o[3]) for o in objects],
        areas=np.array([int(o[3].sum()) for o in objects], np.int64),
        boxes=np.array([box(o[3]) for o in objects], np.float64).reshape(-1, 4),
        depth=np.array([o[4] for o in objects], np.float64),
        size=(H, W),
    )


def props(*masks: np.ndarray) -> StageFrame:
    return StageFrame([coco_rle(m) for m in masks], np.array([box(m) for m in masks], np.float64).reshape(-1, 4))


def tube(tube_id: int, entries: list[tuple[int, np.ndarray]], selected: bool = True,
         score: tuple[float, float, float] = (0.0, 0.0, 0.0), known: bool | None = False) -> MinedTube:
    frames = [TubeFrame(f, f * 100_000_000, True, 0, coco_rle(m), np.array(box(m)), np.zeros(3), np.zeros(3),
                        np.ones(3), np.zeros(3), 0.5, np.nan, np.nan) for f, m in entries]
    motion, mask, obj = score
    total = BETA * (ALPHA * motion + (1 - ALPHA) * mask) + (1 - BETA) * obj
    cat = TubeCategory(None, {True: "car", False: "unknown", None: None}[known], float("nan"), known,
                       None if known is None else "car")
    return MinedTube(Tube(tube_id, 0, frames), TubeScore(motion, mask, obj, total), cat, selected)


CAR = rect(0, 0, 20, 20)  # 400 px, 20 px tall
CONE = rect(30, 10, 45, 30)  # 300 px
EMPTY = rect(22, 30, 30, 40)  # overlaps nothing
IOU_06 = rect(0, 0, 20, 12)  # 240 / 400 = 0.6 with CAR
IOU_04 = rect(0, 0, 20, 8)  # 160 / 400 = 0.4 with CAR
PART = rect(0, 0, 12, 10)  # 120 px, inside CAR: IoA 1, IoU 0.3


def funnel(truths, mined=(), stages=None, **kw) -> dict:
    return evaluate_funnel(truths, list(mined), stages, alpha=ALPHA, beta=BETA, **kw)


def test_a_proposal_counts_from_iou_half():
    truths = {0: gt((1, "car", True, CAR, 10.0)), 1: gt((1, "car", True, CAR, 10.0))}
    f = funnel(truths, stages={"proposed": {0: props(IOU_06), 1: props(IOU_04)}})
    tot = f["frames"]["all"]["total"]
    assert (tot["gt"], tot["proposed"], tot["candidate"], tot["selected"]) == (2, 1, 0, 0)
    assert tot["recall"]["proposed"] == 0.5
    assert f["stages"] == ["proposed", "candidate", "selected"]


def test_candidate_and_selected_come_from_tubes():
    truths = {t: gt((1, "car", True, CAR, 10.0)) for t in range(4)}
    mined = [tube(1, [(0, CAR), (1, CAR)], selected=False), tube(2, [(2, IOU_06)])]
    tot = funnel(truths, mined)["frames"]["all"]["total"]
    assert (tot["gt"], tot["candidate"], tot["selected"]) == (4, 3, 1)


def test_known_and_unknown_are_separate():
    truths = {0: gt((1, "car", True, CAR, 10.0), (2, "cone", False, CONE, 10.0))}
    f = funnel(truths, stages={"proposed": {0: props(CONE)}})["frames"]
    assert (f["known"]["total"]["gt"], f["known"]["total"]["proposed"]) == (1, 0)
    assert (f["unknown"]["total"]["gt"], f["unknown"]["total"]["proposed"]) == (1, 1)
    assert (f["all"]["total"]["gt"], f["all"]["total"]["proposed"]) == (2, 1)


def test_distance_and_height_bins():
    truths = {0: gt((1, "car", True, CAR, 45.0), (2, "cone", False, CONE, 61.0))}
    f = funnel(truths, stages={"proposed": {0: props(CAR)}})
    d = f["frames"]["all"]["distance"]
    assert list(d) == ["0–20 m", "20–40 m", "40–60 m", ">60 m"] == f["bins"]["distance_m"]["names"]
    assert (d["40–60 m"]["gt"], d["40–60 m"]["proposed"], d[">60 m"]["gt"], d[">60 m"]["proposed"]) == (1, 1, 1, 0)
    assert d["0–20 m"]["gt"] == d["20–40 m"]["gt"] == 0
    h = f["frames"]["all"]["height"]
    assert (h["0–25 px"]["gt"], h["0–25 px"]["proposed"]) == (2, 1)  # 20 px, 20 px
    assert f["frames"]["all"]["cells"]["40–60 m | 0–25 px"]["gt"] == 1


def test_ignored_objects_are_not_counted():
    tiny = rect(50, 0, 55, 5)  # 25 px < 100
    truths = {0: gt((1, "car", True, CAR, 10.0), (3, "debris", False, tiny, 10.0), (4, "cone", False, CONE, 50.0))}
    f = funnel(truths)
    assert f["frames"]["all"]["total"]["gt"] == 2 and f["frames"]["unknown"]["total"]["gt"] == 1
    assert funnel(truths, max_depth_m=40.0)["frames"]["all"]["total"]["gt"] == 1


def test_track_level_needs_one_tube_over_the_cover_share():
    truths = {t: gt((1, "car", True, CAR, 10.0)) for t in range(4)}
    every = {t: props(CAR) for t in range(4)}
    # two tubes, two frames each: each covers half the track, the protocol's cover
    mined = [tube(1, [(0, CAR), (1, CAR)]), tube(2, [(2, CAR), (3, CAR)], selected=False)]
    r = funnel(truths, mined, {"proposed": {0: props(CAR)}})["tracks"]["known"]
    assert (r["gt"], r["proposed"], r["candidate"], r["selected"]) == (1, 0, 1, 1)
    r = funnel(truths, mined, {"proposed": every}, track_cover=0.75)["tracks"]["known"]
    assert (r["proposed"], r["candidate"], r["selected"]) == (1, 0, 0)
    assert funnel(truths, mined)["tracks"]["unknown"]["gt"] == 0


def test_a_part_tube_is_reported_with_the_term_that_carried_it():
    truths = {t: gt((7, "car", True, CAR, 10.0)) for t in range(3)}
    part = tube(5, [(t, PART) for t in range(3)], score=(2.0, 1.0, 30.0))
    on_car = tube(6, [(t, CAR) for t in range(3)], score=(50.0, 5.0, 1.0))
    c = funnel(truths, [part, on_car])["carried"]
    assert c["summary"]["selected"] == 2 and c["summary"]["on objects"] == 1 and c["summary"]["part"] == 1
    (x,) = c["tubes"]
    assert (x["tube_id"], x["kind"], x["frames"], x["of"]["track_id"], x["of"]["category"]) == (5, "part", 3, 7, "car")
    assert x["label"] == "part of track 7 (car)"
    assert x["terms"] == pytest.approx({"motion": 0.5, "mask": 0.25, "objectness": 15.0})
    assert sum(x["terms"].values()) == pytest.approx(x["total"])
    assert x["carried_by"] == "objectness" and c["carried_by"]["objectness"] == 1
    assert (x["category"], x["known_call"]) == ("unknown", False)


def test_under_the_calibrated_unary_the_caller_names_the_groups_and_each_score_gives_its_split():
    """The funnel does not know the unary (eval imports only the shared floor): the caller passes the
    groups (``mining.score.unary.unary_groups``), each tube's score carries its split (``TubeScore.terms``)."""
    truths = {t: gt((7, "car", True, CAR, 10.0)) for t in range(3)}
    part = tube(5, [(t, PART) for t in range(3)])
    part.score.total, part.score.terms = 2.5, {"prior": -1.0, "shape": 3.5}
    c = funnel(truths, [part], groups=("prior", "shape"))["carried"]
    assert c["tubes"][0]["terms"] == {"prior": -1.0, "shape": 3.5} and c["tubes"][0]["carried_by"] == "shape"
    assert c["carried_by"] == {"prior": 0, "shape": 1, "none": 0}
    part.score.terms = None  # a REFERENCE score has no split
    with pytest.raises(InputError, match="tube 5: its score has no groups of terms"):
        funnel(truths, [part], groups=("prior", "shape"))


def test_clutter_is_reported_and_unselected_tubes_are_not():
    truths = {t: gt((1, "car", True, CAR, 10.0)) for t in range(2)}
    mined = [tube(3, [(0, EMPTY), (1, EMPTY)], score=(40.0, 2.0, -1.0), known=None),
             tube(4, [(0, EMPTY)], selected=False, score=(0.0, 0.0, 99.0))]
    c = funnel(truths, mined)["carried"]
    assert c["summary"]["clutter"] == 1 and c["summary"]["part"] == 0
    (x,) = c["tubes"]
    assert (x["tube_id"], x["kind"], x["label"], x["carried_by"], x["known_call"]) == (3, "clutter", "clutter",
                                                                                      "motion", None)


def test_a_tube_inside_another_selected_tube_is_a_part_of_it():
    truths = {0: gt((1, "car", True, CAR, 10.0))}
    big, inside = rect(25, 0, 60, 30), rect(30, 2, 40, 12)  # off the car; inside is within big
    c = funnel(truths, [tube(1, [(0, big)]), tube(2, [(0, inside)])])["carried"]
    kinds = {x["tube_id"]: x["label"] for x in c["tubes"]}
    assert kinds == {1: "clutter", 2: "part of tube 1"}


def test_box_similarity_and_bad_input():
    truths = {0: gt((1, "car", True, CAR, 10.0))}
    # a diagonal sliver has a small mask IoU but its box equals the car's
    sliver = np.eye(20, dtype=bool)
    sliver = np.pad(sliver, ((0, H - 20), (0, W - 20)))
    stages = {"proposed": {0: props(sliver)}}
    assert funnel(truths, stages=stages)["frames"]["all"]["total"]["proposed"] == 0
    assert funnel(truths, stages=stages, similarity="box")["frames"]["all"]["total"]["proposed"] == 1
    with pytest.raises(InputError):
        funnel({})
    with pytest.raises(InputError):
        funnel(truths, similarity="centre")
    with pytest.raises(InputError):
        funnel(truths, stages={"selected": {}})


def test_format_shows_every_split_and_the_carried_list():
    truths = {t: gt((7, "car", True, CAR, 10.0), (8, "cone", False, CONE, 50.0)) for t in range(2)}
    mined = [tube(k, [(0, EMPTY)], score=(1.0, 1.0, float(k))) for k in range(30)]
    text = format_funnel(funnel(truths, mined, {"proposed": {0: props(CAR)}}), max_tubes=5)
    for word in (*SPLITS, "40–60 m", "0–25 px", "proposed", "candidate", "selected", "50 %", "clutter"):
        assert word in text
    assert "… and 25 more" in text


def test_known_objects_called_unknown_by_bin_and_clutter_called_unknown_by_term():
    far = rect(0, 0, 20, 30)  # 30 px tall
    truths = {t: gt((1, "person", True, far, 45.0), (2, "car", True, CONE, 12.0)) for t in range(3)}
    mined = [tube(1, [(t, far) for t in range(3)], known=False),  # a far pedestrian called unknown
             tube(2, [(t, CONE) for t in range(3)], known=True),
             tube(3, [(t, EMPTY) for t in range(3)], score=(0.0, 8.0, 1.0), known=False),  # clutter called unknown
             tube(4, [(t, EMPTY) for t in range(3)], score=(9.0, 0.0, 1.0), known=None, selected=False)]
    f = funnel(truths, mined, tube_split={1: "known", 2: "known"})
    c = f["calls"]
    assert c["total"] == {"tubes": 2, "known": 1, "unknown": 1, "clutter": 0, "unclassified": 0}
    assert c["distance"]["40–60 m"] == {"tubes": 1, "known": 0, "unknown": 1, "clutter": 0, "unclassified": 0}
    assert c["distance"]["0–20 m"]["known"] == 1 and c["distance"]["20–40 m"]["tubes"] == 0
    assert c["height"]["25–50 px"]["unknown"] == 1 and c["height"]["0–25 px"]["known"] == 1  # CONE is 20 px tall
    cu = f["carried"]["called_unknown_by"]
    assert cu["clutter"]["mask"] == 1 and sum(cu["clutter"].values()) == 1 and sum(cu["part"].values()) == 0
    text = format_funnel(f)
    assert "called unknown, by the term that carried them: part 0; clutter 1 (mask 1)" in text
    assert "40–60 m" in text and "50 %" in text
    assert "calls" not in funnel(truths, mined)  # without the split there is nothing to call it against


@pytest.mark.slow  # mines 16 rendered frames (10–30 s)
def test_funnel_of_the_real_pipeline_is_monotone_and_counts_the_evaluated_truth():
    cv2.setNumThreads(1)
    mined, r = run_synthetic("0001", 16, load_config())
    f = r["funnel"]
    assert f["stages"] == ["proposed", "observed", "candidate", "selected"]
    for split in SPLITS:
        s = f["frames"][split]
        for row in [s["total"], *s["distance"].values(), *s["height"].values(), *s["cells"].values(),
                    f["tracks"][split]]:
            assert row["gt"] >= row["proposed"] >= row["observed"] >= row["candidate"] >= row["selected"]
        for axis in ("distance", "height", "cells"):
            for k in ("gt", *f["stages"]):
                assert sum(x[k] for x in s[axis].values()) == s["total"][k]
    # the evaluated detections are the synthetic protocol's, and the stages found something
    assert f["frames"]["all"]["total"]["gt"] == r["all"]["gt_dets"] > 0
    assert f["frames"]["known"]["total"]["gt"] + f["frames"]["unknown"]["total"]["gt"] == r["all"]["gt_dets"]
    assert f["tracks"]["all"]["gt"] == r["all"]["tracks"]
    assert f["frames"]["all"]["total"]["selected"] > 0
    # the protocol's frame recall counts a subset of the selected detections (step 3 drops some)
    assert f["frames"]["all"]["total"]["recall"]["selected"] >= r["all"]["frame_recall"]
    # every selected tube is accounted for once
    s = f["carried"]["summary"]
    assert s["selected"] == sum(m.selected for m in mined) == sum(v for k, v in s.items() if k != "selected")
    assert len(f["carried"]["tubes"]) == s["part"] + s["clutter"] == sum(f["carried"]["carried_by"].values())
    text = json.dumps(f)  # plain JSON: no numpy values
    assert json.dumps(json.loads(text)) == text
    assert format_funnel(json.loads(text)) == format_funnel(f)
    print(format_funnel(f))


def test_kitti_labels_become_box_truth(tmp_path):
    from mining.eval.recall import kitti_truths
    from mining.formats.kitti_tracking import read_kitti_tracking

    # frame track type truncated occluded alpha x1 y1 x2 y2 h w l x y z rotation_y
    (tmp_path / "0000.txt").write_text(
        "0 3 Car 0 0 0 10 5 30 25 1.5 1.6 4 1 1.6 45.0 0\n"
        "0 4 Misc 0 0 0 35 10 50 30 1 1 1 2 1.6 12.0 0\n"
        "0 -1 DontCare -1 -1 -10 0 0 5 5 -1 -1 -1 -1000 -1000 -1000 -10\n")
    truths = kitti_truths(read_kitti_tracking(tmp_path / "0000.txt"), [0], (H, W))
    g = truths[0]
    assert g.track_ids.tolist() == [3, 4] and g.known.tolist() == [True, False]
    assert g.categories == ["Car", "Misc"] and g.depth.tolist() == [45.0, 12.0] and g.areas.tolist() == [400, 300]
    # box similarity: a tube whose box is the Misc box covers it, whatever its mask
    sliver = np.zeros((H, W), bool)
    sliver[10:30, 35] = sliver[10, 35:50] = True
    f = funnel(truths, [tube(1, [(0, sliver)])], similarity="box")["frames"]
    assert (f["unknown"]["total"]["gt"], f["unknown"]["total"]["selected"]) == (1, 1)
    assert (f["known"]["distance"]["40–60 m"]["gt"], f["known"]["total"]["selected"]) == (1, 0)


@pytest.mark.slow  # runs the pipeline on 6 KITTI frames (~2 s, more under load)
def test_kitti_recall_command_prints_and_writes_the_funnel(kitti_tracking_root, tmp_path, capsys):
    from mining.cli import main

    out = tmp_path / "r.json"
    assert main(["eval", "recall", "--dataset", "kitti", "--root", str(kitti_tracking_root), "--sequence", "0005",
                 "--frames", "0:6", "--funnel", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "recall funnel" in text and "box IoU" in text
    doc = json.loads(out.read_text())
    f = doc["funnel"]["frames"]["all"]["total"]
    assert f["gt"] == doc["recall_at_n"]["n_all"] > 0  # every labelled box is evaluated
    assert f["gt"] >= f["proposed"] >= f["observed"] >= f["candidate"] >= f["selected"]
