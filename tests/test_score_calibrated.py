"""The calibrated unary (issue 18, scope 4): its family, its fit, its labels and its config.

Truth is independent of the code under test: the REFERENCE unary written out by hand, weights
that generated the data, pairwise counts for the AUC, masks from the renderer's truth.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from pycocotools import mask as mask_utils

from mining.bench.calibrate import calibrated_config
from mining.bench.fit import fit_log_odds, roc_auc
from mining.config import JobConfig, load_config
from mining.errors import ConfigError
from mining.eval.tube_labels import label_tubes
from mining.masks import rle_box
from mining.pipeline.mine import judge, unary
from mining.score.calibrated import FEATURES, TERMS, calibrated_score, tube_evidence
from mining.score.config import KnownMargin, ScoreConfig
from mining.catalog.records import JobRecord
from mining.catalog.store import Store
from mining.score.config import CALIBRATED
from mining.score.unary import score_tube, unary_version, unary_weights
from mining.sources.synthetic import SyntheticSource
from mining.types import UNKNOWN_CLASS, Tube, TubeFrame


def _frame(k: int, mask: np.ndarray, iou: float, density: float, objectness: float, size=(1.8, 1.5, 4.0),
           posterior: np.ndarray | None = None) -> TubeFrame:
    rle = mask_utils.encode(np.asfortranarray(mask.astype(np.uint8)))
    return TubeFrame(k, k * 100_000_000, True, 0, rle, rle_box(rle), np.zeros(3), np.zeros(3),
                     np.asarray(size, float), np.zeros(3), objectness, np.nan if k == 0 else iou,
                     np.nan if k == 0 else density, posterior)


def _random_tube(rng: np.random.Generator, n: int) -> Tube:
    mask = np.zeros((20, 30), bool)
    mask[5:15, 5:20] = True
    t = Tube(1, 0)
    for k in range(n):
        t.frames.append(_frame(k, mask, rng.uniform(0.05, 1), rng.uniform(1e-4, 2), rng.uniform(0.05, 1),
                               rng.uniform(0.2, 6, 3)))
    return t


def test_the_calibrated_family_holds_the_reference_unary():
    """With w = the REFERENCE's α, β and K written as per-frame weights, θ is the REFERENCE total."""
    cfg = ScoreConfig()
    a, b = cfg.alpha, cfg.beta
    ref = {"ln_motion": b * a, "ln_mask_iou": b * (1 - a), "ln_objectness": 1 - b,
           "frame": b * a * np.log(cfg.motion_k) + b * (1 - a) * np.log(cfg.mask_k) + (1 - b) * np.log(cfg.objectness_k)}
    rng = np.random.default_rng(0)
    for n in (2, 5, 17):
        t = _random_tube(rng, n)
        assert calibrated_score(t, ref, cfg.floor) == pytest.approx(score_tube(t, cfg).total, rel=1e-12)
        assert score_tube(t, cfg, ref).total == pytest.approx(score_tube(t, cfg).total, rel=1e-12)


def test_evidence_sums_frames_after_the_first_and_reads_size_and_class_mass():
    rng = np.random.default_rng(1)
    t = _random_tube(rng, 4)
    post = np.zeros(81)
    post[UNKNOWN_CLASS], post[2] = 0.25, 0.75
    t.frames[2].posterior = post
    ev = dict(zip(TERMS, tube_evidence(t, 1e-6)))
    inl = t.frames[1:]
    assert ev["bias"] == 1.0 and ev["frame"] == 3.0
    assert ev["ln_mask_iou"] == pytest.approx(sum(np.log(f.mask_iou) for f in inl))
    assert ev["ln_height"] == pytest.approx(sum(np.log(f.size[1]) for f in inl))
    assert ev["ln_length_sq"] == pytest.approx(sum(np.log(f.size[2]) ** 2 for f in inl))
    assert ev["known_mass"] == pytest.approx(0.75)
    assert len(FEATURES) + 1 == len(TERMS)


