"""`mine bench calibrate` end to end on rendered scenes: labels, fit, folds, the TOML it prints."""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib

import numpy as np
import pytest

from _run import cli, clean_error
from mining.score.calibrated import TERMS

SMALL = ["--option", "width=621", "--option", "height=188", "--option", "fx=360.77"]


@pytest.mark.slow
def test_calibrate_prints_weights_a_job_config_takes(tmp_path):
    out = tmp_path / "cal.json"
    fits = tmp_path / "fits"
    p = subprocess.run([sys.executable, "-m", "mining.cli", "bench", "calibrate", "--seeds", "0000", "0001",
                        "--frames", "16", *SMALL, "--json", str(out), "--write", str(fits)],
                       capture_output=True, text=True, timeout=900)
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
    # --write recorded the same weights, float for float, with how they were made
    written = tomllib.loads((fits / "stereo.toml").read_text())["unary"]
    assert written["weights"] == doc["weights"] and written["seeds"] == ["0000", "0001"] and written["frames"] == 16
    assert written["command"].startswith("mine bench calibrate --seeds 0000 0001") and written["commit"]
    for fold in doc["folds"]:  # both unaries judged the same held-out tubes
        assert fold["job"]["selected"] >= 0 and fold["calibrated"]["selected"] >= 0
        assert 0.0 <= fold["auc"]["calibrated"] <= 1.0


# -- every option checked before the mining (issue 28, case 9) -------------------------------
#
# The adversarial run: too few frames ended in ``ValueError: need at least one array to
# concatenate``; ``--l2 -1``, ``--l2 nan``, ``--epsilon2 inf``, ``--workers 0`` and ``--json
# /proc/x.json`` were accepted and failed (or not) only after the mining.


@pytest.mark.parametrize("bad, named", [
    (["--l2", "-1"], "--l2"), (["--l2", "nan"], "--l2"), (["--l2", "0"], "--l2"), (["--epsilon2", "inf"], "--epsilon2"),
    (["--epsilon1", "nan"], "--epsilon1"), (["--workers", "0"], "--workers"), (["--frames", "0"], "--frames"),
    (["--json", "/proc/x.json"], "--json"), (["--seeds", "0000"], "--seeds"), (["--seeds", "0001", "0001"], "--seeds"),
])
def test_every_option_is_checked_before_any_mining(bad, named, tmp_path, capsys, monkeypatch):
    import mining.bench.calibrate as calibrate

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(calibrate, "_mine_seed", lambda job: pytest.fail(f"mined {job[0]} before refusing {bad}"))
    rc, out, err = cli(capsys, "bench", "calibrate", *SMALL, *bad)
    line = clean_error(err)
    assert rc == 2 and named in line and len(err.strip().splitlines()) == 1, (rc, out, err)
    assert "calibrate: mining" not in out


def test_too_few_frames_to_fit_is_one_line_naming_what_is_missing(tmp_path, capsys, monkeypatch):
    import mining.bench.calibrate as calibrate

    monkeypatch.chdir(tmp_path)
    # Two frames make no tube at all (the real run: 0 candidate tubes per seed); mining them is not the point here.
    monkeypatch.setattr(calibrate, "_mine_seed", lambda job: (job[0], [], {}, 0.0))
    rc, out, err = cli(capsys, "bench", "calibrate", *SMALL, "--seeds", "0000", "0001", "--frames", "2")
    line = clean_error(err)
    assert rc == 2 and len(err.strip().splitlines()) == 1, (rc, out, err)
    assert "too few frames to fit" in line and "no object tube and no part or clutter tube" in line, line
    assert "0001" in line and "--frames" in line, line
