"""One writer per catalogue: the lock a ``mine submit`` holds on its ``--out`` while it writes.

Everything that writes a catalogue — planning and ``job.json``, the windows' steps,
stitching, repair, ``--new-run`` — runs under one ``mine submit`` driver, and the driver
holds this lock from before it reads ``job.json`` until its last result is in. A second
submit on the same ``--out`` waits up to ``wait_s`` seconds (``--lock-wait``) and is then
refused, naming the holder (pid, host, start time, command).

How, on a local folder: ``OUT/.mine.lock`` is opened (created if absent) and locked with
``fcntl.flock``; the kernel releases the lock when its process ends, however it ends, so
a dead holder never blocks anyone. The file's content names the holder; a holder that
ends cleanly empties it, so a lock taken over a file that still names someone is a
*stale* lock (its process was killed): that is said, with the old holder, and the lock
is taken. Where the filesystem refuses ``flock`` (some network mounts), the lock falls
back to creating ``OUT/.mine.lock.excl`` with ``O_CREAT | O_EXCL``; a leftover of a dead
process on this host (its pid gone) is taken over with a message, one of another host
must be removed by hand (the message says so).

The lock file is opened with ``O_NOFOLLOW`` and must be a plain file with one name: a
link planted at ``OUT/.mine.lock`` (or a hard link to a file elsewhere) is refused, naming
it, instead of being "taken over" and emptied (``safe_files.py``: no write follows a link).

Other pyarrow filesystems (``s3://``, ``gs://``…) have no atomic create-if-absent that
pyarrow exposes, so the lock is taken on this machine only, on a file in the system
temporary folder named by the URI's hash: two submits from one machine are serialised,
two machines writing one bucket prefix are not. Run one driver per prefix (a cluster's
Ray Jobs all run their drivers on its head node).
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
import socket
import stat
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

from mining.catalog.layout import LOCK
from mining.catalog.safe_files import link_error, write_error
from mining.catalog.store import Store
from mining.errors import InputError, MiningError

POLL_S = 0.5  # ours: how often a waiting submit tries the lock again


class LockedError(MiningError):
    """The catalogue is being written by another process."""


def _holder() -> dict:
    return {"pid": os.getpid(), "host": socket.gethostname(),
            "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "command": " ".join(sys.argv)[:500]}


def describe(holder: dict) -> str:
    """``pid 12 on host h since 2025-01-01T00:00:00+00:00 (mine submit …)``."""
    if not holder:
        return "another process (it has not written its name yet)"
    if "pid" not in holder:  # not a holder's record (a damaged lock file): say what it held
        return f"an unknown holder (the lock file held {holder.get('unreadable', holder)!r})"
    text = f"pid {holder.get('pid')} on host {holder.get('host')} since {holder.get('started')}"
    return text + (f" ({holder['command']})" if holder.get("command") else "")


def _parse(data: bytes) -> dict:
    try:
        d = json.loads(data.decode() or "{}")
        return d if isinstance(d, dict) else {"unreadable": data[:80].decode(errors="replace")}
    except (ValueError, RecursionError):  # RecursionError: nested past the parser
        return {"unreadable": data[:80].decode(errors="replace")}


def _pid_alive(pid: object) -> bool:
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except (PermissionError, TypeError, ValueError):
        return True  # someone else's live process, or no pid to check: assume alive
    return True


def lock_file(store: Store) -> Path:
    """Where ``store``'s lock lives: in the folder, or (other filesystems) in this machine's temporary folder."""
    if store.local:
        return Path(store.full(LOCK))
    digest = hashlib.sha256(store.uri.encode()).hexdigest()[:24]
    return Path(tempfile.gettempdir()) / "tube-miner-locks" / f"{digest}.lock"


def _read(path: Path) -> bytes:
    """The start of a lock file, never read through a link."""
    fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    try:
        return os.pread(fd, 4096, 0)
    finally:
        os.close(fd)


def _open_lock(path: Path, flags: int) -> int:
    """``path`` opened for the lock (``O_NOFOLLOW``); a LinkError for a link, an InputError
    for anything but a plain file with one name (a hard link's writes would land elsewhere too)."""
    try:
        fd = os.open(path, flags | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    except OSError as e:
        if e.errno == errno.ELOOP and path.is_symlink():
            raise link_error(path) from None
        raise
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode) or st.st_nlink != 1:
        os.close(fd)
        kind = "not a plain file" if not stat.S_ISREG(st.st_mode) else f"a file with {st.st_nlink} names (hard links)"
        raise InputError(f"the lock file is {kind}, so writing it could change another file; remove it and run "
                         "the command again", path)
    return fd


def read_holder(store: Store) -> dict:
    """Who holds (or last held without releasing) ``store``'s lock; {} when nobody."""
    path = lock_file(store)
    for p in (path, path.with_name(path.name + ".excl")):
        try:
            d = _parse(_read(p))
        except OSError:
            continue
        if d:
            return d
    return {}


def current_writer(store: Store) -> dict:
    """The holder named in ``store``'s lock when it is plausibly writing now: on this host
    its pid is alive; on another host it cannot be checked and is returned as named. {}
    when nobody is named. Reads only (no lock is tried: a probe could refuse a submit)."""
    holder = read_holder(store)
    if holder and holder.get("host") == socket.gethostname() and not _pid_alive(holder.get("pid")):
        return {}
    return holder


class OutputLock:
    """``with OutputLock(store, wait_s):`` — hold ``store``'s writer lock (module docstring)."""

    def __init__(self, store: Store, wait_s: float = 0.0, notify=None):
        self.store, self.wait_s = store, max(0.0, float(wait_s))
        self.notify = notify or (lambda msg: print(msg, file=sys.stderr))
        self.path = lock_file(store)
        self.fd: int | None = None
        self.excl: Path | None = None  # the O_EXCL fallback file, when that is what we hold
        self.took_over: dict = {}  # the stale holder this lock replaced, if any

    # -- flock -------------------------------------------------------------------------

    def acquire(self) -> OutputLock:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            if self.path.parent.is_symlink() and not self.store.local:  # the shared temporary folder: ours only
                raise link_error(self.path.parent)
            fd = _open_lock(self.path, os.O_RDWR | os.O_CREAT)
        except OSError as e:
            raise InputError(f"{self.path.parent}: the output folder cannot be written (its lock file: {e.strerror})",
                             self.path) from None
        deadline = time.monotonic() + self.wait_s
        try:
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    if time.monotonic() >= deadline:
                        raise self._refusal(_parse(os.pread(fd, 4096, 0))) from None
                    time.sleep(POLL_S)
                except OSError as e:
                    if e.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS):
                        os.close(fd)
                        fd = -1
                        return self._acquire_excl(deadline)
                    raise
        except BaseException:
            if fd >= 0:
                os.close(fd)
            raise
        previous = _parse(os.pread(fd, 4096, 0))
        try:
            self._write(fd)
        except BaseException:
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)
            raise
        self.fd = fd
        if previous:
            self.took_over = previous
            self.notify(f"mine: {self.store.uri}: taking over a stale lock of {describe(previous)}: "
                        "that process ended without releasing it (killed?); its work is resumed")
        return self

    def _write(self, fd: int) -> None:
        data = json.dumps(_holder()).encode()
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, data, 0)
            os.fsync(fd)
        except OSError as e:  # a full disk: one line naming the lock file, not a traceback
            raise write_error(e, self.path) from None

    def _refusal(self, holder: dict) -> LockedError:
        waited = f" after waiting {self.wait_s:g} s" if self.wait_s else ""
        return LockedError(f"{self.store.uri} is being written by {describe(holder)}{waited}; one writer per "
                           "catalogue: wait for it to finish, or pass --lock-wait SECONDS to wait for it")

    # -- O_EXCL fallback ---------------------------------------------------------------

    def _acquire_excl(self, deadline: float) -> OutputLock:
        path = self.path.with_name(self.path.name + ".excl")
        while True:
            try:
                fd = _open_lock(path, os.O_RDWR | os.O_CREAT | os.O_EXCL)
            except FileExistsError:
                if path.is_symlink():  # O_EXCL never follows one; a planted link is no holder to wait for
                    raise link_error(path) from None
                holder = read_holder(self.store)
                if holder.get("host") == socket.gethostname() and not _pid_alive(holder.get("pid")):
                    self.notify(f"mine: {self.store.uri}: taking over a stale lock of {describe(holder)}: "
                                "that process is gone")
                    self.took_over = holder
                    path.unlink(missing_ok=True)
                    continue
                if time.monotonic() >= deadline:
                    err = self._refusal(holder)
                    if holder.get("host") != socket.gethostname():
                        err = LockedError(f"{err} (a holder on another host cannot be checked from here: "
                                          f"if it is gone, remove {path})")
                    raise err from None
                time.sleep(POLL_S)
                continue
            try:
                self._write(fd)
            except BaseException:
                path.unlink(missing_ok=True)
                raise
            finally:
                os.close(fd)
            self.excl = path
            return self

    # -- release -----------------------------------------------------------------------

    def release(self) -> None:
        if self.fd is not None:
            try:
                os.ftruncate(self.fd, 0)  # released cleanly: the next holder takes over nothing
            finally:
                fcntl.flock(self.fd, fcntl.LOCK_UN)
                os.close(self.fd)
                self.fd = None
        if self.excl is not None:
            self.excl.unlink(missing_ok=True)
            self.excl = None

    def __enter__(self) -> OutputLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
