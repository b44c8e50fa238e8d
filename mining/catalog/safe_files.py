"""Writing inside a folder the user named without following links: ``--out``, an export's
DEST, the folder of a rendered video, the lock folder.

A link planted inside such a folder (``OUT/.mine.lock`` → a file elsewhere, ``DEST/index.json``
→ ``~/.bashrc``, ``DEST/JPEGImages`` → another folder) would make a plain ``open`` or
``mkdir -p`` write where the user never pointed the tool. So every write of this module:

* takes the folder the user named as given (links in *its* path are the user's choice) and
  follows nothing below it: each folder on the way is opened relative to its parent with
  ``O_NOFOLLOW | O_DIRECTORY`` (made when absent), and a link there is refused, naming it
  (``LinkError``);
* writes its bytes to a temporary name of its own, ``.<name>.tmp-<random>``, created with
  ``O_CREAT | O_EXCL | O_NOFOLLOW`` (never an existing file, never through a link), then
  renames it onto the final name: a rename replaces a link there instead of writing
  through it, and readers never see half a file;
* removes an entry itself (a link is removed, never what it points to);
* turns a failed write (no space left on device, file too large, an I/O error) into a
  ``WriteError`` naming the file and the reason, after removing its temporary file, so the
  file it would have replaced is untouched.

Writers that open files by path themselves (OpenCV, PyAV, Parquet by path) write into a
``private_dir``: a folder made with ``mkdir`` under an unpredictable name, which holds
nothing they did not write; what they made is then renamed into place (``move_in``,
``publish_file``).

One file a command writes where the user named it (``mine query --output``, every
``--json``, a bench's PNGs, ``mine render``'s video) keeps one destination rule
(``write_file``, checked up front by ``check_output_file``): written under a temporary name
in the same folder and renamed onto the name; a link at the name is refused (never written
through, never replaced); an existing file is replaced only with ``--overwrite`` and only
when it is a plain file; without it the name is claimed atomically (a hard link), so a file
made meanwhile is not replaced either. A path the system cannot hold (a name over
``NAME_MAX`` bytes, a path over ``PATH_MAX``) or that would not print as one line (control
characters, bytes that are not UTF-8) is refused before any work (``names.path_problem``).
"""

from __future__ import annotations

import errno
import os
import posixpath
import secrets
import shutil
import stat
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO

from mining.errors import InputError, MiningError
from mining.names import path_problem, shown

TMP_MARK = ".tmp-"  # part of every temporary name (store.is_temporary: readers skip such files)
_DIR = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC
_NEW = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
# What a full or limited disk says; the hint the user gets with it.
_HINTS = {errno.ENOSPC: "free some space and run the command again",
          errno.EDQUOT: "free some space (or raise the quota) and run the command again",
          errno.EFBIG: "the file exceeds the size limit of this process or filesystem"}

Fill = bytes | bytearray | memoryview | Callable[[BinaryIO], None]


class WriteError(MiningError, OSError):
    """A file could not be written (no space left on device, file too large, an I/O error).

    Both a MiningError (the command prints one line) and an OSError with the errno (code
    that treats a failed write as best effort keeps doing so)."""

    def __str__(self) -> str:
        reason = self.strerror or "the write failed"
        reason = reason[:1].lower() + reason[1:]
        hint = _HINTS.get(self.errno)
        return f"file {self.filename}: cannot be written: {reason}" + (f" ({hint})" if hint else "")


class LinkError(InputError):
    """A link where this module was to write a file or enter a folder."""


def write_error(e: OSError, path: str | os.PathLike) -> WriteError:
    """``e`` as a WriteError naming ``path`` (the file the user knows, not a temporary name)."""
    if isinstance(e, WriteError):
        return e
    return WriteError(e.errno or errno.EIO, e.strerror or str(e), os.fspath(path))


def link_error(path: str | os.PathLike) -> LinkError:
    try:
        target = os.readlink(path)
    except OSError:
        target = "?"
    return LinkError(f"is a link (to {target}): Tube Miner never writes through a link inside the folder you named "
                     "(it could write elsewhere); remove the link, or name the folder it points to yourself", path)


