"""Discovery measured on synthetic truth (mining/eval/discovery.py): each measure on hand-made
descriptors and kinds where its value is known (perfect separation, shuffled kinds, noise,
kinds seen once, the exemplar's choice), the true kind of a tube from a hand-made truth, and
`mine eval synthetic --json` writing the section on the real pipeline."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from pycocotools import mask as mask_utils
from conftest import coco_rle

from mining import cli
from mining.bench.synthetic import pool_rows, pooled_discovery
from mining.discovery.descriptors import DESCRIPTOR_VERSION
from mining.discovery.groups import centre_distances, group_vectors
from mining.eval.discovery import discovery_metrics, exemplars, format_discovery, group_purity, nn_same_kind, propagation
from mining.errors import InputError
from mining.eval.synthetic import evaluate_synthetic
from mining.types import FrameTruth, MinedTube, ObjectTruth, Tube, TubeCategory, TubeFrame, TubeScore

KINDS = ("cone", "bin", "crate", "tyre")


def clusters(per_kind: int, spread: float = 0.02, seed: int = 0) -> tuple[np.ndarray, list[str]]:
    """``per_kind`` vectors near each of len(KINDS) orthogonal directions, with their kinds."""
    rng = np.random.default_rng(seed)
    dim = 8
    vectors = np.concatenate([np.eye(dim)[k] + rng.normal(0, spread, (per_kind, dim)) for k in range(len(KINDS))])
    return vectors, [k for k in KINDS for _ in range(per_kind)]


def test_perfect_separation_scores_one_with_the_products_grouping():
    vectors, kinds = clusters(15)
    labels, _ = group_vectors(vectors)
    d = discovery_metrics(vectors, kinds, labels, centre_distances(vectors, labels))
    assert d["nn_same_kind"] == 1.0 and d["nn_counted"] == 60 and d["single_kind_tubes"] == 0
    assert d["group_purity"] == 1.0 and d["groups"] == d["kinds"] == 4
    assert d["propagation"] == 1.0 and d["labelled"] == 4
    assert d["nn_chance"] == pytest.approx(0.25) and d["majority_share"] == pytest.approx(0.25)
    assert "nn_same_kind 1.00 (chance 0.25)" in format_discovery(d)


def test_shuffled_kinds_score_near_chance():
    vectors, kinds = clusters(100)
    shuffled = list(np.random.default_rng(1).permutation(kinds))
    labels = np.repeat(np.arange(4), 100)  # the four true clusters as groups: their kinds are now random
    d = discovery_metrics(vectors, shuffled, labels, centre_distances(vectors, labels))
    assert abs(d["nn_same_kind"] - 0.25) < 0.08
    assert d["group_purity"] < 0.40  # chance: the largest of ~25 % shares
    assert abs(d["propagation"] - 0.25) < 0.08


def test_noise_is_left_out_of_purity_and_reached_by_propagation():
    # two groups of three (rows 0-2 cone, 3-5 bin) and two noise tubes, one near each group
    vectors = np.array([[1, 0], [1, 0.05], [1, -0.05], [0, 1], [0.05, 1], [-0.05, 1], [1, 0.2], [0.2, 1]], float)
    kinds = ["cone", "cone", "bin", "bin", "bin", "bin", "cone", "cone"]
    labels = np.array([0, 0, 0, 1, 1, 1, -1, -1])
    g = group_purity(labels, kinds)
    assert g == {"group_purity": 5 / 6, "groups": 2, "kinds": 2, "noise_share": 0.25}
    cd = centre_distances(vectors, labels)
    assert list(exemplars(labels, cd)) == [0, 3]  # nearest each group's mean direction
    p = propagation(vectors, kinds, labels, cd)
    # unlabelled: 1 ✓, 2 ✗ (bin near the cone exemplar), 4 ✓, 5 ✓, noise 6 ✓ (cone), 7 ✗ (cone near bin)
    assert p == {"propagation": 4 / 6, "propagation_grouped": 3 / 4, "labelled": 2}
    assert math.isnan(group_purity(np.full(3, -1), ["a", "b", "c"])["group_purity"])
    assert math.isnan(propagation(vectors[:3], kinds[:3], np.full(3, -1), np.zeros(3))["propagation"])


def test_the_exemplar_labels_its_group_with_its_own_kind():
    # the tube nearest the mean direction is the odd one: its kind is what the group is labelled
    vectors = np.array([[1, 0.3], [1, 0], [1, -0.3], [0, 1]], float)
    kinds = ["cone", "bin", "cone", "bin"]
    labels = np.array([0, 0, 0, -1])
    cd = centre_distances(vectors, labels)
    assert list(exemplars(labels, cd)) == [1]
    assert propagation(vectors, kinds, labels, cd)["propagation"] == pytest.approx(1 / 3)  # only the noise bin


def test_a_kind_seen_once_is_not_counted_but_stays_a_neighbour():
    vectors = np.array([[1, 0], [1, 0.01], [0, 1], [0.01, 1], [1, 1]], float)
    kinds = ["cone", "cone", "bin", "bin", "tyre"]
    share, counted, single = nn_same_kind(vectors, kinds)
    # every cone and bin finds its kind; the tyre, alone of its kind, is not counted (its nearest is wrong)
    assert (share, counted, single) == (1.0, 4, 1)
    share, counted, _ = nn_same_kind(np.array([[1, 0], [1, 0.01], [1, 0.02]], float), ["cone", "tyre", "cone"])
    assert counted == 2 and share == 0.0  # each cone's nearest is the tyre between them
    assert math.isnan(nn_same_kind(vectors[:2], ["a", "b"])[0])


def _tube(tube_id: int, masks: list[np.ndarray]) -> MinedTube:
    frames = []
    for f, m in enumerate(masks):
        rle = coco_rle(m)
        x, y, w, h = mask_utils.toBbox(rle)
        frames.append(TubeFrame(f, f * 100_000_000, True, 0, rle, np.array([x, y, x + w, y + h]),
                                np.zeros(3), np.zeros(3), np.ones(3), np.zeros(3), 0.5, np.nan, np.nan))
    return MinedTube(Tube(tube_id, 0, frames), TubeScore(0.0, 0.0, 0.0, 1.0),
                     TubeCategory(None, "unknown", float("nan"), False, None), True)


def _rect(x0: int, x1: int) -> np.ndarray:
    m = np.zeros((40, 60), bool)
    m[5:30, x0:x1] = True
    return m


def test_a_tubes_true_kind_is_the_unknown_category_it_collected_most_iou_on():
    def obj(tid: int, category: str, known: bool, mask: np.ndarray) -> ObjectTruth:
        ys, xs = np.nonzero(mask)
        return ObjectTruth(tid, category, known, mask, (float(xs.min()), float(ys.min()), float(xs.max() + 1),
                                                        float(ys.max() + 1)), np.array([0, 0, 10.0]), np.ones(3), np.zeros(3))
    cone, bin_, car = _rect(0, 15), _rect(20, 35), _rect(40, 58)
    truths = {f: FrameTruth(np.zeros((40, 60), np.float32), np.eye(4),
                            [obj(1, "cone", False, cone), obj(2, "bin", False, bin_), obj(3, "car", True, car)])
              for f in range(3)}
    # tube 7: a cone twice, then the bin once; tube 8: the car (known, no kind)
    r = evaluate_synthetic([_tube(7, [cone, cone, bin_]), _tube(8, [car, car, car])], truths)
    assert r["tube_split"] == {7: "unknown", 8: "known"} and r["tube_kind"] == {7: "cone"}


@pytest.mark.slow  # mines 20 frames with the real pipeline
def test_mine_eval_synthetic_writes_a_discovery_section(tmp_path, capsys):
    out = tmp_path / "r.json"
    assert cli.main(["eval", "synthetic", "--sequence", "0001", "--n-frames", "20", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    d = doc["discovery"]
    kinds = doc["tube_kind"]
    assert d["tubes"] == len(kinds) == doc["tubes"]["unknown"] - sum(1 for t, s in doc["tube_split"].items()
                                                                      if s == "unknown" and t not in kinds)
    assert d["kinds"] == len(set(kinds.values())) and sum(d["kind_counts"].values()) == d["tubes"]
    for key in ("nn_same_kind", "group_purity", "propagation", "propagation_grouped", "noise_share", "nn_chance"):
        assert math.isnan(d[key]) or 0.0 <= d[key] <= 1.0, key
    assert d["groups"] >= 0 and d["labelled"] == d["groups"]
    assert sorted(str(r["tube_id"]) for r in d["rows"]) == sorted(kinds) and all(len(r["vector"]) == 19 for r in d["rows"])
    assert "discovery over" in capsys.readouterr().out
    # a second sequence, pooled with the first
    second = tmp_path / "s.json"
    assert cli.main(["eval", "synthetic", "--sequence", "0002", "--n-frames", "10", "--json", str(second),
                     "--pool", str(out)]) == 0
    both = json.loads(second.read_text())["discovery"]
    assert both["pooled"]["tubes"] == both["tubes"] + d["tubes"] and both["pooled"]["pooled_with"] == ["0001"]
    assert "pooled with 0001: discovery over" in capsys.readouterr().out


def _result(path, sequence: str, vectors: np.ndarray, kinds: list[str], version: str = DESCRIPTOR_VERSION) -> str:
    rows = [{"tube_id": k, "kind": kind, "group": -1, "vector": v.tolist()} for k, (kind, v) in enumerate(zip(kinds, vectors))]
    path.write_text(json.dumps({"sequence": sequence, "discovery": {"descriptor_version": version, "rows": rows}}))
    return str(path)


def test_sequences_too_small_to_group_alone_are_grouped_pooled(tmp_path):
    vectors, kinds = clusters(12)
    thirds = [np.arange(k, 48, 3) for k in range(3)]  # each 16 tubes, 4 of a kind: no group of 10 alone
    section = {"descriptor_version": DESCRIPTOR_VERSION,
               "rows": [{"tube_id": int(k), "kind": kinds[k], "group": -1, "vector": vectors[k].tolist()} for k in thirds[0]]}
    labels, _ = group_vectors(vectors[thirds[0]])
    assert not (labels >= 0).any()  # 16 tubes, 4 of a kind: no group of 10 in one sequence
    paths = [_result(tmp_path / f"{s}.json", s, vectors[t], [kinds[k] for k in t]) for s, t in zip(("0002", "0003"), thirds[1:])]
    pooled = pooled_discovery(section, paths)
    assert pooled["tubes"] == 48 and pooled["pooled_with"] == ["0002", "0003"]
    assert pooled["groups"] == 4 and pooled["group_purity"] == 1.0 and pooled["propagation"] == 1.0


def test_a_pool_file_of_another_recipe_or_not_a_result_is_one_line(tmp_path):
    vectors, kinds = clusters(2)
    old = _result(tmp_path / "old.json", "0002", vectors, kinds, version="d0-00000000")
    with pytest.raises(InputError, match="recipe d0-00000000") as e:
        pool_rows(old)
    assert "\n" not in str(e.value)
    (tmp_path / "bad.json").write_text('{"HOTA": 1}')
    with pytest.raises(InputError, match="discovery rows") as e:
        pool_rows(str(tmp_path / "bad.json"))
    assert "\n" not in str(e.value) and "bad.json" in str(e.value)
