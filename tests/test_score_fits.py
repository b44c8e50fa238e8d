"""Fitted weights are package data (mining/score/fits/*.toml) with their provenance, written by
`mine bench calibrate --write` (and `--calling --write`), read back float for float."""

from __future__ import annotations

import shutil
import tomllib

import numpy as np
import pytest

from _run import cli
from mining.bench import calibrate, calling
from mining.bench.fit import write_fit
from mining.score.calibrated import TERMS
from mining.score.category import ROW_FEATURES
from mining.score.clutter import OBJECT_TERMS
from mining.score.config import CALIBRATED, OBJECT_EVIDENCE, ROW_KNOWN, ROW_ON_OBJECT
from mining.score.fits import (FITS_DIR, OBJECT_FIT, ROWS, UNARY_FIT, fit_text, proposer_weights, read_fits,
                               row_weights, updated_fit)

PROVENANCE = {"command", "commit", "proposer", "seeds", "frames", "samples", "auc", "note"}


def _tables():
    for name, doc in read_fits().items():
        for fit, table in doc.items():
            yield name, fit, table


def test_the_defaults_are_the_fit_files_each_fit_saying_how_it_was_made():
    assert CALIBRATED == proposer_weights(UNARY_FIT) and set(CALIBRATED) == {"onnx+stereo", "stereo"}
    assert OBJECT_EVIDENCE == proposer_weights(OBJECT_FIT) and set(OBJECT_EVIDENCE) == {"onnx+stereo"}
    assert (ROW_ON_OBJECT, ROW_KNOWN) == row_weights()
    for weights in CALIBRATED.values():
        assert list(weights) == list(TERMS)
    assert list(OBJECT_EVIDENCE["onnx+stereo"]) == list(OBJECT_TERMS)
    assert list(ROW_ON_OBJECT) == list(ROW_KNOWN) == list(ROW_FEATURES)
    for name, fit, table in _tables():
        assert PROVENANCE <= set(table), (name, fit)
        assert table["command"].startswith("mine bench calibrate") and table["seeds"], (name, fit)


def test_the_shipped_files_are_what_the_writer_writes_floats_as_their_repr():
    """Byte for byte: so each float is written as Python's repr, which reads back to the same float."""
    for name, doc in read_fits().items():
        assert fit_text(name, doc) == (FITS_DIR / f"{name}.toml").read_text(encoding="utf-8"), name
    text = (FITS_DIR / "stereo.toml").read_text()
    assert "\nln_objectness = 8.66293\n" in text and CALIBRATED["stereo"]["ln_objectness"] == 8.66293


def test_write_replaces_one_fit_keeps_the_others_and_reads_back_bitwise(tmp_path):
    fits = tmp_path / "fits"
    shutil.copytree(FITS_DIR, fits)
    before = {p.name: p.read_bytes() for p in FITS_DIR.iterdir()}
    weights = {k: float(v) for k, v in zip(TERMS, np.random.default_rng(3).normal(size=len(TERMS)))}
    weights["frame"] = 0.1 + 0.2  # 0.30000000000000004: a float whose short spelling would not read back
    table = {"command": "mine bench calibrate --write", "commit": "abc1234", "proposer": "onnx+stereo",
             "seeds": ["0000", "0001"], "frames": 16, "note": "a test", "samples": {"object": 3, "part_or_clutter": 5},
             "auc": {"mean": 0.75, "reference_mean": 0.5}, "weights": weights}
    path = write_fit("onnx+stereo", UNARY_FIT, table, fits)
    assert path == fits / "onnx+stereo.toml"
    back = proposer_weights(UNARY_FIT, fits)["onnx+stereo"]
    assert all(back[k].hex() == weights[k].hex() for k in TERMS) and list(back) == list(TERMS)
    assert proposer_weights(OBJECT_FIT, fits) == OBJECT_EVIDENCE  # the other table of the same file kept
    assert proposer_weights(UNARY_FIT, fits)["stereo"] == CALIBRATED["stereo"]
    assert tomllib.loads(path.read_text())[UNARY_FIT]["commit"] == "abc1234"
    write_fit("onnx", UNARY_FIT, table, fits)  # a proposer without a file gets one
    assert proposer_weights(UNARY_FIT, fits)["onnx"] == weights
    assert {p.name: p.read_bytes() for p in FITS_DIR.iterdir()} == before  # the package's files untouched
    with pytest.raises(ValueError, match="finite"):
        updated_fit("stereo", UNARY_FIT, {**table, "weights": {"bias": float("nan")}}, fits)


