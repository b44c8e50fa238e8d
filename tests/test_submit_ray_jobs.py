"""``mine submit --address http://HOST:PORT`` through Ray Jobs, against a real head.

A head with a dashboard (the Ray Jobs server) is started here by ``ray start --head`` in
a process group of its own, with ports and a temporary folder of its own, so that other
Rays on the machine are left alone; the group is killed at the end. ``mine`` is run as a
command from a working folder with a *relative* ``--out``: the job runs in Ray's working
folder, so the path must travel resolved. Both jobs (one that mines, one that fails on
the cluster) run side by side to keep the test short.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import pytest

from mining.catalog.views import connect

pytestmark = pytest.mark.slow  # a Ray head with a dashboard, jobs through Ray Jobs

BIN = Path(sys.executable).parent  # the venv's bin: ``ray`` and ``mine`` (the job's entrypoint) live here
START_TIMEOUT_S = 180  # a loaded 2-core machine takes about a minute to bring a head up
JOB_TIMEOUT_S = 300
N_FRAMES, CORE, CONTEXT = 20, 10, 5


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _kill_group(pgid: int) -> None:
    """End the head's process group (and only it): TERM, then KILL what is left."""
    for sig, grace in ((signal.SIGTERM, 3.0), (signal.SIGKILL, 0.0)):
        try:
            os.killpg(pgid, sig)
        except ProcessLookupError:
            return
        t_end = time.monotonic() + grace
        while time.monotonic() < t_end:
            try:
                os.killpg(pgid, 0)
            except ProcessLookupError:
                return
            time.sleep(0.2)


@pytest.fixture(scope="module")
def head():
    """(dashboard address, environment) of a fresh one-node Ray cluster with 2 CPUs."""
    assert (BIN / "ray").exists() and (BIN / "mine").exists(), f"ray and mine must be installed in {BIN}"
    try:
        import aiohttp  # noqa: F401 - the dashboard (Ray Jobs server) needs ray[default]
    except ImportError:
        pytest.fail("the Ray Jobs server needs ray[default]: scripts/setup.sh test (the test extra has it)")
    temp = tempfile.mkdtemp(prefix="rj", dir="/tmp")  # short: Ray's socket paths live under it
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    env.update(PATH=f"{BIN}{os.pathsep}{env.get('PATH', '')}", RAY_USAGE_STATS_ENABLED="0",
               # the dashboard gives its modules 30 s to start: too little on a loaded machine
               RAY_DASHBOARD_SUBPROCESS_MODULE_WAIT_READY_TIMEOUT="120")
    dash = _free_port()
    ports = {"--port": _free_port(), "--dashboard-port": dash, "--ray-client-server-port": _free_port(),
             "--dashboard-agent-listen-port": _free_port(), "--dashboard-agent-grpc-port": _free_port(),
             "--runtime-env-agent-port": _free_port(), "--metrics-export-port": _free_port()}
    cmd = [str(BIN / "ray"), "start", "--head", "--node-ip-address", "127.0.0.1", "--dashboard-host", "127.0.0.1",
           "--num-cpus", "2", "--temp-dir", temp, "--disable-usage-stats"]
    cmd += [str(x) for kv in ports.items() for x in kv]
    log = open(Path(temp) / "ray_start.log", "w+")
    proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    address = f"http://127.0.0.1:{dash}"
    try:
        rc = proc.wait(timeout=START_TIMEOUT_S)
        log.seek(0)
        assert rc == 0, f"ray start failed:\n{log.read()[-3000:]}"
        t_end = time.monotonic() + 60
        while True:  # ray start returns once the dashboard is up; the Jobs API may lag a moment
            try:
                with urllib.request.urlopen(f"{address}/api/version", timeout=5) as r:
                    if r.status == 200:
                        break
            except OSError:
                if time.monotonic() > t_end:
                    raise
            time.sleep(0.5)
        yield address, env
    finally:
        if proc.poll() is None:
            proc.kill()
        _kill_group(proc.pid)  # ray start's daemons stay in its group after it returns
        log.close()
        shutil.rmtree(temp, ignore_errors=True)


