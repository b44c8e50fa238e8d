"""The benches' own parts, fast (their whole runs are in the slow tier): the detectability fit
recovers the curve it is given, the balanced accuracy counts calls by their truth, the looks
tallies put an object in the rows that name it, and `mine bench proposals` times a real proposer."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mining.bench.classify import balanced_accuracy, fit_detectability
from mining.bench.looks import ClassTally, format_tallies, tally_rows
from mining.score.category import UNKNOWN_CLASS


def test_detectability_fit_recovers_the_curve_it_samples():
    rng = np.random.default_rng(0)
    h50, s = 22.0, 0.35
    heights = np.exp(rng.uniform(np.log(5), np.log(200), 6000))
    p = 1.0 / (1.0 + np.exp(-(np.log(heights) - np.log(h50)) / s))
    covered = rng.random(heights.size) < p
    got_h50, got_s = fit_detectability(heights, covered)
    assert got_h50 == pytest.approx(h50, rel=0.06) and got_s == pytest.approx(s, rel=0.1)


def _posterior(p_car: float, p_unknown: float) -> np.ndarray:
    post = np.zeros(UNKNOWN_CLASS + 1)
    post[2], post[UNKNOWN_CLASS] = p_car, p_unknown  # COCO class 2 is car
    return post


def test_balanced_accuracy_weighs_known_and_unknown_alike():
    calls = [("known", _posterior(0.9, 0.1))] * 3 + [("known", _posterior(0.2, 0.8))] \
        + [("unknown", _posterior(0.1, 0.9)), ("unknown", None)]
    bal, k, u = balanced_accuracy(calls, margin=0.0)
    assert (k, u) == (0.75, 0.5) and bal == pytest.approx(0.625)  # no posterior is no call: a miss either way
    # A margin of ln 10 calls the 0.9 / 0.1 tubes unknown too.
    _, k, _ = balanced_accuracy(calls, margin=np.log(10) + 1e-9)
    assert k == 0.0


def test_looks_rows_and_their_table():
    assert tally_rows("car", "van", 30.0) == [("car", ("car", "truck")), ("car, strict", ("car",)),
                                              ("car, 25–50 px", ("car", "truck")), ("car:van", ("car",))]
    assert tally_rows("bicycle") == [("bicycle", ("bicycle", "person"))]
    t = ClassTally(objects=4, recalled=3, located=4)
    t.argmax.update(["car", "car", "truck"])
    text = format_tallies("KITTI", {"car": t})
    assert "car" in text and "0.750" in text and "1.000" in text and "car 2, truck 1" in text


def test_bench_proposals_times_the_stereo_proposer(shared_data, tmp_path, capsys):
    from mining.cli import main

    assert main(["bench", "proposals", "--data", str(shared_data), "--frames", "0:3",
                 "--json", str(tmp_path / "bench.json")]) == 0
    assert "frames/s" in capsys.readouterr().out
    (row,) = json.loads((tmp_path / "bench.json").read_text())["rows"]
    assert row["mode"] == "per frame" and row["frames"] == 2 and row["fps"] > 0 and row["proposals_per_frame"] > 0