def _is_link(name: str, dir_fd: int) -> bool:
    try:
        return stat.S_ISLNK(os.stat(name, dir_fd=dir_fd, follow_symlinks=False).st_mode)
    except OSError:
        return False


def _parts(rel: str) -> list[str]:
    parts = [p for p in rel.split("/") if p]
    if any(p in (".", "..") for p in parts):
        raise InputError("not a path inside the folder", rel)
    return parts


@contextmanager
def folder(root: str | os.PathLike, rel: str = "", create: bool = True) -> Iterator[int]:
    """A descriptor of the folder ``root/rel`` (``rel`` ``/``-separated), every folder below
    ``root`` entered without following links (made when absent with ``create``); a
    LinkError names a link on the way, FileNotFoundError a folder missing without ``create``."""
    root = os.fspath(root)
    if create:
        os.makedirs(root, exist_ok=True)  # the folder the user named: links in its path are theirs
    fd = os.open(root, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    path = root
    try:
        for part in _parts(rel):
            path = os.path.join(path, part)
            if create:
                try:
                    os.mkdir(part, 0o777, dir_fd=fd)
                except FileExistsError:
                    pass
            try:
                sub = os.open(part, _DIR, dir_fd=fd)
            except OSError as e:
                if e.errno in (errno.ELOOP, errno.ENOTDIR) and _is_link(part, fd):
                    raise link_error(path) from None
                raise
            os.close(fd)
            fd = sub
        yield fd
    finally:
        os.close(fd)


def _new_temporary(dir_fd: int, name: str) -> tuple[str, int]:
    """A new file beside ``name`` under an unpredictable temporary name: (name, descriptor)."""
    short = name if len(os.fsencode(name)) <= 200 else name[:50]  # cut, so a name of NAME_MAX bytes has a temporary
    for _ in range(100):
        tmp = f".{short}{TMP_MARK}{secrets.token_hex(6)}"
        try:
            return tmp, os.open(tmp, _NEW, 0o666, dir_fd=dir_fd)
        except FileExistsError:  # taken (by chance, or planted): another name
            continue
    raise FileExistsError(errno.EEXIST, "no free temporary name", name)


def _unlink_quietly(name: str, dir_fd: int) -> None:
    try:
        os.unlink(name, dir_fd=dir_fd)
    except OSError:
        pass


def stage(root: str | os.PathLike, rel: str, fill: Fill) -> str:
    """Write ``fill`` (bytes, or a function writing to a binary file) to a new temporary
    file beside ``root/rel``; its path relative to ``root``, to ``publish`` or ``discard``."""
    where, name = posixpath.split(rel)
    full = os.path.join(os.fspath(root), rel)
    try:
        with folder(root, where) as dir_fd:
            tmp, fd = _new_temporary(dir_fd, name)
            try:
                with os.fdopen(fd, "wb") as f:
                    if isinstance(fill, (bytes, bytearray, memoryview)):
                        f.write(fill)
                    else:
                        fill(f)
            except BaseException:
                _unlink_quietly(tmp, dir_fd)
                raise
    except LinkError:
        raise
    except OSError as e:
        raise write_error(e, full) from None
    return posixpath.join(where, tmp)


def publish(root: str | os.PathLike, tmp_rel: str, rel: str) -> None:
    """Rename the staged ``tmp_rel`` onto ``rel`` (one folder): a link at ``rel`` is
    replaced, never written through."""
    where, name = posixpath.split(rel)
    tmp_where, tmp = posixpath.split(tmp_rel)
    if tmp_where != where:
        raise ValueError(f"{tmp_rel} is not beside {rel}")
    try:
        with folder(root, where, create=False) as dir_fd:
            os.replace(tmp, name, src_dir_fd=dir_fd, dst_dir_fd=dir_fd)
    except LinkError:
        raise
    except OSError as e:
        raise write_error(e, os.path.join(os.fspath(root), rel)) from None


def write_atomic(root: str | os.PathLike, rel: str, fill: Fill) -> None:
    """Create or replace ``root/rel`` with ``fill`` (``stage``, then ``publish``)."""
    tmp = stage(root, rel, fill)
    try:
        publish(root, tmp, rel)
    except BaseException:
        discard(root, tmp)
        raise


def remove(root: str | os.PathLike, rel: str) -> None:
    """Delete ``root/rel`` itself (a link is removed, not followed); a missing file is fine."""
    where, name = posixpath.split(rel)
    try:
        with folder(root, where, create=False) as dir_fd:
            os.unlink(name, dir_fd=dir_fd)
    except FileNotFoundError:
        pass


def discard(root: str | os.PathLike, rel: str) -> None:
    """Remove a temporary file, ignoring every error (cleaning up after another one)."""
    try:
        remove(root, rel)
    except (OSError, MiningError):
        pass


def rename(root: str | os.PathLike, src: str, dst: str) -> None:
    """Move the entry ``root/src`` to ``root/dst`` (its folder made), both folders entered
    without following links; the entry itself moves, a link as a link."""
    (src_where, src_name), (dst_where, dst_name) = posixpath.split(src), posixpath.split(dst)
    with folder(root, src_where, create=False) as src_fd, folder(root, dst_where) as dst_fd:
        os.rename(src_name, dst_name, src_dir_fd=src_fd, dst_dir_fd=dst_fd)


def make_folder(root: str | os.PathLike, rel: str) -> None:
    """``mkdir -p root/rel`` that never follows a link below ``root``."""
    with folder(root, rel):
        pass


def private_dir(parent: Path, prefix: str) -> Path:
    """A new empty folder in ``parent`` under an unpredictable name (``mkdtemp``: made by
    ``mkdir``, mode 0700), so it holds nothing its writers did not put there."""
    try:
        return Path(tempfile.mkdtemp(prefix=prefix, dir=parent))
    except OSError as e:
        raise write_error(e, parent / f"{prefix}…") from None


def remove_tree(path: Path) -> None:
    """Delete ``path``: a file or link itself, a folder with what is in it (``shutil.rmtree``
    does not follow links inside); a missing path is fine."""
    try:
        if path.is_symlink() or not path.is_dir():
            path.unlink()
        else:
            shutil.rmtree(path)
    except FileNotFoundError:
        pass


def links_under(top: Path, limit: int = 5) -> list[Path]:
    """Up to ``limit`` links inside the folder ``top``, at any depth (none is followed)."""
    found: list[Path] = []
    todo = [os.fspath(top)]
    while todo and len(found) < limit:
        try:
            entries = list(os.scandir(todo.pop()))
        except (FileNotFoundError, NotADirectoryError):
            continue
        for e in sorted(entries, key=lambda e: e.name):
            if e.is_symlink():
                found.append(Path(e.path))
            elif e.is_dir(follow_symlinks=False):
                todo.append(e.path)
    return found[:limit]


def describe_links(links: list[Path], top: Path) -> str:
    """``a → /x, b/c → /y``: links by their path under ``top`` and their target."""
    def target(p: Path) -> str:
        try:
            return os.readlink(p)
        except OSError:
            return "?"
    return ", ".join(f"{p.relative_to(top)} → {target(p)}" for p in links)


def move_in(staging: Path, name: str, dest: Path) -> None:
    """Rename ``staging/name`` to ``dest/name``; refused when ``dest`` has an entry of that
    name (a link included: it is neither followed nor replaced)."""
    with folder(staging, create=False) as src_fd, folder(dest, create=False) as dst_fd:
        try:
            os.stat(name, dir_fd=dst_fd, follow_symlinks=False)
        except FileNotFoundError:
            os.rename(name, name, src_dir_fd=src_fd, dst_dir_fd=dst_fd)
            return
    raise InputError("exists already (made while this command ran?); nothing was written over it", dest / name)


def publish_file(src: Path, dest: Path, replace: bool) -> None:
    """Move the finished file ``src`` to ``dest`` (same filesystem). Without ``replace`` an
    existing ``dest`` is never replaced (a hard link claims the name atomically); with it,
    a regular file there is; a link or a folder at ``dest`` is refused either way."""
    if dest.is_symlink():
        raise link_error(dest)
    if os.path.lexists(dest) and not dest.is_file():
        raise InputError("exists and is not a file; nothing was written over it", dest)
    try:
        if replace:
            os.replace(src, dest)
            return
        try:
            os.link(src, dest, follow_symlinks=False)
        except FileExistsError:
            raise InputError("exists already; pass --overwrite to replace it", dest) from None
        except OSError as e:
            if e.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK):
                raise
            if os.path.lexists(dest):  # no hard links here: the nearest thing to claiming the name
                raise InputError("exists already; pass --overwrite to replace it", dest) from None
            os.rename(src, dest)
            return
        os.unlink(src)
    except (InputError, LinkError):
        raise
    except OSError as e:
        raise write_error(e, dest) from None