def test_fit_recovers_the_weights_that_made_the_labels():
    """Labels drawn from σ(w·x) with known w: the fit finds w (weak penalty, many samples)."""
    rng = np.random.default_rng(2)
    n = 20000
    x = np.column_stack([np.ones(n), rng.normal(3, 2, n), rng.normal(-1, 0.5, n)])
    w = np.array([-1.0, 0.8, -2.0])
    y = rng.random(n) < 1 / (1 + np.exp(-(x @ w)))
    got = fit_log_odds(x, y, l2=1e-3)
    assert got == pytest.approx(w, abs=0.1)


def test_roc_auc_is_the_pairwise_share():
    rng = np.random.default_rng(3)
    s = np.round(rng.normal(size=60), 1)  # ties on purpose
    y = rng.random(60) < 0.4
    pos, neg = s[y], s[~y]
    pairs = (pos[:, None] > neg[None, :]).sum() + 0.5 * (pos[:, None] == neg[None, :]).sum()
    assert roc_auc(s, y) == pytest.approx(pairs / (len(pos) * len(neg)))


ONNX = 'proposals.proposer="onnx"'  # a proposer without default weights


def test_calibrated_model_needs_weights_for_the_jobs_proposer():
    with pytest.raises(ConfigError, match="no weights for proposer 'onnx'"):
        load_config(None, ['score.model="calibrated"', ONNX])
    with pytest.raises(ConfigError, match="unknown term"):
        load_config(None, ['score.model="calibrated"', 'score.calibrated.stereo.wheel=1.0'])
    cfg = load_config(None, ['score.model="calibrated"', 'score.calibrated.onnx.frame=-1.5', ONNX])
    assert unary_weights(cfg.score, "onnx") == {"frame": -1.5}
    # the weights for one proposer are never used for another
    with pytest.raises(ConfigError, match="'torch'"):
        load_config(None, ['score.model="calibrated"', 'score.calibrated.onnx.frame=-1.5',
                           'proposals.proposer="torch"'])


def test_a_weight_set_in_a_job_config_keeps_the_defaults_other_terms():
    from mining.score.config import CALIBRATED

    cfg = load_config(None, ['score.calibrated.stereo.frame=-1.5'])
    assert cfg.score.calibrated["stereo"] == {**CALIBRATED["stereo"], "frame": -1.5}
    assert cfg.score.calibrated["onnx+stereo"] == CALIBRATED["onnx+stereo"]
    assert JobConfig().score.calibrated == CALIBRATED and JobConfig().score.model == "auto"


def test_judge_selects_by_log_odds_with_the_calibrated_model():
    """A tube whose log-odds is positive is selected at ε1 = 0; one whose is negative is not."""
    rng = np.random.default_rng(4)
    good, bad = _random_tube(rng, 6), _random_tube(rng, 6)
    bad.tube_id = 2
    for f in bad.frames:  # far apart: no overlap between the two
        f.rle = mask_utils.encode(np.asfortranarray(np.pad(np.ones((3, 3), np.uint8), ((0, 17), (26, 1)))))
        f.box = rle_box(f.rle)
    for f in good.frames[1:]:
        f.mask_iou = 0.9
    for f in bad.frames[1:]:
        f.mask_iou = 0.1
    cfg = calibrated_config(JobConfig(), {"frame": 0.5, "ln_mask_iou": 2.0})
    theta = unary(cfg)
    assert theta(good).total > 0 > theta(bad).total
    chosen = {m.tube.tube_id: m.selected for m in judge([good, bad], cfg)}
    assert chosen == {1: True, 2: False}


