"""Recording gaps (``SequencePlan.gaps``): no egomotion is estimated across one, and no tube
crosses one — on a RobotCar-layout recording of real KITTI frames with a chunk missing, and
on a synthetic sequence with frames dropped, mined as a windowed job."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from conftest import REPO, kitti_0005_stereo
from mining.config import load_config
from mining.pipeline.frames import frame_records
from mining.pipeline.mine import mine_tubes
from mining.pipeline.executors import LocalExecutor
from mining.pipeline.submit import mine_job
from mining.sources.oxford import OxfordSource
from mining.testing.fixtures import write_robotcar_fixture

N_FRAMES = 10  # KITTI 0005 frames 0-9, chunks of 2: chunk 3 (frames 4, 5) missing


@pytest.fixture(scope="module")
def robotcar_gap(kitti_tracking_root, tmp_path_factory):
    left, right, calib = kitti_0005_stereo(kitti_tracking_root, N_FRAMES)
    root = tmp_path_factory.mktemp("robotcar_gap")
    write_robotcar_fixture(root, left, right, calib, traversal="t", missing_chunks=(3,), list_missing=True)
    source = OxfordSource(root)
    return source, source.plan("t")


def _cfg(shared_data: Path):
    # The source's frame indices are the timestamp lines, i.e. the KITTI frame numbers, so the
    # shared 4D-GVT proposals of KITTI 0005 belong to these frames (parked cars on both sides).
    folder = shared_data / "proposals_4dgvt_format" / "kitti_tracking_0005" / "top20"
    return load_config(None, ['proposals.proposer="json"', f'proposals.json.folder="{folder}"'])


def test_robotcar_missing_chunk_no_egomotion_across_the_gap(robotcar_gap, shared_data):
    source, plan = robotcar_gap
    assert plan.frames == (0, 1, 2, 3, 6, 7, 8, 9) and plan.gaps == (4,)
    recs = list(frame_records(source, plan, 0, len(plan), _cfg(shared_data)))
    ego = [r.geometry.egomotion for r in recs]
    assert ego[0] is None and ego[4] is None  # nothing to match against: the frame before the gap is not "previous"
    assert recs[4].geometry.flow is None and recs[4].ground_age == 0
    assert all(e is not None and e.ok for i, e in enumerate(ego) if i not in (0, 4))
    assert [r.tracking.segment for r in recs] == [0, 0, 0, 0, 1, 1, 1, 1]
    # The control: had the plan not named the gap, frame 6 would have been matched to frame 3.
    blind = dataclasses.replace(plan, gaps=())
    recs_blind = list(frame_records(source, blind, 3, 5, _cfg(shared_data)))
    assert recs_blind[1].geometry.egomotion is not None


def test_robotcar_missing_chunk_no_tube_crosses_the_gap(robotcar_gap, shared_data):
    source, plan = robotcar_gap
    cfg = _cfg(shared_data)
    recs = list(frame_records(source, plan, 0, len(plan), cfg))
    mined = mine_tubes((r.tracking for r in recs), cfg)
    segment = {r.frame.index: r.tracking.segment for r in recs}
    sides = [{segment[f.frame] for f in m.tube.frames} for m in mined]
    assert {0} in sides and {1} in sides, "tubes are made on both sides of the gap"
    assert all(len(s) == 1 for s in sides), "no tube spans the gap"
    assert all(m.tube.segment == segment[m.tube.first_frame] for m in mined)


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_synthetic_forced_gap_in_a_windowed_job(tmp_path):
    """Frames 16-21 dropped; 8-frame windows (the gap falls inside a window core and in the
    warm-up and context of its neighbours)."""
    cfg = load_config(REPO / "jobs" / "synthetic.toml", [
        "source.options.n_frames=46", "source.options.width=621", "source.options.height=188",
        "source.options.fx=360.77", "source.options.drop_frames=[[16, 22]]",
        "window.core=8", "window.context_before=4", "window.context_after=4"])
    out = tmp_path / "catalog"
    summary = mine_job(cfg, str(out), executor=LocalExecutor)
    assert not summary.failed and summary.ok == 5
    frames = pq.read_table(out / "catalog" / "frames").to_pylist()
    frames.sort(key=lambda r: r["position"])
    at_gap = next(r for r in frames if r["frame"] == 22)
    assert at_gap["position"] == 16 and at_gap["egomotion_ok"] is None  # none estimated across the gap
    before = next(r for r in frames if r["frame"] == 15)
    assert at_gap["segment"] == before["segment"] + 1
    assert all(r["egomotion_ok"] for r in frames if r["frame"] not in (0, 22))
    segment = {r["frame"]: r["segment"] for r in frames}
    tf = pq.read_table(out / "catalog" / "tube_frames", columns=["tube_id", "frame"]).to_pylist()
    by_tube: dict[str, set[int]] = {}
    for r in tf:
        by_tube.setdefault(r["tube_id"], set()).add(segment[r["frame"]])
    assert len(by_tube) > 5
    assert all(len(s) == 1 for s in by_tube.values()), "no tube spans the gap"
    sides = {next(iter(s)) for s in by_tube.values()}
    assert sides == {segment[15], segment[22]}, "tubes are made on both sides"
    assert json.loads((out / "job.json").read_text())["params_hash"] == cfg.params_hash
