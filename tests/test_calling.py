"""Calling a tube unknown (issue 29): the classifier rows' calibrated confidence, the object
evidence and its gate, the fits on tables with a known answer, the mined-seed cache.

Truth is independent of the code under test: rows built from a known posterior, labels drawn
from known logistics, hand-made tubes whose evidence is worked out by hand.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import coco_rle

from mining.bench.calling import (KNOWN, NOTHING, UNKNOWN, MARGIN_GRID, best_margin, classifier_rows, fit_rows, load_seed,
                                  save_seed)
from mining.config import load_config
from mining.errors import InputError
from mining.eval.synthetic import GtFrame
from mining.pipeline.mine import judge
from mining.proposals.yolo_seg import class_posterior
from mining.score.clutter import OBJECT_FEATURES, OBJECT_TERMS, object_evidence, object_log_odds
from mining.score.category import ROW_FEATURES, RowConfidence, frame_class_evidence, row_features, tube_category
from mining.types import UNKNOWN_CLASS, Tube, TubeFrame, max_class_score

H, W = 40, 60


def rect(x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    m = np.zeros((H, W), bool)
    m[y0:y1, x0:x1] = True
    return m


def frame(k: int, mask: np.ndarray, posterior: np.ndarray | None, depth: float = 10.0, weight: float = 1.0,
          observed: bool = True) -> TubeFrame:
    ys, xs = np.nonzero(mask)
    box = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float64)
    return TubeFrame(k, k * 100_000_000, observed, 0 if observed else -1, coco_rle(mask), box, np.array([0.0, 0, depth]),
                     np.zeros(3), np.array([1.0, 1.0, 1.0]), np.array([0.0, 0.0, depth]), 0.5,
                     np.nan if k == 0 else 0.8, np.nan if k == 0 else 0.1, posterior, weight)


def person_row(score: float) -> np.ndarray:
    p = np.zeros((1, 80))
    p[0, 0] = score  # COCO 0: person
    return class_posterior(p)[0].astype(np.float64)


def test_the_max_class_score_comes_back_from_the_posterior():
    for s in (0.01, 0.25, 0.6, 0.999):
        assert max_class_score(person_row(s)) == pytest.approx(s, rel=1e-5)
    agnostic = np.zeros(81)
    agnostic[UNKNOWN_CLASS] = 1.0
    assert max_class_score(agnostic) == 0.0


def test_a_calibrated_row_splits_known_and_unknown_by_its_confidence_and_weighs_by_being_on_an_object():
    # P(on object) = σ(ln 3) = 0.75 everywhere; P(known | object) = σ(ln 4) = 0.8 everywhere
    conf = RowConfidence({"bias": np.log(3.0)}, {"bias": np.log(4.0)})
    f = frame(1, rect(0, 0, 10, 20), person_row(0.25), weight=1.0)
    post, w = frame_class_evidence(f, conf)
    assert w == pytest.approx(0.75) and post.sum() == pytest.approx(1.0)
    assert post[0] == pytest.approx(0.8) and post[UNKNOWN_CLASS] == pytest.approx(0.2)
    # the paper's row: 0.25 of person against 0.75 unknown, weight 1
    post0, w0 = frame_class_evidence(f)
    assert w0 == 1.0 and post0[UNKNOWN_CLASS] / post0[0] == pytest.approx(3.0, rel=1e-5)
    # a class-agnostic row keeps its own evidence; a predicted frame has none
    agnostic = np.zeros(81)
    agnostic[UNKNOWN_CLASS] = 1.0
    post_a, w_a = frame_class_evidence(frame(2, rect(0, 0, 10, 20), agnostic, weight=0.4), conf)
    assert w_a == pytest.approx(0.4) and post_a[UNKNOWN_CLASS] == 1.0
    assert frame_class_evidence(frame(3, rect(0, 0, 10, 20), person_row(0.9), observed=False), conf) is None
    # a far small pedestrian at 0.25 in every frame: unknown by the paper's rule, known when calibrated
    tube = Tube(1, 0, [frame(k, rect(0, 0, 8, 16), person_row(0.25), depth=45.0) for k in range(6)])
    assert tube_category(tube, log_margin=0.0).known is False
    c = tube_category(tube, log_margin=0.0, confidence=conf)
    assert c.known is True and c.category == "person" and c.evidence == pytest.approx(6 * 0.75)


def test_row_features_and_their_weights_by_name():
    x = row_features(np.array([0.5, 0.0]), np.array([20.0, 0.2]), np.array([40.0, np.nan]))
    assert x.shape == (2, len(ROW_FEATURES))
    assert x[0] == pytest.approx([1.0, 0.0, np.log(20), np.log(40), 0.0, 0.0])
    assert np.isfinite(x).all() and x[1, 2] == 0.0 and x[1, 3] == 0.0  # clipped: 1 px, 1 m
    conf = RowConfidence({"ln_depth": 1.0}, {})
    on, known = conf(0.5, 20.0, np.e)
    assert on == pytest.approx(1 / (1 + np.exp(-1.0))) and known == 0.5


def test_fit_rows_recovers_the_logistics_that_drew_the_labels():
    rng = np.random.default_rng(0)
    n = 20000
    s, h, z = rng.uniform(0.02, 0.9, n), rng.uniform(8, 200, n), rng.uniform(5, 70, n)
    x = row_features(s, h, z)
    w_on = np.array([0.5, 0.8, 0.0, -0.3, 0.0, 0.0])
    w_known = np.array([-1.0, 1.0, 0.0, 0.5, 0.0, 0.0])
    on = rng.uniform(size=n) < 1 / (1 + np.exp(-(x @ w_on)))
    known = rng.uniform(size=n) < 1 / (1 + np.exp(-(x @ w_known)))
    label = np.where(~on, NOTHING, np.where(known, KNOWN, UNKNOWN))
    conf = fit_rows(np.column_stack([s, h, z, label]), l2=1e-3)
    # compared where the data lie: the fitted probabilities against the ones that drew the labels
    grid = row_features(*(g.ravel() for g in np.meshgrid([0.1, 0.3, 0.7], [15.0, 100.0], [10.0, 50.0])))

    def sigma(v):
        return 1 / (1 + np.exp(-v))
    got_on = grid @ np.array([conf.on_object[k] for k in ROW_FEATURES])
    assert sigma(got_on) == pytest.approx(sigma(grid @ w_on), abs=0.03)
    # the known fit is at equal priors (the unknown rows weighted up): its log-odds are the drawing ones
    # less ln(n_known / n_unknown) of the rows on objects
    k = label[on] == KNOWN
    got_known = grid @ np.array([conf.known[k_] for k_ in ROW_FEATURES])
    assert got_known - grid @ w_known == pytest.approx(np.full(len(grid), -np.log(k.sum() / (~k).sum())), abs=0.25)
    with pytest.raises(InputError):
        fit_rows(np.column_stack([s, h, z, np.full(n, NOTHING)]))


def test_best_margin_takes_the_balanced_accuracy_and_the_margin_nearest_zero_on_ties():
    def post(ratio: float) -> np.ndarray:  # P[person] / P[unknown] = ratio
        p = np.zeros(81)
        p[0], p[UNKNOWN_CLASS] = ratio / (1 + ratio), 1 / (1 + ratio)
        return p
    # known tubes at ln-ratios 2.2 and 1.2, an unknown one at 0.6: any margin in [0.6, 1.2) separates them
    m, acc = best_margin([post(np.exp(2.2)), post(np.exp(1.2)), post(np.exp(0.6))], np.array([True, True, False]))
    assert acc == 1.0 and m == 1.0
    # known at 1.2, unknown at −1.2: every margin of [0, 1.2) separates them, the nearest 0 is taken; and a
    # known tube below 0 is never bought by a negative margin (the grid holds none: mining/score/call.py)
    m, acc = best_margin([post(np.exp(1.2)), post(np.exp(-1.2)), post(np.exp(-0.5))], np.array([True, False, True]))
    assert m == 0.0 and acc == 0.75 and min(MARGIN_GRID) == 0.0
    m, acc = best_margin([post(np.exp(1.2)), None], np.array([True, False]))  # an unclassified tube is a miss
    assert acc == 0.5 and m == 0.0


def test_object_evidence_of_a_hand_made_tube():
    mask = rect(10, 10, 30, 30)  # 20 × 20 px, fills its box
    frames = [frame(k, mask, person_row(0.5) if k % 2 else None, depth=10.0) for k in range(4)]
    frames.insert(2, frame(9, mask, None, observed=False))  # a gap frame: not evidence
    psi = dict(zip(OBJECT_FEATURES, object_evidence(Tube(1, 0, frames))))
    assert psi["ln_observed"] == pytest.approx(np.log(4)) and psi["observed_share"] == pytest.approx(0.8)
    assert psi["sd_ln_area_3d"] == pytest.approx(0.0) and psi["sd_ln_aspect"] == pytest.approx(0.0)
    assert psi["mean_fill"] == pytest.approx(1.0) and psi["classifier_share"] == pytest.approx(0.5)
    assert psi["mean_class_score"] == pytest.approx(0.5, rel=1e-5) and psi["mean_detectability"] == 0.0
    assert psi["ln_depth"] == pytest.approx(np.log(10)) and psi["ln_height_px"] == pytest.approx(np.log(20))
    assert psi["border_share"] == 0.0 and psi["mean_ln_mask_iou"] == pytest.approx(np.log(0.8))
    assert psi["ln_width"] == pytest.approx(0.0) and psi["bottom_gap"] == pytest.approx(10 / H)
    assert object_log_odds(Tube(1, 0, frames), {"bias": 2.0, "mean_fill": -1.0}) == pytest.approx(1.0)
    assert OBJECT_TERMS[0] == "bias"


def _unknown_tube(tube_id: int, mask: np.ndarray) -> Tube:
    agnostic = np.zeros(81)
    agnostic[UNKNOWN_CLASS] = 1.0
    return Tube(tube_id, 0, [frame(k, mask, agnostic) for k in range(5)])


@pytest.mark.parametrize("action", ["off", "call", "drop"])
def test_the_gate_keeps_a_clutter_like_unknown_tube_out_of_the_unknown_set(action):
    # two unknown tubes, apart: the one whose mask fills its box passes the gate, the ragged one does not
    solid = _unknown_tube(1, rect(0, 0, 20, 20))
    ragged_mask = rect(30, 0, 60, 30)
    ragged_mask[::2] = False
    ragged = _unknown_tube(2, ragged_mask)
    cfg = load_config(None, ["proposals.proposer=stereo", f"score.unknown_gate={action}",
                             "score.unknown_min_object=0.5", "select.price.calibrated=-100",
                             "score.object_evidence.stereo.bias=-3", "score.object_evidence.stereo.mean_fill=4"])
    mined = {m.tube.tube_id: m for m in judge([solid, ragged], cfg)}
    assert mined[1].category.call == "unknown" and mined[1].selected
    assert mined[1].category.object_prob >= 0.5 if action != "off" else np.isnan(mined[1].category.object_prob)
    expect = {"off": ("unknown", True), "call": ("clutter", True), "drop": ("clutter", False)}[action]
    assert (mined[2].category.call, mined[2].selected) == expect
    # clutter is its own call: unknown still wins its posterior (known false), the badge is not unclassified
    assert mined[2].category.known is False and mined[2].category.category == "unknown"
    if action != "off":
        assert mined[2].category.object_prob < 0.5


def test_the_seed_cache_reads_back_what_it_wrote(tmp_path):
    t = Tube(3, 1, [frame(0, rect(0, 0, 10, 10), person_row(0.3)), frame(1, rect(1, 0, 11, 10), None, weight=0.0)],
             "gap")
    gt = GtFrame(np.array([5], np.int64), np.array([True]), ["person"], [coco_rle(rect(0, 0, 10, 12))],
                 np.array([120]), np.array([[0.0, 0, 10, 12]]), np.array([10.0]), (H, W))
    save_seed(tmp_path / "s.npz", [t], {0: gt, 1: gt})
    (back,), truths = load_seed(tmp_path / "s.npz")
    assert (back.tube_id, back.segment, back.end_reason, len(back.frames)) == (3, 1, "gap", 2)
    assert back.frames[0].rle == t.frames[0].rle and back.frames[1].posterior is None
    assert back.frames[0].posterior == pytest.approx(t.frames[0].posterior)
    assert sorted(truths) == [0, 1] and truths[1].categories == ["person"] and truths[1].rles[0] == gt.rles[0]
    # the rows: frame 0 is the classifier's on the person (mask IoU 100/120 ≥ 0.5); frame 1 has no posterior
    rows = classifier_rows([back], truths)
    assert rows.shape == (1, 4) and rows[0] == pytest.approx([0.3, 10.0, 10.0, KNOWN], rel=1e-5)
    (tmp_path / "bad.npz").write_bytes(b"not an npz")
    with pytest.raises(InputError, match="bad.npz"):
        load_seed(tmp_path / "bad.npz")


def test_the_calibrated_rows_apply_to_the_jobs_whose_classifier_they_were_fit_on():
    # a pedestrian at 20 m found at 0.25 in every frame: by the paper's rule (P(unknown) 0.75 wins) unknown
    tube = Tube(1, 0, [frame(k, rect(0, 0, 16, 40), person_row(0.25), depth=20.0) for k in range(6)])
    calls = {}
    for proposer in ("onnx", "stereo"):
        cfg = load_config(None, [f"proposals.proposer={proposer}", "select.price.calibrated=-100",
                                 "select.price.reference=-100"])
        calls[proposer] = judge([tube], cfg)[0].category.known
    assert calls == {"onnx": True, "stereo": False}
    ref = load_config(None, ["proposals.proposer=onnx", "score.class_confidence=reference"])
    assert judge([tube], ref)[0].category.known is False


def test_the_unknown_price_is_paid_by_tubes_called_unknown_only():
    # one tube unknown wins in, one a classifier's confident person: the same masks, apart in the image
    unknown = _unknown_tube(1, rect(0, 0, 20, 20))
    person = Tube(2, 0, [frame(k, rect(30, 0, 50, 20), person_row(0.9)) for k in range(5)])
    base = ["proposals.proposer=stereo", "score.unknown_gate=off", "select.price.calibrated=-100",
            "select.price.reference=-100"]
    calls = {m.tube.tube_id: (m.category.call, m.selected) for m in judge([unknown, person], load_config(None, base))}
    assert calls == {1: ("unknown", True), 2: ("known", True)}
    dear = {m.tube.tube_id: (m.category.call, m.selected)
            for m in judge([unknown, person], load_config(None, [*base, "select.unknown_price=1000"]))}
    assert dear == {1: ("unknown", False), 2: ("known", True)}
