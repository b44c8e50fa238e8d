"""``mine bench scale``: the projection's arithmetic, and the command on a small synthetic source."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import pytest

from _run import env
from conftest import REPO
from mining.bench.scale import Cluster, project_hours


def test_the_projection_takes_the_slower_side():
    # 806,000 frames × 0.2 CPU-s over 64 cores at 90 %: 806000 · 0.2 / 57.6 / 3600 = 0.7774 h.
    p = project_hours(806_000, 0.2, 0.0, Cluster(64, 0, 0.9), None)
    assert p["cpu_hours"] == pytest.approx(806_000 * 0.2 / 57.6 / 3600) and p["gpu_hours"] == 0
    # Where GPUs run the model part (0.15 of 0.35 CPU-s), the CPUs keep 0.2; 4 GPUs at 50 frames/s
    # take 806000 / 200 / 3600 = 1.119 h: the GPU side is the slower, the job takes it.
    g = project_hours(806_000, 0.35, 0.15, Cluster(64, 4, 0.9), 50.0)
    assert g["cpu_s_per_frame"] == pytest.approx(0.2)
    assert g["gpu_hours"] == pytest.approx(806_000 / 200 / 3600) and g["hours"] == g["gpu_hours"]
    # A noisy end-to-end figure below the model part: the other stages' sum is the CPU side's floor.
    f = project_hours(806_000, 11.0, 11.1, Cluster(64, 4, 0.9), 50.0, rest_s_per_frame=0.3)
    assert f["cpu_s_per_frame"] == pytest.approx(0.3)
    # Without GPUs the model part stays on the CPUs.
    c = project_hours(806_000, 0.35, 0.15, Cluster(64, 0, 0.9), 50.0)
    assert c["cpu_s_per_frame"] == pytest.approx(0.35) and c["hours"] == c["cpu_hours"]


@pytest.mark.slow  # over ~1.5 s: the fast tier's 3-minute budget
def test_the_command_prints_every_stage_and_writes_its_chart_and_json(tmp_path):
    chart, out = tmp_path / "scale.png", tmp_path / "scale.json"
    p = subprocess.run([sys.executable, "-m", "mining.cli", "bench", "scale", "--option", "width=414",
                        "--option", "height=125", "--frames", "5", "--ray-frames", "0", "--cpus", "32", "--chart", str(chart),
                        "--json", str(out)], cwd=REPO, env=env(), capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    for stage in ("read", "geometry", "frame proposals", "localise", "tubes", "end to end", "Ray 2.58"):
        assert stage in p.stdout
    r = json.loads(out.read_text())
    stages = r["stage_cpu_s_per_frame"]
    assert set(stages) == {"read", "geometry", "frame proposals", "localise", "tubes", "tubes: context"}
    assert stages["tubes: context"] == pytest.approx(0.6 * stages["tubes"])  # 30 + 30 context frames a 100-frame core
    assert r["size"] == [125, 414] and r["end_to_end_cpu_s_per_frame"] > 0
    assert r["projection"]["hours"] == pytest.approx(
        806_000 * r["end_to_end_cpu_s_per_frame"] / (32 * 0.9) / 3600)
    img = cv2.imread(str(chart))
    assert img is not None and img.shape[0] > 300 and img.shape[1] > 500
    assert (img < 128).any(axis=2).mean() > 0.005  # lines and text drawn, not a blank canvas
    again = subprocess.run([sys.executable, "-m", "mining.cli", "bench", "scale", "--no-job", "--chart", str(chart)],
                           cwd=REPO, env=env(), capture_output=True, text=True, timeout=60)
    assert again.returncode == 2 and "exists" in again.stderr  # an existing file is refused before any work


@pytest.mark.slow  # a job on a local Ray
def test_the_ray_job_reports_the_object_store_worker_memory_and_the_gpu_busy_share(tmp_path, fastsam_model):
    out = tmp_path / "scale.json"
    model = ["--set", "proposals.proposer='fastsam+stereo'", "--set", f"proposals.fastsam.model_path='{fastsam_model}'",
             "--set", "proposals.fastsam.input_height=64", "--set", "proposals.fastsam.input_width=64"]
    p = subprocess.run([sys.executable, "-m", "mining.cli", "bench", "scale", "--option", "width=414",
                        "--option", "height=125", "--frames", "4", "--no-job", "--ray-frames", "30", "--ray-gpus", "2",
                        *model, "--json", str(out)], cwd=REPO, env=env(), capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    r = json.loads(out.read_text())["ray_job"]
    assert r["frames"] == 30 and r["object_store_samples"] > 0 and r["peak_rss_bytes"] > 100 * 2**20
    assert "object store peak" in p.stdout and "worker peak memory" in p.stdout
    # Two logical GPUs: the proposal stage ran there, and its busy share from the first second is said.
    assert len(r["placement"]["proposal_actors"]) == 2
    assert 0 < r["stage_busy"]["share"] <= 1 and "busy" in p.stdout and "% of the mining time" in p.stdout
