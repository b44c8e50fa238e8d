"""``mine bench stages``: the proposal stage fed by explicit actor queues and by Ray Data, measured alike."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from _run import env
from conftest import REPO
from mining.bench.stages import EmulatedModel, agreement, proposals_digest, windows_of
from mining.types import Proposals


def _props(frame: int, x: float) -> Proposals:
    return Proposals(frame=frame, rles=[{"size": [4, 4], "counts": b"04"}], boxes=np.array([[0, 0, x, 2]], np.float32),
                     objectness=np.array([0.5], np.float32), proposer=["fastsam"])


def test_a_digest_sees_every_difference_and_no_other():
    assert proposals_digest([_props(0, 2.0)]) == proposals_digest([_props(0, 2.0)])
    assert proposals_digest([_props(0, 2.0)]) != proposals_digest([_props(0, 3.0)])  # a box
    assert proposals_digest([_props(0, 2.0)]) != proposals_digest([])
    assert windows_of(250, 100) == [(0, 100), (100, 200), (200, 250)]
    assert EmulatedModel(0.0).propose_images([3, 4], [None, None]) == [[], []]


def test_agreement_counts_frames_that_differ_or_are_extra():
    run = {"ways": {"actors": [{"digests": {"0": "a", "1": "b"}}],
                    "data": [{"digests": {"0": "a", "1": "c", "2": "d"}}, {"digests": {"0": "a", "1": "b"}}]}}
    assert agreement(run) == {"actors": 0, "data": 2}


@pytest.mark.slow  # a local Ray, two ways over 16 frames (the growing pool is the pre-sized one's code with concurrency=(1, N))
def test_every_way_proposes_every_frame_alike_and_reports_its_gpu_busy_share(tmp_path, fastsam_model):
    out = tmp_path / "stages.json"
    p = subprocess.run([sys.executable, "-m", "mining.cli", "bench", "stages", "--option", "width=212",
                        "--option", "height=64", "--frames", "16", "--set", "window.core=8",
                        "--set", "proposals.proposer='fastsam'", "--set", f"proposals.fastsam.model_path='{fastsam_model}'",
                        "--set", "proposals.fastsam.input_height=64", "--set", "proposals.fastsam.input_width=64",
                        "--gpus", "2", "--workers", "2", "--rounds", "1", "--ways", "actors", "data",
                        "--json", str(out)],
                       cwd=REPO, env=env(), capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout + p.stderr
    r = json.loads(out.read_text())
    assert r["ray_version"] == "2.58.0" and r["windows"] == 2 and list(r["ways"]) == ["actors", "data"]
    assert r["frames_differing"] == {"actors": 0, "data": 0}
    empty = proposals_digest([])
    for name, (x,) in r["ways"].items():
        assert x["frames"] == 16, name
        assert sum(d != empty for d in x["digests"].values()) > 0, name  # the model proposed something
        assert 0 < x["busy_share"] <= 1 and x["busy_s"] > 0, name
    # The pipeline's actors: each CPU worker feeds its own model actor, so both had work.
    assert r["ways"]["actors"][0]["model_actors"] == 2 and r["ways"]["actors"][0]["all_busy_after_s"] > 0
    for way in ("actors", "data"):
        assert way in p.stdout
    assert "GPU busy" in p.stdout and "frames differing" in p.stdout