@pytest.fixture(scope="module")
def jobs(head, tmp_path_factory):
    """Both submissions, run side by side: {name: (workdir, exit status, stdout, stderr)}."""
    address, env = head
    common = ["--address", address, "--out", "catalog"]
    argv = {
        "mine": ["--dataset", "synthetic", "--sequences", "0000", "--option", f"n_frames={N_FRAMES}",
                 "--set", f"window.core={CORE}", "--set", f"window.context_before={CONTEXT}",
                 "--set", f"window.context_after={CONTEXT}"],
        # loads as a config here; the source is opened only on the cluster, where it fails
        "fail": ["--dataset", "kitti", "--root", "no-such-root", "--sequences", "0000"],
    }
    started = {}
    for name, args in argv.items():
        work = tmp_path_factory.mktemp(name)
        p = subprocess.Popen([str(BIN / "mine"), "submit", *args, *common], cwd=work, env=env,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        started[name] = (work, p)
    out = {}
    try:
        for name, (work, p) in started.items():
            stdout, stderr = p.communicate(timeout=JOB_TIMEOUT_S)
            out[name] = (work, p.returncode, stdout, stderr)
    finally:
        for _, p in started.values():
            if p.poll() is None:
                p.kill()
    return out


def test_submit_runs_on_the_cluster_and_writes_the_catalogue(jobs):
    work, rc, stdout, stderr = jobs["mine"]
    assert rc == 0, f"stdout:\n{stdout}\nstderr:\n{stderr}"
    assert "submitted Ray job" in stderr
    # the job's own logs came back: Ray's job manager line, then mine's summary
    assert "Running entrypoint for job" in stdout
    assert f"--out {work / 'catalog'}" in stdout  # the relative --out travelled resolved
    n_windows = N_FRAMES // CORE
    assert f"windows: {n_windows} ok, 0 failed" in stdout
    selected = int(re.search(r"tubes written this run: (\d+) selected", stdout).group(1))
    assert selected > 0

    con = connect(work / "catalog")  # written where the command line meant, not in Ray's folder
    try:
        windows = con.sql('SELECT "window", status FROM windows ORDER BY "window"').fetchall()
        n_tubes = con.sql("SELECT count(*) FROM tubes WHERE selected").fetchone()[0]
        n_rows = con.sql("SELECT count(*) FROM tube_frames").fetchone()[0]
    finally:
        con.close()
    assert len(windows) == n_windows and all(s == "done" for _, s in windows)
    assert n_tubes == selected
    assert n_rows >= n_tubes


def test_failed_job_fails_the_command(jobs):
    work, rc, stdout, stderr = jobs["fail"]
    assert rc == 2, f"expected mine's error status from the cluster; stdout:\n{stdout}\nstderr:\n{stderr}"
    assert "Running entrypoint for job" in stdout  # it failed on the cluster, not here
    assert "mine: error:" in stdout  # the driver's error, from the job's logs
    assert str(work / "no-such-root") in stdout  # resolved on the submitting side
    assert "FAILED" in stderr
    assert not (work / "catalog").exists()


def test_no_wait_returns_the_submission_id_and_status_follows_it(head, jobs, tmp_path):
    """--no-wait hands the job over and returns; `mine status --address` lists it and, with
    --job, shows it finishing (the catalogue is written as with a followed job)."""
    address, env = head
    args = ["--dataset", "synthetic", "--sequences", "0000", "--option", "n_frames=6", "--set", "window.core=6",
            "--set", "window.context_before=0", "--set", "window.context_after=0"]
    r = subprocess.run([str(BIN / "mine"), "submit", *args, "--address", address, "--out", "catalog", "--no-wait"],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    job_id = r.stdout.strip().splitlines()[-1]
    assert job_id and "follow it with: mine status --address" in r.stderr
    listed = subprocess.run([str(BIN / "mine"), "status", "--address", address], env=env, capture_output=True,
                            text=True, timeout=60)
    assert job_id in listed.stdout and "Tube Miner job(s)" in listed.stdout
    t_end = time.monotonic() + JOB_TIMEOUT_S
    while True:
        one = subprocess.run([str(BIN / "mine"), "status", "--address", address, "--job", job_id], env=env,
                             capture_output=True, text=True, timeout=60)
        if "SUCCEEDED" in one.stdout.splitlines()[0] or time.monotonic() > t_end:
            break
        time.sleep(2)
    assert one.returncode == 0 and one.stdout.startswith(f"{job_id}: SUCCEEDED"), one.stdout
    assert "--no-wait" not in one.stdout.splitlines()[0]  # the driver on the cluster follows nothing
    assert (tmp_path / "catalog" / "job.json").exists()