# -- one file where the user named it --------------------------------------------------------


def refusal(path: str | os.PathLike, reason: str, what: str = "", kind: type[InputError] = InputError) -> InputError:
    """The error refusing ``path``: ``--json PATH: reason`` when the option ``what`` is known,
    else ``file PATH: reason``; the path shown on one line."""
    if what:
        e = kind(f"{what} {shown(path)}: {reason}")
        e.path = os.fspath(path)
        return e
    return kind(reason, shown(path))


def check_path(path: str | os.PathLike, what: str = "") -> None:
    """InputError naming ``path`` (and the option ``what``) when ``path_problem`` finds one."""
    problem = path_problem(path)
    if problem is not None:
        raise refusal(path, problem, what)


def _nearest_folder(path: Path) -> Path:
    """``path`` when it exists, else its nearest existing ancestor (the folder that would be made in)."""
    here = path if str(path) else Path(".")
    while not os.path.lexists(here) and here != here.parent:
        here = here.parent
    return here


def check_writable_folder(path: str | os.PathLike, what: str = "") -> None:
    """InputError unless a file can be created in the folder ``path``, or (when absent) in the
    folder it would be made in: a probe file is created there (``O_EXCL``, never through a
    link) and removed."""
    path = Path(path)
    where = _nearest_folder(path)
    if not where.is_dir():
        raise refusal(path, f"cannot be written: {'it' if where == path else shown(where)} is not a folder", what)
    try:
        with folder(where, create=False) as dir_fd:
            tmp, fd = _new_temporary(dir_fd, "probe")
            os.close(fd)
            os.unlink(tmp, dir_fd=dir_fd)
    except OSError as e:
        reason = (e.strerror or str(e)).lower()
        raise refusal(path, f"cannot be written: nothing can be made in {shown(where)} ({reason})", what) from None


