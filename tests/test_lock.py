"""One writer per catalogue (issue 11, item 4): the lock a ``mine submit`` holds on its ``--out``.

* two ``mine submit`` processes on one ``--out``: the second is refused at once, naming the
  holder (pid, host, start time); with ``--lock-wait`` it waits, then resumes the finished
  job (nothing left to do) — no work is done twice, no race on ``job.json``;
* a lock left by a killed process is taken over, saying whose it was;
* in this process: a held lock refuses, ``lock_wait`` waits for its release;
* the ``O_EXCL`` fallback (filesystems without ``flock``): a dead holder on this host is
  taken over, a live one or one on another host refuses.
"""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from mining.catalog.lock import LockedError, OutputLock, read_holder
from mining.catalog.store import Store
from _jobs import CLI_SMALL, copy_of, mine, tables
from _run import JOB_TIMEOUT_S, SUMMARY, Mine, env, status
from conftest import REPO


def _submit(out: Path, *extra: str, logs: Path) -> Mine:
    return Mine(out, *CLI_SMALL, "--frames", "0:16", *extra, logs=logs, workers=1)


@pytest.mark.slow  # two `mine submit` processes, one on a local Ray
def test_a_second_submit_on_one_out_is_refused_naming_the_holder_or_waits(tmp_path):
    out = tmp_path / "out"
    first = _submit(out, logs=tmp_path / "first")
    deadline = time.monotonic() + JOB_TIMEOUT_S
    while not read_holder(Store(out)):
        assert first.proc.poll() is None, (tmp_path / "first" / "stderr.txt").read_text()
        assert time.monotonic() < deadline
        time.sleep(0.05)
    holder = read_holder(Store(out))
    assert holder["pid"] == first.proc.pid and holder["host"] == socket.gethostname()

    rc, stdout, err = _submit(out, logs=tmp_path / "second").finish()
    assert rc == 2, stdout + err
    assert (f"is being written by pid {first.proc.pid} on host {socket.gethostname()} since {holder['started']}"
            in err), err
    assert "--lock-wait" in err and "Traceback" not in err
    assert first.proc.poll() is None, "the first job ended before the second was refused: the test proved nothing"
    _, shown = status(out)
    assert f"being written now by pid {first.proc.pid} on host" in shown, shown

    waiting = _submit(out, "--lock-wait", str(JOB_TIMEOUT_S), logs=tmp_path / "waiting")
    rc1, stdout1, err1 = first.finish()
    rc2, stdout2, err2 = waiting.finish()
    assert rc1 == 0, stdout1 + err1
    assert SUMMARY.search(stdout1).groups() == ("2", "0", "0", "2"), stdout1
    assert rc2 == 0, stdout2 + err2
    assert SUMMARY.search(stdout2).groups() == ("0", "0", "2", "2"), stdout2  # it waited, then found it all done
    assert len(tables(out)["frames"]) == 16
    assert read_holder(Store(out)) == {}, "a finished submit left its name in the lock"


@pytest.mark.slow  # a process that takes the lock and is killed
def test_a_stale_lock_of_a_killed_process_is_taken_over(base_catalogue, tmp_path, capsys):
    out = copy_of(base_catalogue, tmp_path / "out")
    code = ("import sys, time; from mining.catalog.lock import OutputLock; from mining.catalog.store import Store; "
            "OutputLock(Store(sys.argv[1])).acquire(); print('held', flush=True); time.sleep(600)")
    holder = subprocess.Popen([sys.executable, "-c", code, str(out)], cwd=REPO, env=env(), stdout=subprocess.PIPE,
                              text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(LockedError, match=f"pid {holder.pid} on host {re.escape(socket.gethostname())}"):
            mine(out)
    finally:
        holder.kill()
        holder.wait(10)
    assert read_holder(Store(out))["pid"] == holder.pid  # the killed process's name is still in the file
    s = mine(out)
    assert s.skipped == 2 and not s.failed
    err = capsys.readouterr().err
    assert f"taking over a stale lock of pid {holder.pid} on host {socket.gethostname()}" in err, err


@pytest.mark.slow  # over ~1.5 s: the fast tier's 3-minute budget
def test_a_held_lock_refuses_and_lock_wait_waits_for_its_release(base_catalogue, tmp_path):
    out = copy_of(base_catalogue, tmp_path / "out")
    lock = OutputLock(Store(out)).acquire()
    try:
        with pytest.raises(LockedError, match=f"is being written by pid {os.getpid()} .* after waiting 1 s"):
            mine(out, lock_wait=1)
        threading.Timer(1.0, lock.release).start()
        t0 = time.monotonic()
        s = mine(out, lock_wait=60)
        assert time.monotonic() - t0 >= 0.9 and s.skipped == 2
    finally:
        lock.release()


def _dead_pid() -> int:
    p = subprocess.Popen(["true"])
    p.wait()
    return p.pid


def test_the_exclusive_file_fallback_takes_over_only_a_dead_holder_of_this_host(tmp_path, capsys):
    store = Store(tmp_path / "out")
    (tmp_path / "out").mkdir()
    excl = Path(store.full(".mine.lock.excl"))

    def plant(pid: int, host: str) -> None:
        excl.write_text(json.dumps({"pid": pid, "host": host, "started": "2025-01-01T00:00:00+00:00"}))

    plant(os.getpid(), socket.gethostname())  # alive
    with pytest.raises(LockedError, match=f"pid {os.getpid()}"):
        OutputLock(store)._acquire_excl(time.monotonic())
    plant(_dead_pid(), "elsewhere.example")  # on another host: cannot be checked from here
    with pytest.raises(LockedError, match=r"another host .* remove .*\.mine\.lock\.excl"):
        OutputLock(store)._acquire_excl(time.monotonic())
    dead = _dead_pid()
    plant(dead, socket.gethostname())
    lock = OutputLock(store)._acquire_excl(time.monotonic())
    try:
        assert lock.took_over["pid"] == dead
        assert f"taking over a stale lock of pid {dead}" in capsys.readouterr().err
        assert json.loads(excl.read_text())["pid"] == os.getpid()
    finally:
        lock.release()
    assert not excl.exists()