def test_labels_from_rendered_truth_object_part_clutter():
    """Tubes cut from the renderer's truth masks: an object's whole mask, the lower quarter of
    it (a part), and a patch of road far from every object (clutter)."""
    src = SyntheticSource(n_frames=4, scenario="alongside", width=621, height=188, fx=360.77)
    plan = src.plan("0000")
    truths = {i: src.read_frame(plan, i).truth for i in range(4)}
    objs = [{o.track_id: o for o in truths[i].objects} for i in range(4)]
    tid = max(objs[0], key=lambda k: objs[0][k].mask.sum())
    assert all(tid in o for o in objs)
    whole, part, clutter = Tube(1, 0), Tube(2, 0), Tube(3, 0)
    union = np.zeros_like(objs[0][tid].mask)
    for i in range(4):
        for o in objs[i].values():
            union |= o.mask
    for i in range(4):
        m = objs[i][tid].mask
        whole.frames.append(_frame(i, m, 0.9, 1.0, 0.9))
        rows = np.flatnonzero(m.any(axis=1))
        low = m.copy()
        low[: rows[0] + 3 * (rows[-1] - rows[0]) // 4] = False
        part.frames.append(_frame(i, low, 0.9, 1.0, 0.9))
        ys, xs = np.nonzero(~union)
        patch = np.zeros_like(m)
        y0, x0 = ys[len(ys) // 2], xs[len(xs) // 2]
        patch[max(y0 - 5, 0):y0 + 5, max(x0 - 5, 0):x0 + 5] = True
        clutter.frames.append(_frame(i, patch & ~union, 0.9, 1.0, 0.9))
    labels = label_tubes([whole, part, clutter], truths)
    assert labels[1].label == "object" and labels[1].object_track == tid and labels[1].share == 1.0
    assert labels[2].label == "part"
    assert labels[3].label == "clutter"
    assert label_tubes([whole], {99: truths[0]})[1].label == "outside"


def test_grouped_terms_add_up_to_the_log_odds():
    """The funnel's "carried by" for the calibrated model: its groups split θ exactly."""
    from mining.eval.funnel import carried_by
    from mining.score.calibrated import GROUPS, grouped_terms

    rng = np.random.default_rng(5)
    t = _random_tube(rng, 7)
    w = dict(zip(TERMS, rng.normal(size=len(TERMS))))
    g = grouped_terms(t, w, 1e-6)
    assert set(g) == set(GROUPS) and sorted(sum(GROUPS.values(), ())) == sorted(TERMS)
    assert sum(g.values()) == pytest.approx(calibrated_score(t, w, 1e-6))
    assert carried_by(g) == max(g, key=g.get) or max(g.values()) <= 0


def test_auto_falls_back_to_the_reference_and_says_so():
    from mining.score.unary import unary_line

    cfg = load_config(None, ['score.model="auto"'])
    assert unary_weights(cfg.score, "stereo") == cfg.score.calibrated["stereo"]
    assert unary_weights(cfg.score, "onnx") is None  # no weights for it: the REFERENCE, stated
    assert "calibrated" in unary_line(cfg.score, "stereo")
    assert "REFERENCE" in unary_line(cfg.score, "onnx") and "no calibrated weights for 'onnx'" in unary_line(cfg.score, "onnx")
    assert "REFERENCE" in unary_line(load_config(None, ['score.model="reference"']).score, "stereo")


def test_the_calibrated_unary_is_priced_by_its_own_epsilon1():
    """ε1 = 20 is the REFERENCE's price on its own scale; a log-odds is priced by select.price.calibrated."""
    rng = np.random.default_rng(6)
    t = _random_tube(rng, 6)
    for f in t.frames[1:]:
        f.mask_iou = 0.9
    cfg = calibrated_config(JobConfig(), {"frame": 0.5, "ln_mask_iou": 2.0})  # θ ≈ 1.45
    assert cfg.select.price.reference == 20.0 and cfg.select.price.calibrated == 0.0
    assert judge([t], cfg)[0].selected
    cfg.select.price.calibrated = 2.0
    assert not judge([t], cfg)[0].selected


def test_balance_gives_unknown_objects_the_known_objects_weight():
    from mining.bench.fit import balance_weights

    y = np.array([1, 1, 1, 1, 1, 1, 0, 0], bool)
    unknown = np.array([0, 0, 0, 0, 1, 1, 0, 1], bool)  # the last is not an object: it keeps weight 1
    w = balance_weights(y, unknown)
    assert w[y & unknown].sum() == pytest.approx(w[y & ~unknown].sum()) == 4.0
    assert list(w[~y]) == [1.0, 1.0]
    assert list(balance_weights(y, np.zeros(8, bool))) == [1.0] * 8


def test_detections_only_mode_is_never_scored_with_an_image_proposers_weights():
    """3D detections are not the job's (default: stereo) proposer: "auto" scores them by the REFERENCE."""
    from mining.pipeline.detections import DETECTIONS

    cfg = load_config(None, ['score.model="auto"'])
    t = _random_tube(np.random.default_rng(7), 5)
    assert unary(cfg, DETECTIONS)(t).total == score_tube(t, cfg.score).total
    assert unary(cfg)(t).total == pytest.approx(calibrated_score(t, cfg.score.calibrated["stereo"], cfg.score.floor))


def test_the_catalogue_stores_which_unary_made_the_score_and_the_terms_that_add_up_to_it(base_catalogue):
    from mining.catalog.rows import THETA_GROUPS
    from mining.catalog.views import connect
    from mining.score.calibrated import GROUPS
    from mining.score.config import KnownMargin, ScoreConfig

    assert THETA_GROUPS == tuple(GROUPS)
    out, _ = base_catalogue
    con = connect(out)
    try:
        rows = con.execute("SELECT score_model, score, score_motion, score_mask, score_objectness, "
                           + ", ".join(f"theta_{g}" for g in GROUPS) + " FROM tubes").fetchall()
        versions = con.execute("SELECT DISTINCT score_model, score_version FROM tube_scores").fetchall()
    finally:
        con.close()
    assert rows and {r[0] for r in rows} <= {"calibrated", "reference"}
    # One unary per catalogue, and its version is the hash of the job's own parameters.
    job = JobRecord.load(Store(out)).job_config()
    (model, version), = versions
    assert version == unary_version(job.score, unary_weights(job.score, job.proposals.proposer))
    assert version.startswith(f"{model}-")
    cfg = ScoreConfig()
    for model, score, motion, mask, obj, *theta in rows:
        if model == "calibrated":
            assert None not in theta and abs(sum(theta) - score) <= 1e-9 * max(1.0, abs(score))
        else:
            assert theta == [None] * len(GROUPS)
            assert abs(cfg.beta * (cfg.alpha * motion + (1 - cfg.alpha) * mask) + (1 - cfg.beta) * obj - score) < 1e-9


def test_the_score_version_changes_with_any_parameter_of_the_total_and_only_those():
    from mining.score.config import KnownMargin, ScoreConfig
    from mining.score.unary import unary_version

    cfg = ScoreConfig()
    w = dict(CALIBRATED["stereo"])
    base, ref = unary_version(cfg, w), unary_version(cfg, None)
    assert base.startswith("calibrated-") and ref.startswith("reference-") and base[11:] != ref[10:]
    assert unary_version(cfg, dict(reversed(list(w.items())))) == base  # the order of a table is no parameter
    assert unary_version(cfg, {**w, "bias": w["bias"] + 1e-6}) != base
    assert unary_version(dataclasses.replace(cfg, floor=1e-5), w) != base
    assert unary_version(dataclasses.replace(cfg, alpha=0.4), None) != ref
    assert unary_version(dataclasses.replace(cfg, alpha=0.4), w) == base  # not a parameter of the calibrated total
    assert unary_version(dataclasses.replace(cfg, known_margin=KnownMargin(reference=0.0)), None) == ref  # the class call is not the score
