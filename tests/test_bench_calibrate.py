"""`mine bench calibrate` end to end on rendered scenes: labels, fit, folds, the TOML it prints."""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib

import numpy as np
import pytest

from mining.score.calibrated import TERMS

SMALL = ["--option", "width=621", "--option", "height=188", "--option", "fx=360.77"]


@pytest.mark.slow
def test_calibrate_prints_weights_a_job_config_takes(tmp_path):
    out = tmp_path / "cal.json"
    p = subprocess.run([sys.executable, "-m", "mining.cli", "bench", "calibrate", "--seeds", "0000", "0001",
                        "--frames", "16", *SMALL, "--json", str(out)], capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stdout + p.stderr
    doc = json.loads(out.read_text())
    assert [f["held_out"] for f in doc["folds"]] == ["0000", "0001"]
    assert set(doc["weights"]) == set(TERMS) and all(np.isfinite(list(doc["weights"].values())))
    assert doc["balance"] is True and doc["epsilon2"] == 3.0
    # the printed table is valid TOML for a job config and holds the same weights
    start = p.stdout.index('[score.calibrated."stereo"]')
    table = p.stdout[start:p.stdout.index("\ncalibrate: ", start)]
    parsed = tomllib.loads(table)["score"]["calibrated"]["stereo"]
    assert parsed == pytest.approx(doc["weights"], rel=1e-5)
    for fold in doc["folds"]:  # both unaries judged the same held-out tubes
        assert fold["job"]["selected"] >= 0 and fold["calibrated"]["selected"] >= 0
        assert 0.0 <= fold["auc"]["calibrated"] <= 1.0
