"""Issue 11 item 3: a plain local `mine submit` keeps every Ray port on loopback.

The job runs as a real `mine submit` on a real local Ray; while it runs, the test lists
the TCP sockets in LISTEN state of every process of the job's session (the driver, GCS,
raylet, the dashboard and runtime-env agents, the workers) from /proc, and every one
must be bound to 127.0.0.1 or ::1 (or ::ffff:127.0.0.1). The infra files (cluster
launcher, KubeRay) may name 0.0.0.0 only beside a comment saying what protects it.
"""

from __future__ import annotations

import re
import sys
import time

import pytest
from _reliability_b import TINY, Mine, is_loopback, listening_sockets, session_pids
from conftest import REPO

pytest.importorskip("ray")


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads listening sockets from /proc (Linux)")
def test_a_local_submit_listens_on_loopback_only(tmp_path):
    job = Mine(tmp_path / "cat", *TINY, logs=tmp_path / "logs")
    seen: set[tuple[int, str, str, int]] = set()
    try:
        while job.proc.poll() is None:
            seen |= listening_sockets(session_pids(job.sid))
            time.sleep(0.2)
    finally:
        rc, stdout, stderr = job.finish()
    assert rc == 0, stdout + stderr
    processes = {name for _, name, _, _ in seen}
    # The listing saw Ray itself, not just the driver: its GCS, its raylet and its agents.
    assert {"gcs_server", "raylet"} <= processes, sorted(seen)
    assert len({pid for pid, *_ in seen}) >= 4, sorted(seen)
    exposed = sorted(s for s in seen if not is_loopback(s[2]))
    assert not exposed, "listening beyond loopback:\n" + "\n".join(map(str, exposed))


def test_infra_names_no_open_interface_without_saying_what_protects_it():
    for name in ("ray-cluster.yaml", "rayjob.yaml", "networkpolicy.yaml"):
        lines = (REPO / "infra" / name).read_text().splitlines()
        for i, line in enumerate(lines):
            if re.search(r"0\.0\.0\.0|\[::\]|[\"'=]::[\"']?(\s|$)", line) and not line.lstrip().startswith("#"):
                comment = " ".join(lines[max(0, i - 6):i + 1])
                assert "#" in comment and re.search(r"protect|NetworkPolicy|tunnel|port-forward", comment), \
                    f"infra/{name}:{i + 1} opens an interface without saying what protects it: {line.strip()}"
    head = (REPO / "infra" / "ray-cluster.yaml").read_text()
    assert "--dashboard-host=0.0.0.0" not in head
    assert re.search(r"--dashboard-host=127\.0\.0\.1", head)
    readme = (REPO / "infra" / "README.md").read_text()
    for how in ("ray dashboard", "kubectl port-forward", "NetworkPolicy"):
        assert how in readme, how
