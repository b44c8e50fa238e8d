"""`mine bench memory`: its slope recovers a planted growth, and a short real job (local Ray,
the whole `mine submit` job) gives one sample per window for every role."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mining.bench.memory import memory_job, slope_per_1k
from mining.config import JobConfig


def test_slope_recovers_a_planted_growth_and_leaves_out_the_first_window():
    frames = np.arange(100, 5001, 100)
    grow = 300 + 2.5 * frames / 1000  # 2.5 MB per 1,000 frames
    grow[0] = 50  # the first window (start-up) is not part of the trend
    assert slope_per_1k(frames, grow) == pytest.approx(2.5)
    flat = 300 + np.random.default_rng(0).normal(0, 0.5, len(frames))
    assert abs(slope_per_1k(frames, flat)) < 0.5
    assert slope_per_1k(frames, grow, skip=0) > 2.5  # with the first window, the start-up bends the line
    assert math.isnan(slope_per_1k([100, 200], [1.0, 2.0]))  # one sample after the first: no line


def test_memory_job_is_one_sequence_of_n_frames_at_the_cheap_size():
    cfg = JobConfig()
    cfg.source.sequences = ["0003", "0004"]
    job = memory_job(cfg, 57_600)
    assert job.source.sequences == ["0003"]
    assert job.source.options["n_frames"] == 57_600 and job.source.options["width"] == 414
    assert cfg.source.sequences == ["0003", "0004"]  # the caller's config is left as it was


@pytest.mark.slow  # a 300-frame job on a local Ray
@pytest.mark.own_process
def test_a_short_job_gives_every_role_a_sample_per_window(tmp_path):
    pytest.importorskip("ray")
    from mining.bench.memory import measure_memory, report

    r = measure_memory(memory_job(JobConfig(), 300), 300, tmp_path / "out", workers=2)
    assert r["frames"] == 300 and r["windows"] == 3 and r["tubes"] > 0
    roles = r["roles"]
    assert {"driver", "workers", "ray_raylet", "ray_gcs_server", "object_store"} <= set(roles)
    assert roles["workers"]["processes"] == 2 and roles["driver"]["processes"] == 1
    assert not r["object_store_error"]
    for role, v in roles.items():
        frames = [f for f, _ in v["samples"]]
        assert frames == [100, 200, 300, 300], role  # each window's track step, then the stitch
        assert math.isfinite(v["slope_mb_per_1k_frames"]), role
        if role != "object_store":
            assert v["peak_mb"] > 10 and v["peak_hwm_mb"] > 10, role  # a live process, not a zero read
    # A Python process with numpy and OpenCV holds well over 50 MB; the sum of two, more.
    assert roles["workers"]["peak_mb"] > 100
    assert 50 < r["stitch_peak_mb"] <= roles["workers"]["peak_hwm_mb"]  # reset as the stitch began, then its own
    assert isinstance(report(r), bool)
