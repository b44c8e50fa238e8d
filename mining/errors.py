"""Errors that name the file, the frame and the reason, so a user can fix their input."""

from __future__ import annotations

from pathlib import Path


class MiningError(Exception):
    """Base class of all errors Tube Miner raises on purpose."""


class InputError(MiningError):
    """Bad input: a file that is missing, unreadable, or contradicts the rest of the data.

    The message always names the file, the frame (when one is concerned) and the reason.
    """

    def __init__(self, reason: str, path: str | Path | None = None, frame: int | None = None):
        self.reason = reason
        self.path = None if path is None or str(path) == "" else str(path)  # an empty path names no file
        self.frame = frame
        parts = []
        if self.path is not None:
            parts.append(f"file {self.path}")
        if frame is not None:
            parts.append(f"frame {frame}")
        where = ", ".join(parts)
        super().__init__(f"{where}: {reason}" if where else reason)


class ConfigError(MiningError):
    """A job configuration that cannot be used (unknown key, wrong type, bad value)."""


class NothingMatched(Exception):
    """A predicate matched nothing, so nothing was written (``mine export``, ``mine render``).

    An answer, not a failure of the input: ``cli.main`` maps it to exit status 1 (as grep's
    "no match"), once for every command. Not a MiningError on purpose: the commands report
    those as failures (exit status 2)."""


def decode_text(data: bytes, path: str | Path, what: str, frame: int | None = None) -> str:
    """``data``, the bytes of a user's text file ``path`` (``what`` it is: "job config"), as
    text with universal newlines (as ``Path.read_text``); InputError, one line naming the file,
    the first byte that is not UTF-8, its offset and line, where the bytes are not UTF-8."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        line = data.count(b"\n", 0, e.start) + 1
        raise InputError(f"{what} is not UTF-8 text: byte 0x{data[e.start]:02x} at offset {e.start} (line {line}); "
                         "save it as UTF-8", path, frame) from None
    return text.replace("\r\n", "\n").replace("\r", "\n")
