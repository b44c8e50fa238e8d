"""How a test runs ``mine``: in this process (``cli``), or as a subprocess in a session of its own.

Every ``mine submit`` subprocess runs in a session of its own (``start_new_session``), so a
test can list, signal and finally SIGKILL exactly the processes that job started (the driver
and its local Ray), never another job's on a shared machine.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from conftest import REPO

JOB_TIMEOUT_S = 420  # a hung job fails its test, not the whole run (a loaded 2-core machine is slow)
SUMMARY = re.compile(r"windows: (\d+) ok, (\d+) failed, (\d+) already done \(of (\d+)\)")  # `mine submit`'s last line
ANSI = "\x1b["


def mine_cmd(*args: str) -> list[str]:
    """The command line of ``mine ARGS`` with this interpreter."""
    return [sys.executable, "-m", "mining.cli", *args]


def env() -> dict[str, str]:
    """The environment of a subprocess of this checkout's code: a fresh local Ray of its own."""
    e = dict(os.environ, RAY_USAGE_STATS_ENABLED="0", PYTHONPATH=str(REPO))
    e.pop("RAY_ADDRESS", None)  # always a fresh local Ray of the job's own
    e.pop("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", None)  # conftest's: `mine submit` must keep Ray on loopback itself
    e.pop("TUBE_MINER_OWN_PROCESS", None)  # a child pytest hands its own_process tests on (tests/_own_process.py)
    return e


# -- in this process ------------------------------------------------------------------------


def cli(capsys, *args: str) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of ``mine ARGS`` run in this process (``mining.cli.main``):
    for the cases that start no Ray, without an interpreter's start-up each."""
    from mining.cli import main

    capsys.readouterr()
    try:
        rc = main(list(args))
    except SystemExit as e:  # argparse's own errors
        rc = e.code
    out, err = capsys.readouterr()
    return rc, out, err


def command_parsers(parser=None) -> list[tuple[str, object]]:
    """(``"bench calibrate"``, its parser) of every ``mine`` command, found by walking
    ``cli.build_parser()`` (or ``parser``) with every group's commands loaded: a new command
    is covered by the tests that use this without a line of theirs."""
    import argparse

    from mining.cli import build_parser

    found = []

    def walk(p: argparse.ArgumentParser, words: tuple[str, ...]) -> None:
        subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs:
            found.append((" ".join(words), p))
        for a in subs:
            for name, sub in a.choices.items():
                if hasattr(sub, "load_command"):
                    sub.load_command()
                walk(sub, (*words, name))

    walk(parser if parser is not None else build_parser(), ())
    return found


def valued_options(parser) -> list:
    """The actions of ``parser`` that take a value (not --help, flags or --version)."""
    import argparse

    return [a for a in parser._actions if a.nargs != 0 and not isinstance(a, argparse._SubParsersAction)]


def cli_status(capsys, out: Path | str, *extra: str) -> tuple[int, str]:
    """(exit status, what it printed) of ``mine status --out OUT`` in this process."""
    rc, o, e = cli(capsys, "status", "--out", str(out), *extra)
    return rc, o + e


def clean_error(stderr: str) -> str:
    """The error line (``mine: error: …``, ``mine export: …``), the last of standard error;
    asserts there is no traceback."""
    assert "Traceback" not in stderr, stderr
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert lines, "no error message"
    return lines[-1]


# -- in a session of its own ----------------------------------------------------------------


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

    def running(self) -> dict[int, str]:
        """The live processes of the job: pid → command line."""
        return session_pids(self.sid)

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


def submit(out: Path, *args: str, logs: Path | None = None, workers: int = 2) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of a finished ``mine submit ARGS --out OUT``; its output is
    kept under ``logs`` when given."""
    if logs is not None:
        return Mine(out, *args, logs=logs, workers=workers).finish()
    with tempfile.TemporaryDirectory(prefix="mine-logs-") as tmp:
        return Mine(out, *args, logs=Path(tmp), workers=workers).finish()


def status(out: Path) -> tuple[int, str]:
    """(exit status, what it printed) of ``mine status --out OUT`` as a subprocess."""
    p = subprocess.run(mine_cmd("status", "--out", str(out)), cwd=REPO, env=env(), capture_output=True, text=True,
                       timeout=120)
    return p.returncode, p.stdout + p.stderr
