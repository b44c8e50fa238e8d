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

from collections.abc import Callable
from operator import ge, gt, le
from typing import Any

import pytest

from conftest import MODEL
from mining.bench.synthetic import run_synthetic
from mining.config import load_config

pytestmark = pytest.mark.slow  # the whole pipeline over 30–40 rendered frames each

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


# (scenario, frame size, result group, [(key, comparison, bound), ...]): first a floor on what
# was mined at all, then the target.
TARGETS = [
    pytest.param("barriers", HALF, "unknown", [("tracks", ge, 4), ("tube_recall", ge, 0.5)],
                 id="barriers-mined-as-unknown-objects",
                 marks=pytest.mark.xfail(strict=True, reason="issue 18: measured unknown tube recall 0.00, frame "
                                         "recall 0.05 (0 of 7 barriers; the stereo proposer proposes 19 % of barrier "
                                         "detections, none beyond 20 m; 2026-12-02)")),
    pytest.param("verge", HALF, "tubes", [("evaluated", gt, 0), ("clutter_share", le, 0.25)],
                 id="verge-hedge-fence-grass-not-selected",
                 marks=pytest.mark.xfail(strict=True, reason="issue 18: measured clutter 29 % of the selected tubes "
                                         "(2 of 7; 74 % before the calibrated unary; 2026-12-02)")),
    pytest.param("parkedpair", HALF, "known", [("tracks", ge, 4), ("tube_recall", ge, 0.9)],
                 id="parkedpair-far-cars-each-one-tube",
                 marks=pytest.mark.xfail(strict=True, reason="issue 18: measured known tube recall 0.67 (4 of 6 "
                                         "parked cars at 35–55 m; frame recall 0.69; 2026-12-02)")),
    # full size: at half size the pieces are under the 100-pixel evaluation floor
    pytest.param("debris", None, "unknown", [("tracks", ge, 2), ("tube_recall", ge, 0.5)],
                 id="debris-seen-for-a-few-frames-is-mined",
                 marks=pytest.mark.xfail(strict=True, reason="issue 18: measured unknown tube recall 0.00, frame "
                                         "recall 0.00 (debris in view 5–8 frames is not mined; 2026-12-02)")),
]


@pytest.mark.parametrize("scenario, size, group, checks", TARGETS)
def test_scenario_meets_its_target(scenario: str, size: dict[str, int] | None, group: str,
                                   checks: list[tuple[str, Callable[[Any, Any], bool], float]]) -> None:
    r = _mine(scenario, 40, size)[group]
    for key, meets, bound in checks:
        assert meets(r[key], bound), f"{group} {key} = {r[key]}, target {meets.__name__} {bound}: {r}"
