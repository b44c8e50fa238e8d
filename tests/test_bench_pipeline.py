"""The pipeline bench's measurements on a tiny synthetic job, on a real local Ray."""

from __future__ import annotations

import pytest

pytest.importorskip("ray")

from mining.bench.pipeline import bench_job, growth, measure_run  # noqa: E402
from mining.config import JobConfig  # noqa: E402

pytestmark = pytest.mark.slow  # the pipeline benchmark on 1 and 2 Ray workers


def test_measure_run_numbers_are_sane(tmp_path):
    cfg = bench_job(JobConfig(), n_frames=8, sequences=["0000"], core=4)
    cfg.window.context_before = cfg.window.context_after = 2
    runs = {n: measure_run(cfg, tmp_path / f"w{n}", n) for n in (1, 2)}
    for n, r in runs.items():
        assert r["windows"] == 2 and r["frames"] == 8
        assert r["fps"] > 0 and r["wall_s"] > 0
        assert 0 < r["step_s"] <= n * r["wall_s"]  # steps are timed inside the job's wall time
        assert r["overhead_s_per_window"] >= 0
        assert r["worker_processes"] == n  # one actor per worker, found by its parent raylet
        assert 50 * 2**20 < r["peak_rss_bytes"] < 2 * 2**30  # a Python + numpy + OpenCV process, under the target
        peaks = r["window_peak_rss_bytes"]
        assert len(peaks) == 2 and all(p is not None and 0 < p <= r["peak_rss_bytes"] for p in peaks)
    eff = runs[2]["fps"] / (2 * runs[1]["fps"])
    assert 0 < eff <= 1.5
    with pytest.raises(FileExistsError):
        measure_run(cfg, tmp_path / "w1", 1)  # a used catalogue would resume, not measure


def test_growth_flags_a_rising_series():
    flat = growth([100, 101, 99, 100, 100, 101, 100, 99])
    rising = growth([100, 110, 120, 130, 140, 150, 160, 170])
    assert abs(flat["ratio"] - 1.0) < 0.02 and abs(flat["slope_mb_per_100_windows"]) < 1e-3
    assert rising["ratio"] > 1.1 and rising["slope_mb_per_100_windows"] > 0
