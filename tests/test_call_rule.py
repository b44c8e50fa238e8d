"""The call agrees with the numbers stored beside it (issue 39): a property over random posteriors.

Random tubes (random class posteriors per frame, random evidence weights, some frames no
classifier looked at), random margins ≥ 0 and gate thresholds: whatever the draw, the call
written to the catalogue (``rows.tube_row``), the label the exports write (``category_label``)
and the caption renders draw (``tube_caption``) must follow the one rule of
``mining.score.call`` from the stored posterior alone. The rule is restated here in its own
terms (argmax, sums), not by calling the code under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_calling import frame, rect

from mining.catalog.rows import tube_row
from mining.config import ConfigError, job_config_from_record, load_config
from mining.export.render import tube_caption
from mining.export.selection import category_label, tube_call
from mining.formats.coco import COCO_CLASSES
from mining.pipeline.mine import judge
from mining.types import CALLS, UNKNOWN_CLASS, Tube

DRAWS = 300  # random tubes; each is judged under its own margin and gate


def _random_tube(rng: np.random.Generator, tube_id: int) -> Tube:
    n = int(rng.integers(1, 7))
    frames = []
    for k in range(n):
        looked = rng.random() < 0.7
        # peaked or flat posteriors, unknown often winning: Dirichlet with a random concentration
        alpha = np.full(81, rng.choice([0.05, 0.3, 1.0]))
        alpha[UNKNOWN_CLASS] *= rng.choice([1.0, 5.0, 40.0])
        p = rng.dirichlet(alpha)
        frames.append(frame(k, rect(2 + k, 2, 22 + k, 30), p if looked else None, depth=float(rng.uniform(5, 60)),
                            weight=float(rng.choice([0.05, 0.3, 1.0])) if looked else 0.0))
    return Tube(tube_id, 0, frames)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_call_follows_the_stored_posterior(seed):
    rng = np.random.default_rng(seed)
    for i in range(DRAWS // 3):
        margin = float(rng.choice([0.0, 0.0, 0.5, 1.5]))
        gate = float(rng.choice([0.0, 0.5, 0.9]))
        # the stereo proposer: rows as given (reference reading)
        cfg = load_config(None, ["proposals.proposer=stereo", f"score.known_margin.reference={margin}",
                                 f"score.unknown_min_object={gate}", "select.price.calibrated=-100",
                                 "select.price.reference=-100",  # an object gate of its own, of random lean
                                 f"score.object_evidence.stereo.bias={rng.uniform(-3, 3):.3f}",
                                 f"score.object_evidence.stereo.mean_fill={rng.uniform(-2, 2):.3f}"])
        m = judge([_random_tube(rng, i)], cfg)[0]
        c = m.category
        assert c.call in CALLS
        row = tube_row(m, f"d/s/{i}", _Run())
        post = None if row["class_posterior"] is None else np.asarray(row["class_posterior"], np.float64)
        if c.classified_frames == 0:  # unclassified is only a tube no classifier looked at
            assert (row["call"], row["known"], row["category"], post) == ("unclassified", None, None, None)
        else:
            assert row["call"] != "unclassified" and post is not None
            best = int(np.argmax(post[:UNKNOWN_CLASS]))
            p_best, p_unknown = post[best], post[UNKNOWN_CLASS]
            wins = p_best > 0 and (p_unknown <= 0 or math.log(p_best) - math.log(p_unknown) > margin + 1e-6)
            loses = p_best <= 0 or math.log(p_best) - math.log(p_unknown) <= margin - 1e-6
            if row["known"]:
                assert not loses and row["call"] == "known" and row["category"] == COCO_CLASSES[best]
                # a known call's class beats unknown, so unknown holds under half of the posterior
                assert row["category_prob"] == pytest.approx(p_best, rel=1e-5) and p_best > p_unknown
                assert p_unknown < 0.5 and math.isnan(c.object_prob)
            else:
                assert not wins and row["known"] is False and row["category"] == "unknown"
                assert row["category_prob"] == pytest.approx(p_unknown, rel=1e-5)
                # the gate judged it; clutter exactly where P(object) is under the threshold
                assert row["object_prob"] is not None
                assert row["call"] == ("clutter" if row["object_prob"] < gate - 1e-6 else "unknown") or \
                    abs(row["object_prob"] - gate) < 1e-6
        # the exports and the renders read the same call
        assert tube_call(row) == row["call"]
        label = category_label(row)
        assert label == (row["category"] if row["call"] == "known" else row["call"])
        assert tube_caption(row).split(" ", 1)[1].startswith(label)


class _Run:
    run_id, params_hash, bf = "r", "h", None


def test_rows_written_before_the_call_column_read_it_from_known():
    assert tube_call({"known": True, "category": "car"}) == "known"
    assert tube_call({"known": False, "category": "unknown"}) == "unknown"
    assert tube_call({"known": None, "category": None}) == "unclassified"
    assert tube_call({"call": "clutter", "known": False}) == "clutter"
    assert category_label({"call": None, "known": True, "category": "car"}) == "car"


def test_a_negative_margin_is_refused_in_a_job_but_read_in_a_record():
    with pytest.raises(ConfigError, match=r"known_margin.calibrated = -1: must be ≥ 0"):
        load_config(None, ["score.known_margin.calibrated=-1"])
    # a job recorded before issue 39: margin −1, the gate action "unclassified", min_class_evidence
    old = load_config().to_dict()
    old["score"]["known_margin"]["calibrated"] = -1.0
    old["score"]["unknown_gate"] = "unclassified"
    old["score"]["min_class_evidence"] = 1.0
    cfg = job_config_from_record(old, "job.json")
    assert cfg.score.known_margin.calibrated == -1.0 and cfg.score.unknown_gate == "call"
    with pytest.raises(ConfigError, match=r"'unclassified' is now 'call'"):
        load_config(None, ["score.unknown_gate=unclassified"])
    with pytest.raises(ConfigError, match=r"score.min_class_evidence was removed"):
        load_config(None, ["score.min_class_evidence=1"])
