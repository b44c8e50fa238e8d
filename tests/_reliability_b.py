"""Helpers of the reliability tests of issue 11 items 3 and 6: `mine` subprocesses and their sockets.

Every `mine submit` runs in a session of its own (``start_new_session``), so a test can
list, signal and finally SIGKILL exactly the processes that job started (the driver and
its local Ray), never another job's on a shared machine.
"""

from __future__ import annotations

import ipaddress
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from conftest import REPO

JOB_TIMEOUT_S = 420  # a hung job fails its test, not the whole run (a loaded 2-core machine is slow)
# A tiny synthetic job: 12 frames, two 6-frame windows (seconds of work once Ray is up).
TINY = ["--dataset", "synthetic", "--sequences", "0000", "--option", "n_frames=12", "--option", "width=320",
        "--option", "height=96", "--option", "fx=186.0", "--set", "window.core=6", "--set", "window.context_before=2",
        "--set", "window.context_after=2"]
TINY_WINDOWS = ["0000-0000000-0000006", "0000-0000006-0000012"]
ANSI = "\x1b["


def mine_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "mining.cli", *args]


def env() -> dict[str, str]:
    e = dict(os.environ, RAY_USAGE_STATS_ENABLED="0", PYTHONPATH=str(REPO))
    e.pop("RAY_ADDRESS", None)  # always a fresh local Ray of the job's own
    e.pop("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", None)  # conftest's: `mine submit` must keep Ray on loopback itself
    return e


def session_pids(sid: int) -> dict[int, str]:
    """Live processes of session ``sid``: pid → command line."""
    ps = subprocess.run(["ps", "-eo", "pid=,sid=,stat=,args="], capture_output=True, text=True, check=True).stdout
    out = {}
    for line in ps.splitlines():
        pid, s, stat, args = (line.split(None, 3) + [""])[:4]
        if int(s) == sid and int(pid) != os.getpid() and not stat.startswith("Z"):
            out[int(pid)] = args
    return out


def kill_session(sid: int) -> None:
    """SIGKILL every process of the session until none is left."""
    deadline = time.monotonic() + 20
    while pids := session_pids(sid):
        for pid in pids:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        assert time.monotonic() < deadline, f"processes of session {sid} survive SIGKILL: {pids}"
        time.sleep(0.2)


class Mine:
    """A `mine submit` in a session of its own; ``finish()`` waits, ``kill()`` ends every process of it."""

    def __init__(self, out: Path, *args: str, logs: Path, workers: int = 2):
        logs.mkdir(parents=True, exist_ok=True)
        self.stdout, self.stderr = open(logs / "stdout.txt", "w+"), open(logs / "stderr.txt", "w+")
        self.proc = subprocess.Popen(mine_cmd("submit", *args, "--out", str(out), "--workers", str(workers),
                                              "--no-progress"),
                                     cwd=REPO, env=env(), stdout=self.stdout, stderr=self.stderr,
                                     start_new_session=True)

    @property
    def sid(self) -> int:
        return self.proc.pid  # the session id is the driver's pid

    def finish(self, timeout: float = JOB_TIMEOUT_S) -> tuple[int, str, str]:
        try:
            rc = self.proc.wait(timeout)
        finally:
            self.kill()
        texts = []
        for f in (self.stdout, self.stderr):
            f.seek(0)
            texts.append(f.read())
            f.close()
        return rc, *texts

    def kill(self) -> None:
        kill_session(self.sid)
        self.proc.wait(10)


def submit(out: Path, *args: str, logs: Path) -> tuple[int, str, str]:
    return Mine(out, *args, logs=logs).finish()


def status(out: Path) -> tuple[int, str]:
    p = subprocess.run(mine_cmd("status", "--out", str(out)), cwd=REPO, env=env(), capture_output=True, text=True,
                       timeout=120)
    return p.returncode, p.stdout + p.stderr


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
