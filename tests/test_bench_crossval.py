"""``mine bench crossval``: folds partition the sequences, a fold's held-out sequences never
reach its choice, and the choice is the argmax of the training score that an independent
``evaluate_kitti_mot`` over the training sequences gives."""

from __future__ import annotations

from pathlib import Path

import pytest

from mining.bench.crossval import (KITTI_TRAINING_FOLDS, Setting, combined, cross_validate, grid_settings,
                                   make_folds, objective, parse_grid, score_grid, select_setting)
from mining.config import load_config
from mining.eval.kitti_mot import evaluate_kitti_mot
from mining.formats.kitti_tracking import read_seqmap

from conftest import REPO


def _is_partition(folds, sequences) -> bool:
    flat = [s for f in folds for s in f]
    return sorted(flat) == sorted(sequences) and len(flat) == len(set(flat)) and all(folds)


def test_folds_partition_the_sequences(kitti_tracking_root):
    frames = read_seqmap(kitti_tracking_root / "training" / "seqmaps" / "train.seqmap")
    folds = make_folds(frames, 4)
    assert folds == [tuple(f) for f in KITTI_TRAINING_FOLDS]
    assert _is_partition(folds, list(frames)) and len(folds) == 4
    # the three long sequences go to different folds
    assert sorted(next(i for i, f in enumerate(folds) if s in f) for s in ("0009", "0019", "0020")) == [0, 2, 3]
    for k in (2, 3, 5, 12):  # any other K: the serpentine by length
        other = make_folds(frames, k)
        assert _is_partition(other, list(frames)) and len(other) == k
        assert max(map(len, other)) - min(map(len, other)) <= 1
    some = {s: frames[s] for s in ("0000", "0003", "0012", "0019", "0020")}
    assert _is_partition(make_folds(some, 2), list(some))
    with pytest.raises(ValueError):
        make_folds(some, 6)


def test_grid_is_every_combination_reference_first():
    grid = parse_grid(["tubes.max_gap_frames=5,10,20", "select.overlap_weight.reference=30.0,2.0"])
    settings = grid_settings(grid)
    assert len(settings) == 6 and len(set(settings)) == 6
    assert settings[0] == Setting(("tubes.max_gap_frames=5", "select.overlap_weight.reference=30.0"))
    assert settings[0].label == "gap≤0.5s overlap_weight.reference=30.0"
    cfg = load_config(None, list(settings[-1].overrides))
    assert cfg.tubes.max_gap_frames == 20 and cfg.select.overlap_weight.reference == 2.0


# --- selection on hand-made ground truth and results (fast) -------------------------------

def _row(frame: int, tid: int, kind: str, x: float, score: float | None = None) -> str:
    box = f"{x:.1f} 100.0 {x + 40:.1f} 180.0"
    tail = f" {score}" if score is not None else ""
    return f"{frame} {tid} {kind} 0 0 0 {box} 1.5 1.6 3.9 1 1 10 0{tail}"


def _write_gt(path: Path, n: int) -> None:
    path.write_text("".join(_row(t, 0, "Car", 100 + 5 * t) + "\n" + _row(t, 1, "Pedestrian", 600 + 2 * t) + "\n"
                            for t in range(n)))


