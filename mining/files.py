"""Every file read for data is a regular file: the one door data files are opened by.

A FIFO at a frame's name made its reader wait for a writer that never came: the job hung
until killed. A device streams without end, a directory or a socket is no data at all. So a
data file (an image, a calibration, poses, timestamps, a proposals file, a model, a config,
a catalogue record) is opened here without blocking (``O_NONBLOCK``: opening a FIFO returns
at once), then checked with ``fstat`` on what was opened, so nothing can be swapped in
between the check and the read. Anything but a regular file is one ``InputError`` naming the
file and what it is.

Libraries that open files by name themselves (OpenCV, onnxruntime) are given the bytes read
here, or the name once ``check_regular`` has passed it.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path
from typing import BinaryIO

from mining.errors import InputError, decode_text

_KINDS = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISDIR, "a directory"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"), (stat.S_ISLNK, "a symbolic link"))


def what_is(mode: int) -> str:
    """What a file of ``st_mode`` ``mode`` is, in words ("a regular file", "a FIFO (named pipe)"…)."""
    if stat.S_ISREG(mode):
        return "a regular file"
    return next((kind for test, kind in _KINDS if test(mode)), "not a regular file")


def _refuse(path: str | os.PathLike, mode: int, frame: int | None) -> InputError:
    return InputError(f"is {what_is(mode)}, not a regular file; a data file must be one", os.fspath(path), frame)


def open_regular(path: str | os.PathLike, frame: int | None = None) -> BinaryIO:
    """``path`` opened for reading in binary, when it is a regular file (links followed); an
    InputError naming it and what it is otherwise. Missing or unreadable: the OSError, as
    ``open`` raises it."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)  # a FIFO opens at once, never waits
    except OSError as e:
        if e.errno == errno.ENXIO:  # a socket cannot be opened as a file
            raise _refuse(path, os.stat(path).st_mode, frame) from None
        raise
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise _refuse(path, st.st_mode, frame)
        os.set_blocking(fd, True)  # a regular file reads the same either way; plain reads from here
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_bytes(path: str | os.PathLike, frame: int | None = None) -> bytes:
    """The bytes of the regular file ``path`` (``open_regular``)."""
    with open_regular(path, frame) as f:
        return f.read()


def read_text(path: str | os.PathLike, what: str = "file", frame: int | None = None) -> str:
    """The text of the user's regular file ``path`` (``open_regular``; ``what`` it is: "job
    config"), newlines as ``Path.read_text`` gives them; one line naming the first byte that is
    not UTF-8 (``errors.decode_text``)."""
    return decode_text(read_bytes(path, frame), path, what, frame)


def check_regular(path: str | os.PathLike, frame: int | None = None) -> Path:
    """``path`` when it is a regular file (for a library that opens it by name); an InputError
    naming it and what it is otherwise. A missing file is left to the caller's own message."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return Path(path)
    if not stat.S_ISREG(mode):
        raise _refuse(path, mode, frame)
    return Path(path)
