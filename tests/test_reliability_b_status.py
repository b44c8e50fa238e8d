"""Issue 11 item 6: what `mine status` calls running and pending (no Ray: the markers a driver writes).

A window is running while a live driver holds its marker (``mining/pipeline/running.py``);
a marker whose driver process is gone (a driver killed with SIGKILL leaves it behind)
makes the window pending again. Markers of another job's params are ignored.
"""

from __future__ import annotations

import os
import subprocess
import sys

from conftest import REPO

from mining.catalog.layout import JobRecord
from mining.catalog.store import Store
from mining.config import load_config
from mining.pipeline.executors import LocalExecutor
from mining.pipeline.running import RunningMarkers
from mining.pipeline.status import job_status, print_status
from mining.pipeline.submit import mine_job
from mining.types import Window


def _cfg():
    return load_config(REPO / "jobs" / "synthetic.toml", [
        "source.options.n_frames=12", "source.options.width=320", "source.options.height=96",
        "source.options.fx=186.0", "window.core=6", "window.context_before=2", "window.context_after=2"])


def test_running_needs_a_live_driver(tmp_path, capsys):
    out = str(tmp_path / "cat")
    mine_job(_cfg(), out, executor=LocalExecutor)
    assert not list((tmp_path / "cat").glob("_running/**/*.json")), "a finished run leaves no marker"
    store = Store(out)
    job = JobRecord.load(store)
    later = [Window("synthetic", "0000", (12, 18), (10, 20)), Window("synthetic", "0000", (18, 24), (16, 24))]
    job.windows += later
    job.save(store)

    live = RunningMarkers(store, job.run_id, job.params_hash)  # this process: alive
    live.mark(later[0], "track")
    # A driver that marked a window and died without clearing it (as SIGKILL leaves it).
    subprocess.run([sys.executable, "-c", "import sys; from mining.catalog.store import Store; "
                    "from mining.pipeline.running import RunningMarkers; from mining.types import Window; "
                    "RunningMarkers(Store(sys.argv[1]), sys.argv[2], sys.argv[3])"
                    ".mark(Window('synthetic', '0000', (18, 24), (16, 24)), 'observe')", out, job.run_id,
                    job.params_hash], check=True, cwd=REPO, env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert (tmp_path / "cat" / "_running" / "dataset=synthetic" / "sequence=0000" / f"{later[1].name}.json").exists()

    rows = {r.window: r for r in job_status(out)}
    assert rows[later[0].name].status == "running" and "track step, driver pid" in rows[later[0].name].running
    assert rows[later[1].name].status == "pending"
    assert print_status(out) == 0
    shown = capsys.readouterr().out
    assert "4 windows: 2 done, 0 failed, 1 pending, 1 running" in shown
    assert f"running  synthetic/{later[0].name}  attempts 0  track step, driver pid " in shown

    other = RunningMarkers(store, "other-run", "0" * 16)  # another job's params: not this job's window
    other.mark(later[1], "track")
    assert {r.window: r.status for r in job_status(out)}[later[1].name] == "pending"
    live.clear_all()
    assert {r.window: r.status for r in job_status(out)}[later[0].name] == "pending"
