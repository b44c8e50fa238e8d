"""Issue 11 item 3: a plain local `mine submit` keeps every Ray port on loopback.

The job runs as a real `mine submit` on a real local Ray; while it runs, the test lists
the TCP sockets in LISTEN state of every process of the job's session (the driver, GCS,
raylet, the dashboard and runtime-env agents, the workers) from /proc, and every one
must be bound to 127.0.0.1 or ::1 (or ::ffff:127.0.0.1). The infra files (cluster
launcher, KubeRay) may name 0.0.0.0 only beside a comment saying what protects it.
"""

from __future__ import annotations

import ipaddress
import os
import re
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from _jobs import TINY
from _run import Mine, session_pids
from conftest import REPO

pytest.importorskip("ray")


# -- listening sockets, from /proc ------------------------------------------------------

def _address(hex_addr: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address:
    """An address of /proc/net/tcp{,6}: 32-bit words in host (little-endian) order."""
    raw = bytes.fromhex(hex_addr)
    return ipaddress.ip_address(b"".join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4)))


def _name(pid: int) -> str:
    """The process name (``/proc/PID/comm``, at most 15 characters: gcs_server, raylet, ray::IDLE...)."""
    try:
        return Path(f"/proc/{pid}/comm").read_text().strip()
    except OSError:
        return "?"


def listening_sockets(pids: dict[int, str]) -> set[tuple[int, str, str, int]]:
    """TCP sockets in LISTEN state owned by ``pids``: (pid, process name, address, port)."""
    owner: dict[str, int] = {}
    for pid in pids:
        try:
            fds = os.listdir(f"/proc/{pid}/fd")
        except (FileNotFoundError, PermissionError, ProcessLookupError):
            continue
        for fd in fds:
            try:
                link = os.readlink(f"/proc/{pid}/fd/{fd}")
            except OSError:
                continue
            if link.startswith("socket:["):
                owner[link[len("socket:["):-1]] = pid
    out = set()
    for table in ("tcp", "tcp6"):
        for line in Path(f"/proc/net/{table}").read_text().splitlines()[1:]:
            f = line.split()
            local, state, inode = f[1], f[3], f[9]
            if state == "0A" and inode in owner:  # 0A: TCP_LISTEN
                host, port = local.split(":")
                pid = owner[inode]
                out.add((pid, _name(pid), str(_address(host)), int(port, 16)))
    return out


def is_loopback(address: str) -> bool:
    ip = ipaddress.ip_address(address)
    mapped = getattr(ip, "ipv4_mapped", None)  # ::ffff:127.0.0.1, an IPv6 socket bound to IPv4 loopback
    return ip.is_loopback or (mapped is not None and mapped.is_loopback)


# -- the tests ------------------------------------------------------------------------


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
    names = sorted(p.name for p in (REPO / "infra").glob("*.yaml"))
    assert {"ray-cluster.yaml", "rayjob.yaml", "rayjob-gpu.yaml", "networkpolicy.yaml"} <= set(names)
    for name in names:
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


def _refused_submit(capsys, tmp_path: Path, *args: str) -> str:
    """Standard error of a real ``mine submit`` (in this process) whose preflight refuses the
    job (a frame range past the 8-frame sequence's end), so that no Ray starts."""
    from _jobs import SYNTHETIC
    from _run import cli

    out = tmp_path / "out"
    rc, stdout, stderr = cli(capsys, "submit", *SYNTHETIC, *args, "--frames", "50:60", "--out", str(out),
                             "--workers", "1", "--no-progress")
    assert rc == 2 and "windows:" not in stdout, (rc, stdout, stderr)
    assert "Traceback" not in stderr, stderr
    return stderr


def _exposure_lines(stderr: str) -> list[str]:
    return [ln for ln in stderr.splitlines() if "unauthenticated" in ln]


def test_a_bind_to_every_interface_is_one_line_naming_it_and_where_it_came_from(tmp_path, capsys):
    job_file = tmp_path / "someone-elses.toml"
    job_file.write_text('[run]\nbind_host = "0.0.0.0"\n')
    cases = [(("--host", "0.0.0.0"), "0.0.0.0", "--host"),
             (("--host", "::"), "::", "--host"),
             (("--config", str(job_file)), "0.0.0.0", str(job_file)),
             (("--set", 'run.bind_host="::"'), "::", '--set run.bind_host="::"'),
             (("--config", str(job_file), "--host", "::"), "::", "--host")]
    for args, interface, origin in cases:
        lines = _exposure_lines(_refused_submit(capsys, tmp_path, *args))
        assert len(lines) == 1, (args, lines)
        line = lines[0]
        assert "every interface" in line and interface in line and origin in line and "Ray" in line, (args, line)
    # 127.0.0.1 (the default, or named) says nothing.
    for args in [(), ("--host", "127.0.0.1"), ("--set", 'run.bind_host="127.0.0.1"')]:
        assert not _exposure_lines(_refused_submit(capsys, tmp_path, *args)), args


