"""A job on a several-node Ray cluster (three raylets on this machine) survives losing a node.

The head holds no CPU, so every step runs on one of two 1-CPU worker nodes. While the
faulty run mines, one worker node is removed (its raylet and worker processes killed)
once the first window's manifest row exists: the job must still finish every window,
and its catalogue must equal a clean run's on the same cluster.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import pytest

ray = pytest.importorskip("ray")
from ray.cluster_utils import Cluster  # noqa: E402

from mining.bench.pipeline import worker_processes  # noqa: E402
from mining.catalog.views import connect  # noqa: E402
from mining.config import JobConfig  # noqa: E402
from mining.pipeline.executors import RayExecutor  # noqa: E402
from mining.pipeline.submit import mine_job  # noqa: E402

pytestmark = [pytest.mark.slow, pytest.mark.own_process]  # a three-node Ray cluster, in a process of its own

N_FRAMES = 20
JOB_TIMEOUT_S = 300  # a hung job (a step waiting for an actor that never restarts) fails here


def _job() -> JobConfig:
    cfg = JobConfig()
    cfg.source.dataset = "synthetic"
    cfg.source.sequences = ["0000"]
    cfg.source.options = {"n_frames": N_FRAMES}
    cfg.window.core, cfg.window.context_before, cfg.window.context_after = 5, 3, 3
    return cfg


@pytest.fixture
def cluster():
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    if ray.is_initialized():
        ray.shutdown()
    c = Cluster(initialize_head=True, head_node_args={"num_cpus": 0})
    try:
        workers = [c.add_node(num_cpus=1) for _ in range(2)]
        c.wait_for_nodes()
        ray.init(address=c.address, log_to_driver=False)
        yield c, workers
    finally:
        if ray.is_initialized():
            ray.shutdown()
        c.shutdown()


def _busy_actors(node) -> int:
    """How many of the pipeline's actors on this cluster node are running a step now."""
    raylet = node.all_processes["raylet"][0].process.pid
    titles = [Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")[0] for pid in worker_processes(raylet)]
    return sum(b".run" in t for t in titles)


def _catalogue(out: Path) -> tuple[list, list, list]:
    con = connect(out)
    try:
        tubes = con.sql("SELECT tube_id, selected FROM tubes ORDER BY tube_id").fetchall()
        frames = con.sql("SELECT tube_id, frame FROM tube_frames ORDER BY tube_id, frame").fetchall()
        windows = con.sql('SELECT "window", status, attempts FROM windows ORDER BY "window"').fetchall()
    finally:
        con.close()
    return tubes, frames, windows


def test_node_removed_mid_job_catalogue_complete(cluster, tmp_path):
    c, workers = cluster
    cfg = _job()
    n_windows = N_FRAMES // cfg.window.core

    clean = mine_job(cfg, str(tmp_path / "clean"), executor=RayExecutor)
    assert clean.ok == n_windows and not clean.failed

    out = tmp_path / "faulty"
    result: dict = {}

    def mine() -> None:
        try:
            result["summary"] = mine_job(cfg, str(out), executor=RayExecutor)
        except BaseException as e:  # noqa: BLE001 - handed to the test thread
            result["error"] = e

    t = threading.Thread(target=mine, daemon=True)
    t.start()
    t0 = time.perf_counter()
    while not list((out / "manifest").rglob("*.parquet")):
        assert t.is_alive(), f"job ended before any window was done: {result}"
        assert time.perf_counter() - t0 < JOB_TIMEOUT_S, "no window finished"
        time.sleep(0.2)
    while not (busy := [w for w in workers if _busy_actors(w)]):
        assert t.is_alive() and time.perf_counter() - t0 < JOB_TIMEOUT_S, "no actor busy on a worker node"
        time.sleep(0.05)
    c.remove_node(busy[0])  # mid-step: that step's actor must restart on the other node and redo it
    done_at_removal = len(list((out / "manifest").rglob("*.parquet")))
    t.join(JOB_TIMEOUT_S)
    assert not t.is_alive(), f"job did not finish within {JOB_TIMEOUT_S} s after losing a node"
    assert "error" not in result, result.get("error")
    summary = result["summary"]
    assert summary.ok == n_windows and not summary.failed, summary.lines()
    assert len(ray.nodes()) == 3 and sum(n["Alive"] for n in ray.nodes()) == 2, "the node was not removed"

    tubes, frames, windows = _catalogue(out)
    ref_tubes, ref_frames, ref_windows = _catalogue(tmp_path / "clean")
    assert [w for w, s, _ in windows if s == "done"] == [w for w, _, _ in ref_windows] and len(windows) == n_windows
    assert tubes, "the clean run mined no tubes: nothing to compare"
    assert tubes == ref_tubes  # same tube ids, same selected flags
    assert frames == ref_frames  # every (tube_id, frame) row, no duplicates, none missing
    assert len(set(frames)) == len(frames)
    assert done_at_removal < n_windows, "the node was removed after the job had finished its windows"
