"""Results do not depend on sharding (issue 4): 100-frame windows vs one window over them all.

The sharded job runs on a real local Ray. The unsharded reference re-uses the sharded
job's observations (geometry, proposals and localisation are per-frame functions: the
first test checks that a window's observations equal an unsharded run's), so the test
pays for the frames' geometry once. 300 frames (three windows, two borders, one window with
neighbours on both sides) hold every case 500 did at 60 % of the cost. (Egomotion is equal to ~1e-5: the motion
prediction that guides matching reaches back further than the two warm-up frames.)
"""

from __future__ import annotations

import numpy as np
import pytest
import ray
from conftest import REPO

from mining.catalog.layout import cache_path
from mining.catalog.store import Store
from mining.catalog.views import connect
from mining.config import load_config
from mining.pipeline.cache import decode_frames, encode_frames
from mining.pipeline.executors import LocalExecutor, RayExecutor
from mining.catalog.lock import OutputLock
from mining.pipeline.submit import mine_job, open_job
from mining.pipeline.window import observe_window
from mining.sources.synthetic import SyntheticSource
from mining.testing.sharding import AGREE_IOU, selected_tube_masks, tube_agreement
from mining.types import Window

pytestmark = pytest.mark.slow  # 300 frames at full resolution on a local Ray

N_FRAMES = 200  # two 100-frame windows: one border to cross


def test_observations_do_not_depend_on_the_window():
    cfg = load_config(REPO / "jobs" / "synthetic.toml")
    src = SyntheticSource(n_frames=12)
    plan = src.plan("0001")
    whole = observe_window(src, plan, Window("synthetic", "0001", (0, 12), (0, 12)), cfg)
    late = observe_window(src, plan, Window("synthetic", "0001", (7, 12), (7, 12)), cfg)
    assert [f.position for f in late] == list(range(7, 12))
    for a, b in zip(whole[7:], late):
        assert a.index == b.index and a.egomotion_ok == b.egomotion_ok
        # The motion prediction that guides matching reaches back further than the warm-up:
        # the estimate may differ in the last digits, never more.
        np.testing.assert_allclose(a.T_cur_prev, b.T_cur_prev, atol=1e-3)
        assert [r["counts"] for r in a.observations.proposals.rles] == [r["counts"] for r in b.observations.proposals.rles]
        np.testing.assert_array_equal(a.observations.position, b.observations.position)
    assert sum(len(f.observations) for f in late) > 0


@pytest.fixture(scope="module")
def local_ray():
    # Only in the test's own process (the marker below): the pytest process never starts Ray.
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


@pytest.mark.own_process
def test_100_frame_windows_give_the_tubes_of_one_window_over_all(local_ray, tmp_path):
    cfg = load_config(REPO / "jobs" / "synthetic.toml")
    assert cfg.window.core == 100
    sharded = str(tmp_path / "sharded")
    summary = mine_job(cfg, sharded, ["0000"], (0, N_FRAMES), executor=RayExecutor, keep_cache=True)
    assert summary.ok == N_FRAMES // 100 and not summary.failed

    # The reference: one window over all the frames, from the same observations.
    whole = str(tmp_path / "whole")
    frames = []
    for rel in Store(sharded).list("_cache/obs", ".npz.zst"):
        frames += decode_frames(Store(sharded).read_bytes(rel), rel)
    frames.sort(key=lambda f: f.position)
    assert [f.position for f in frames] == list(range(N_FRAMES))
    ref_cfg = load_config(REPO / "jobs" / "synthetic.toml", [f"window.core={N_FRAMES}"])
    # The job is recorded first: a folder holding an observation cache but no job.json is
    # refused (whose observations would they be?); a recorded job resumes from its cache.
    with OutputLock(Store(whole)):
        open_job(ref_cfg, whole, ["0000"], (0, N_FRAMES))
    window = Window("synthetic", "0000", (0, N_FRAMES), (0, N_FRAMES))
    Store(whole).write_bytes(cache_path(window), encode_frames(frames))
    assert mine_job(ref_cfg, whole, ["0000"], (0, N_FRAMES), executor=LocalExecutor).ok == 1

    agreement = tube_agreement(selected_tube_masks(whole), selected_tube_masks(sharded))
    print(f"selected tubes: unsharded {agreement.n_reference}, sharded {agreement.n_other}, "
          f"agreeing at mean mask IoU >= {AGREE_IOU}: {agreement.fraction:.3f}")
    assert agreement.n_reference >= 20  # enough tubes that the 0.95 agreement below means something (one tube in 20)
    assert agreement.fraction >= 0.95

    con = connect(sharded)
    crossing = con.execute("SELECT count(*) FROM tubes WHERE n_windows > 1 AND selected").fetchone()[0]
    assert crossing > 0  # tubes that cross a border are stitched into one
    assert con.execute("SELECT count(*) - count(DISTINCT tube_id) FROM tubes").fetchone()[0] == 0
    assert con.execute("SELECT count(*) - count(DISTINCT (tube_id, frame)) FROM tube_frames").fetchone()[0] == 0
    assert con.execute("SELECT count(*) FROM frames").fetchone()[0] == N_FRAMES