def check_output_file(dest: str | os.PathLike, overwrite: bool, what: str = "") -> None:
    """Refuse, before any work, a file ``dest`` that ``write_file`` would refuse at the end: a
    path the system cannot hold, a link or a non-file at ``dest``, an existing file without
    ``overwrite``, a folder where nothing can be written. ``what`` names the option."""
    dest = Path(dest)
    check_path(dest, what)
    if dest.is_symlink():
        raise refusal(dest, f"is a link (to {shown(os.readlink(dest))}): a file is never written through a link (it "
                            "could land elsewhere) nor over one; remove the link or name another file", what, LinkError)
    if os.path.lexists(dest) and not dest.is_file():
        raise refusal(dest, "exists and is not a file; nothing is written over it", what)
    if dest.exists() and not overwrite:
        raise refusal(dest, "exists; pass --overwrite to replace it, or choose another name", what)
    check_writable_folder(dest.parent, what)


def write_file(dest: str | os.PathLike, fill: Fill, overwrite: bool = False) -> None:
    """Write one file where the user named it, by the destination rule (module docstring):
    ``fill`` (bytes, or a function writing to a binary file) goes to a temporary name beside
    ``dest`` (its folder made when absent), then onto ``dest`` (``publish_file``: a link there
    is refused; an existing file replaced only with ``overwrite``). A failed write leaves
    ``dest`` as it was and no temporary file."""
    dest = Path(dest)
    check_path(dest)
    parent = dest.parent
    try:
        os.makedirs(parent, exist_ok=True)  # the folder the user named: links in its path are theirs
    except OSError as e:
        raise write_error(e, parent) from None
    if dest.is_symlink():  # before any bytes are written: the rule refuses it whatever the flag
        raise link_error(dest)
    tmp = stage(parent, dest.name, fill)
    try:
        publish_file(parent / tmp, dest, overwrite)
    finally:
        discard(parent, tmp)  # gone after a publish; after a refusal, the bytes never reach dest
