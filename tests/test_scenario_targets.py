"""Issue 18's failure modes, staged by the renderer, each with its target (scope item 5).

Each test mines one staged scenario (``mining/sources/synthetic/scenarios.py``) with the
learned + stereo proposers (``onnx+stereo``, the shared ONNX model) and the default
settings, and checks the issue's target against the renderer's exact truth. Where today's
miner misses a target, the test is a strict ``xfail`` that names the value measured when it
was written: the miss stays visible, and the test fails (XPASS) the day the target is met,
so its marker must then come off.

* ``barriers`` — a row of construction barriers, the real unknown objects of KITTI 0005:
  most of them must be mined as unknown tubes.
* ``verge`` — a hedge behind a fence with gaps and a grass verge, background with no truth:
  clutter at most 25 % of the selected tubes (the issue's stereo-only target).
* ``parkedpair`` — pairs of parked cars nose to tail at 35–55 m: every car whole.
* ``debris`` — small unknown pieces in view for 5–8 frames: mined although short.
"""

from __future__ import annotations

import pytest

from conftest import MODELS
from mining.bench.synthetic import run_synthetic
from mining.config import load_config

pytestmark = pytest.mark.slow  # the whole pipeline over 30–40 rendered frames each

MODEL = MODELS / "yolov8n-seg_int8.onnx"
HALF = {"width": 621, "height": 188}  # half KITTI size: the scenario's objects at half the pixels


def _mine(scenario: str, n_frames: int, size: dict[str, int] | None = None) -> dict:
    if not MODEL.exists():
        pytest.skip(f"no ONNX model at {MODEL}")
    options = {"scenario": scenario, **(size or {})}
    cfg = load_config(None, [f"source.options={_toml(options)}", 'proposals.proposer="onnx+stereo"',
                             f'proposals.onnx.model_path="{MODEL}"'])
    _, results = run_synthetic("0000", n_frames, cfg)
    return results


def _toml(options: dict) -> str:
    return "{" + ", ".join(f'{k}="{v}"' if isinstance(v, str) else f"{k}={v}" for k, v in options.items()) + "}"


@pytest.mark.xfail(strict=True, reason="issue 18: measured unknown tube recall 0.00 (0 of 7 barriers; the stereo "
                                       "proposer proposes 19 % of barrier detections, none beyond 20 m)")
def test_a_row_of_barriers_is_mined_as_unknown_objects():
    r = _mine("barriers", 40, HALF)
    assert r["unknown"]["tracks"] >= 4
    assert r["unknown"]["tube_recall"] >= 0.5, r["unknown"]


@pytest.mark.xfail(strict=True, reason="issue 18: measured clutter 74 % of the selected tubes (14 of 19, hedge, "
                                       "fence and grass called unknown)")
def test_a_hedge_fence_and_grass_verge_are_not_selected():
    r = _mine("verge", 40, HALF)
    assert r["tubes"]["evaluated"] > 0
    assert r["tubes"]["clutter_share"] <= 0.25, r["tubes"]


@pytest.mark.xfail(strict=True, reason="issue 18: measured known tube recall 0.67 (4 of 6 parked cars at 35–55 m)")
def test_parked_cars_side_by_side_far_away_are_each_one_tube():
    r = _mine("parkedpair", 40, HALF)
    assert r["known"]["tracks"] >= 4
    assert r["known"]["tube_recall"] >= 0.9, r["known"]


@pytest.mark.xfail(strict=True, reason="issue 18: measured unknown tube recall 0.00 (debris in view 5–8 frames "
                                       "is not mined)")
def test_small_debris_seen_for_a_few_frames_is_mined():
    r = _mine("debris", 40)  # full size: at half size the pieces are under the 100-pixel evaluation floor
    assert r["unknown"]["tracks"] >= 2
    assert r["unknown"]["tube_recall"] >= 0.5, r["unknown"]