def _write_result(path: Path, n: int, switch_every: int, miss_every: int) -> None:
    """Both objects tracked, with a new id every ``switch_every`` frames and a miss every ``miss_every``."""
    rows = []
    for t in range(n):
        if miss_every and t % miss_every == miss_every - 1:
            continue
        rows.append(_row(t, 10 + t // switch_every, "Car", 100 + 5 * t, 0.9))
        rows.append(_row(t, 1000 + t // switch_every, "Pedestrian", 600 + 2 * t, 0.9))
    path.write_text("\n".join(rows) + "\n")


# (switch_every, miss_every) per setting and sequence: X is good on "a", Y on "b", "c" is mixed.
QUALITY = {"X": {"a": (100, 0), "b": (3, 2), "c": (20, 0)},
           "Y": {"a": (3, 2), "b": (100, 0), "c": (10, 5)},
           "Z": {"a": (5, 3), "b": (5, 3), "c": (100, 4)}}
N_FRAMES = {"a": 30, "b": 20, "c": 25}


@pytest.fixture(scope="module")
def handmade(tmp_path_factory):
    root = tmp_path_factory.mktemp("handmade")
    (root / "gt").mkdir()
    for seq, n in N_FRAMES.items():
        _write_gt(root / "gt" / f"{seq}.txt", n)
    scores = {}
    for name, per_seq in QUALITY.items():
        (root / name).mkdir()
        for seq, (switch, miss) in per_seq.items():
            _write_result(root / name / f"{seq}.txt", N_FRAMES[seq], switch, miss)
        r = evaluate_kitti_mot(root / "gt", root / name, list(N_FRAMES))
        scores[Setting((f"x.name={name}",))] = r.sums
    return root, scores


def _independent_argmax(root: Path, training: list[str]) -> tuple[str, float]:
    truth = {name: objective(evaluate_kitti_mot(root / "gt", root / name, training)) for name in QUALITY}
    best = max(truth, key=truth.get)
    return best, truth[best]


def test_selection_is_the_argmax_of_an_independent_training_score(handmade):
    root, scores = handmade
    folds = make_folds(N_FRAMES, 3)
    chosen = set()
    for held in folds:
        training = [s for s in N_FRAMES if s not in held]
        setting, score = select_setting(scores, training)
        name, truth = _independent_argmax(root, training)
        assert setting.overrides == (f"x.name={name}",)
        assert score == pytest.approx(truth, abs=1e-12)
        chosen.add(name)
    assert len(chosen) > 1, "the hand-made data makes the choice depend on the training folds"


def test_held_out_sequences_never_reach_the_choice(handmade):
    _, scores = handmade
    folds = make_folds(N_FRAMES, 3)
    baseline = scores[Setting(("x.name=Z",))]
    before = cross_validate(scores, baseline, folds)
    names = list(scores)
    other = {s: names[(i + 1) % len(names)] for i, s in enumerate(names)}
    for n, held in enumerate(folds):
        # give every setting another's held-out sums: only the held-out scores may change
        poisoned = {s: {q: scores[other[s]][q] if q in held else v for q, v in per_seq.items()}
                    for s, per_seq in scores.items()}
        after = cross_validate(poisoned, baseline, folds).folds[n]
        assert after.setting == before.folds[n].setting
        assert after.training_score == before.folds[n].training_score
        assert after.held_out_metrics != before.folds[n].held_out_metrics
        # and selecting from the training sequences alone gives the same
        training = [s for s in N_FRAMES if s not in held]
        only_training = {s: {q: per_seq[q] for q in training} for s, per_seq in scores.items()}
        assert select_setting(only_training, training)[0] == before.folds[n].setting


def test_held_out_scores_and_final_setting(handmade):
    root, scores = handmade
    folds = make_folds(N_FRAMES, 3)
    baseline = scores[Setting(("x.name=Z",))]
    result = cross_validate(scores, baseline, folds)
    for r in result.folds:
        direct = evaluate_kitti_mot(root / "gt", root / r.setting.overrides[0].split("=")[1], list(r.held_out))
        assert r.held_out_metrics["Car"]["HOTA"] == pytest.approx(direct["Car"]["HOTA"], abs=1e-12)
        assert r.held_out_metrics["Pedestrian"]["IDSW"] == direct["Pedestrian"]["IDSW"]
        assert set(r.training) | set(r.held_out) == set(N_FRAMES) and not set(r.training) & set(r.held_out)
    eligible = [r.setting for r in result.folds if r.eligible]
    if eligible:
        top = max(eligible.count(s) for s in eligible)
        assert eligible.count(result.final) == top
    else:
        assert result.final == next(iter(scores))


# --- the real pipeline on three short sequences ---------------------------------------------

@pytest.mark.slow
def test_crossval_on_real_sequences_matches_track_detections(shared_data, tmp_path):
    """score_grid's cached frames and tubes give what ``track_detections`` writes, and each fold's
    choice is the argmax of evaluate_kitti_mot over its training sequences."""
    from mining.pipeline.detections import track_detections

    root = shared_data / "kitti_tracking"
    train = root / "training"
    seqmap = train / "seqmaps" / "train.seqmap"
    config = REPO / "jobs" / "kitti-detections.toml"
    sequences = ["0012", "0003", "0000"]
    settings = grid_settings(parse_grid(["tubes.max_gap_frames=1,10", "select.overlap_weight.reference=30.0,2.0"]))
    scores, baseline = score_grid(shared_data, config, [], sequences, settings, log=lambda _: None)
    for i, s in enumerate(settings):
        cfg = load_config(config, list(s.overrides))
        for seq in sequences:
            track_detections(root, seq, train / "det_pointrcnn", train / "egoposes_orbslam3" / f"{seq}.txt", cfg,
                             tmp_path / str(i) / f"{seq}.txt")
        direct = evaluate_kitti_mot(train / "label_02", tmp_path / str(i), sequences, seqmap=seqmap)
        for seq in sequences:
            for cls in ("Car", "Pedestrian"):
                assert combined(scores[s], [seq])[cls] == direct.per_sequence[seq][cls], (s.label, seq, cls)
    folds = make_folds({s: 1 for s in sequences}, 3)
    result = cross_validate(scores, baseline, folds)
    for r in result.folds:
        training = list(r.training)
        truth = [objective(evaluate_kitti_mot(train / "label_02", tmp_path / str(i), training, seqmap=seqmap))
                 for i in range(len(settings))]
        best = max(range(len(settings)), key=lambda i: (truth[i], -i))
        assert r.setting == settings[best]
        assert r.training_score == pytest.approx(truth[best], abs=1e-12)


# --- the image pipeline's settings over synthetic seeds (mine bench crossval-scenarios) ------

def _with_hota(result: dict, hota: float) -> dict:
    return result | {"modes": {m: v | {"HOTA": hota} for m, v in result["modes"].items()}}


def test_scenario_crossval_never_reads_the_held_out_seed():
    from mining.bench.crossval_scenarios import cross_validate_seeds, scenario_score
    from mining.bench.scenarios import run_scenario

    real = run_scenario("far", load_config(REPO / "jobs" / "synthetic.toml"), n_frames=6, sequence="0000", half=True)
    assert scenario_score([real]) == pytest.approx((real["modes"]["on"]["HOTA"] + real["modes"]["off"]["HOTA"]) / 2)
    ref, new = Setting(("tubes.start_hypotheses=0",)), Setting(("tubes.start_hypotheses=3",))
    seeds = ("0000", "0001", "0002")
    # new is better on 0000 and 0001, worse on 0002
    scores = {ref: {s: [_with_hota(real, 0.5)] for s in seeds},
              new: {"0000": [_with_hota(real, 0.6)], "0001": [_with_hota(real, 0.6)], "0002": [_with_hota(real, 0.4)]}}
    res = cross_validate_seeds(scores, seeds)
    by_seed = {f["held_out"]: f for f in res["folds"]}
    # held out 0002: chosen on 0000+0001 → new, which then loses on 0002 → not eligible
    assert by_seed["0002"]["setting"] == new and not by_seed["0002"]["eligible"]
    assert by_seed["0002"]["held_out_score"] == pytest.approx(0.4) and by_seed["0002"]["reference"] == pytest.approx(0.5)
    # held out 0000: training 0001+0002 → new 0.5 vs ref 0.5, a tie keeps the grid's first (REFERENCE)
    assert by_seed["0000"]["setting"] == ref and by_seed["0000"]["eligible"]
    assert by_seed["0001"]["setting"] == ref
    assert res["final"] == ref and res["cv"][new] == pytest.approx((0.6 + 0.6 + 0.4) / 3)
    # changing only the held-out seed's numbers never changes that fold's choice
    scores[new]["0002"] = [_with_hota(real, 0.99)]
    again = {f["held_out"]: f for f in cross_validate_seeds(scores, seeds)["folds"]}
    assert again["0002"]["setting"] == new and again["0002"]["eligible"]
    # a setting that is better only on the seed held out is never chosen: REFERENCE stays
    worse = {ref: {s: [_with_hota(real, 0.5)] for s in seeds}, new: {s: [_with_hota(real, 0.5)] for s in seeds}}
    worse[new]["0000"] = [_with_hota(real, 0.9)]
    worse[new]["0001"] = [_with_hota(real, 0.1)]
    assert cross_validate_seeds(worse, seeds)["final"] == ref