# Ray keeps only 127.0.0.1 to itself: with any other node address its GCS, raylet, driver and
# workers listen on `::` (localray.py's docstring), and ::1 becomes 127.0.0.1.
@pytest.mark.parametrize("host", ["127.0.0.2", "::1", "192.168.7.7", "10.1.2.3", "localhost", "::ffff:127.0.0.1"])
def test_an_address_ray_would_widen_is_refused_before_anything_is_written(tmp_path, capsys, host):
    from _jobs import SYNTHETIC
    from _run import cli, clean_error

    for args, origin in [(("--host", host), "--host"), (("--set", f'run.bind_host="{host}"'), "--set")]:
        out = tmp_path / "out"
        rc, stdout, stderr = cli(capsys, "submit", *SYNTHETIC, *args, "--out", str(out), "--workers", "1",
                                 "--no-progress")
        assert rc == 2 and not stdout, (rc, stdout, stderr)
        line = clean_error(stderr)
        assert len(stderr.strip().splitlines()) == 1, stderr
        assert line.startswith("mine: error: ") and host in line and origin in line, line
        assert "127.0.0.1" in line and "0.0.0.0" in line, line  # what to use instead
        assert not _exposure_lines(stderr)
        assert not out.exists(), f"{host}: --out was made before the bind was refused"


# -- the viewer (issue 40): exactly the address given ---------------------------------------


def _ipv6_loopback() -> bool:
    try:
        with socket.socket(socket.AF_INET6) as s:
            s.bind(("::1", 0))
        return True
    except OSError:
        return False


@pytest.mark.parametrize("host", ["127.0.0.2", "::1"])
def test_the_viewer_listens_exactly_where_told(tmp_path, host):
    from mining.view.server import make_server

    if ":" in host and not _ipv6_loopback():
        pytest.skip("no IPv6 loopback here")
    (tmp_path / "cat").mkdir()
    server = make_server(tmp_path / "cat", host, 0, tmp_path / "cache")
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        bound, port = server.socket.getsockname()[:2]
        assert bound == host
        listening = {(a, p) for _, _, a, p in listening_sockets({os.getpid(): ""})}
        assert (host, port) in listening, listening
        # The address given answers; another loopback address on the same port does not.
        with socket.create_connection((host, port), timeout=10) as s:
            s.sendall(f"GET /static/gallery.js HTTP/1.1\r\nHost: {host if ':' not in host else f'[{host}]'}\r\n"
                      "Connection: close\r\n\r\n".encode())
            assert s.recv(64).startswith(b"HTTP/1.")
        with pytest.raises(ConnectionRefusedError):
            socket.create_connection(("127.0.0.1", port), timeout=10).close()
    finally:
        server.shutdown()
        server.server_close()
        server.app.browser.close()
        thread.join(5)


@pytest.mark.parametrize("host", ["localhost", "", "example.invalid", "127.0.0.1:8765", "[::1]"])
def test_the_viewer_refuses_a_host_that_is_not_an_address_before_opening_anything(tmp_path, host):
    from mining.errors import InputError
    from mining.view.server import make_server

    cache = tmp_path / "cache"
    with pytest.raises(InputError) as e:
        server = make_server(tmp_path / "nowhere", host, 0, cache)
        server.server_close()  # only before the fix: a name was resolved and listened on
    assert f"--host {host!r} is not an IP address" in str(e.value) and "\n" not in str(e.value)
    assert not cache.exists() and not (tmp_path / "nowhere").exists()


def test_the_viewer_says_so_when_it_listens_on_every_interface_and_refuses_a_name_in_one_line(tmp_path):
    from _run import env, mine_cmd

    proc = subprocess.run(mine_cmd("view", "--out", str(tmp_path / "cat"), "--host", "localhost", "--port", "0",
                                   "--cache", str(tmp_path / "cache")),
                          capture_output=True, text=True, env=env(), timeout=60)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and "--host 'localhost' is not an IP address" in proc.stderr
    (tmp_path / "cat").mkdir()
    proc = subprocess.Popen(mine_cmd("view", "--out", str(tmp_path / "cat"), "--host", "0.0.0.0", "--port", "0",
                                     "--cache", str(tmp_path / "cache")),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env())
    try:
        proc.stdout.readline()  # "serving …": the announcement follows it
        line = proc.stderr.readline()
    finally:
        proc.terminate()
        proc.wait(10)
    assert "every interface" in line and "--host 0.0.0.0" in line and "no login" in line, line