def test_the_benches_fit_tables_record_what_each_was_fit_on(tmp_path):
    rng = np.random.default_rng(5)
    final = {k: float(v) for k, v in zip(TERMS, rng.normal(size=len(TERMS)))}
    folds = [{"auc": {"calibrated": 0.8, "job": 0.6}}, {"auc": {"calibrated": 0.9, "job": np.nan}}]
    y = np.array([True, True, False, False, False])
    table = calibrate.unary_fit(final, folds, y, np.array([True, False, False, True, False]), "stereo",
                                ["0000", "0001"], 16, "mine bench calibrate --write")
    assert table["samples"] == {"object": 2, "object_on_unknown": 1, "part_or_clutter": 3}
    assert table["auc"] == {"mean": 0.85, "reference_mean": 0.6} and table["weights"] == final
    assert table["proposer"] == "stereo" and table["frames"] == 16 and table["commit"]
    write_fit("stereo", UNARY_FIT, table, tmp_path)
    assert proposer_weights(UNARY_FIT, tmp_path) == {"stereo": final}

    fit = {"row_on_object": dict(ROW_ON_OBJECT), "row_known": dict(ROW_KNOWN), "margin": 0.0, "unknown_cost": 0.5,
           "balanced_accuracy": 0.9, "object_evidence": dict(OBJECT_EVIDENCE["onnx+stereo"]), "unknown_min_object": 0.5}
    labels = np.array([calling.KNOWN, calling.UNKNOWN, calling.NOTHING, calling.NOTHING], float)
    data = [{"rows": np.column_stack([np.ones((4, 3)), labels]), "y": y,
             "unknown": np.array([False, True, False, False, False])}]
    auc = {"row_on_object": 0.8, "row_known": 0.95, "row_known_score_alone": 0.9, "object_evidence": 0.9}
    folds = [{"auc": auc}, {"auc": {**auc, "row_on_object": 0.7}}]
    rows, obj = calling.calling_fits(fit, folds, data, "onnx+stereo", ["0000", "0001"], 16,
                                     "mine bench calibrate --calling")
    assert rows["samples"] == {"rows": 4, "on_known": 1, "on_unknown": 1, "on_nothing": 2} and "× 0.5" in rows["note"]
    assert rows["auc"]["on_object"] == [0.7, 0.8] and obj["auc"] == {"min": 0.9, "max": 0.9}
    assert obj["samples"] == {"object": 2, "object_on_unknown": 1, "part_or_clutter": 3}
    write_fit("onnx+stereo", OBJECT_FIT, obj, tmp_path)
    write_fit(ROWS, ROWS, rows, tmp_path)
    assert proposer_weights(OBJECT_FIT, tmp_path) == OBJECT_EVIDENCE
    assert row_weights(tmp_path) == (ROW_ON_OBJECT, ROW_KNOWN)
    assert proposer_weights(UNARY_FIT, tmp_path) == {"stereo": final}  # onnx+stereo.toml has no [unary] here


@pytest.mark.parametrize("given, expect", [((), None), (("--write",), FITS_DIR), (("--write", "FITS"), "FITS")])
def test_write_names_the_folder_of_fit_files_the_package_by_default(given, expect, tmp_path, capsys, monkeypatch):
    seen = {}
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(calibrate, "run_calling_bench", lambda *a, **k: seen.update(k) or 0)
    monkeypatch.setattr(calibrate, "run_calibrate_bench", lambda *a, **k: seen.update(k) or 0)
    for calls in (["--calling"], []):
        seen.clear()
        rc, _, err = cli(capsys, "bench", "calibrate", *calls, *given)
        assert rc == 0, err
        assert (seen["write"] if expect in (None, FITS_DIR) else str(seen["write"])) == expect
        assert seen["command"].startswith("mine")
