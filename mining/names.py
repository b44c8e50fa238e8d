"""Names are data: the one rule for dataset, sequence, window and tube names.

Names come from users (``--sequences``, a config's ``source.sequences``), from a source's
own listing (RobotCar traversal folders, MCAP file stems, KITTI calibration files) and
back from a catalogue (``job.json``, the folder names, the files' ``dataset`` / ``sequence``, tube ids), and they end up in
paths under ``--out`` and an export's DEST. So a name is checked where it enters and
again where a path is built from it, and a path is never made from anything else.

The rule (no encoding, so every name reads the same in a path, a query and a log):

* a **name** is 1 to ``MAX_NAME_LENGTH`` characters of ``[A-Za-z0-9._-]``, starts with a
  letter or digit (never ``_``, ``.`` or ``-``), and holds no ``..``. It is one path
  component: no separator, never ``.`` or ``..``, no ``=`` (the hive partition mark).
  Not ``_`` or ``.`` first because the catalogue's folders are named by it and pandas,
  ``pyarrow.dataset`` and ``pq.read_table`` skip such folders by default: a sequence ``_x``
  was silently missing from every plain read. A window name is its sequence's name plus
  its frame range, so it may be longer (``MAX_WINDOW_NAME_LENGTH``).
* a **tube id** is names joined by ``/`` (the catalogue's ``dataset/sequence/frame.obs``);
  its export folder joins them with ``_`` instead (``tube_folder``).

``inside`` is the last line of defence where a path is built under a folder: the
resolved path (symbolic links followed) must lie inside the resolved folder.

A **path** a user names (an option's file or folder) is checked too, before any work
(``path_problem``): the system must be able to hold it (no name over ``NAME_MAX`` bytes, the
whole under ``PATH_MAX``: else a traceback ``File name too long`` far into a run), and it
must print as one line (no control or text-direction character, no bytes that are not
UTF-8, which the catalogue's records and every message would carry on).
"""

from __future__ import annotations

import os
import unicodedata
from pathlib import Path

from mining.errors import InputError

NAME_MAX = 255  # bytes in one name of a path (Linux and macOS filesystems)
PATH_MAX = 4096  # bytes in a path, its terminating NUL included (Linux)
# The longest name of a path the catalogue or an export builds from names is two names joined
# (an export's ``<dataset>_<sequence>.json`` and its temporary ``.<that>.tmp-<12 hex>``, a crops
# folder ``<dataset>_<sequence>_<frame>.<obs>``): 1 + 2*100 + 1 + 5 + 5 + 12 = 224 bytes, under
# NAME_MAX (tests/test_names.py builds every such path and checks it).
MAX_NAME_LENGTH = 100  # characters of a dataset or sequence name (ASCII: one byte each)
FRAME_DIGITS = 9  # a window's frame position prints in at most 9 digits (below 10**9: a year of 30 fps video)
# A window name is ``<sequence>-<first:07d>-<last:07d>`` (types.Window.name): 100 + 2*(1+9) = 120.
MAX_WINDOW_NAME_LENGTH = MAX_NAME_LENGTH + 2 * (1 + FRAME_DIGITS)
NAME_RULE = f"1-{MAX_NAME_LENGTH} characters of A-Z a-z 0-9 . _ -, starting with a letter or digit, no '..'"


def name_problem(name: object, limit: int = MAX_NAME_LENGTH) -> str | None:
    """Why ``name`` is not a safe name of at most ``limit`` characters, or None when it is one."""
    if not isinstance(name, str):
        return f"not a string but {type(name).__name__}"
    if not name:
        return "empty"
    if len(name) > limit:
        return f"{len(name)} characters, more than {limit}"
    problems = []
    bad = sorted({c for c in name if not (c.isascii() and (c.isalnum() or c in "._-"))})
    if bad:
        problems.append("holds " + " ".join(repr(c) for c in bad))
    if ".." in name:
        problems.append("holds '..'")
    if name[0] in "._-":
        problems.append(f"starts with {name[0]!r}")
    return "; ".join(problems) or None


def check_name(name: object, kind: str, origin: str, path: str | Path | None = None) -> str:
    """``name`` when it is a safe ``kind`` name (dataset, sequence, window…); else an
    InputError naming it, where it came from (``origin``) and the rule. A window's name may
    be longer than the others (``MAX_WINDOW_NAME_LENGTH``: its sequence's name and frame range)."""
    problem = name_problem(name, MAX_WINDOW_NAME_LENGTH if kind == "window" else MAX_NAME_LENGTH)
    if problem is not None:
        raise InputError(f"{kind} name {name!r} from {origin} is not a safe name ({problem}); "
                         f"names are {NAME_RULE}", path)
    return name  # type: ignore[return-value]


def check_tube_id(tube_id: object, origin: str, path: str | Path | None = None) -> str:
    """``tube_id`` when it is safe names joined by ``/``; else an InputError."""
    parts = tube_id.split("/") if isinstance(tube_id, str) else [tube_id]
    for part in parts:
        problem = name_problem(part)
        if problem is not None:
            raise InputError(f"tube id {tube_id!r} from {origin} is not safe names joined by '/' "
                             f"(part {part!r}: {problem}); names are {NAME_RULE}", path)
    return tube_id  # type: ignore[return-value]


def tube_id_argument(text: str) -> str:
    """An argparse type: a tube id from the command line (``check_tube_id``), refused by the parser."""
    import argparse

    try:
        return check_tube_id(text, "the command line")
    except InputError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def tube_folder(tube_id: str, origin: str = "the catalogue") -> str:
    """The one-component folder name of a tube (``/`` → ``_``); an InputError for an unsafe id."""
    return "_".join(check_tube_id(tube_id, origin).split("/"))


def inside(folder: str | Path, path: str | Path) -> Path:
    """``path`` (relative to ``folder`` or absolute) when, resolved, it lies inside the
    resolved ``folder``; else an InputError. Returns the unresolved ``folder / path``."""
    folder = Path(folder)
    full = folder / path
    if not full.resolve().is_relative_to(folder.resolve()):
        raise InputError(f"refusing to write outside {folder}", full)
    return full


_BIDI = {chr(c) for c in (*range(0x202A, 0x202F), *range(0x2066, 0x206A))}  # text-direction overrides


def shown(path: str | os.PathLike) -> str:
    """``path`` as it can be printed on one line: control characters and undecodable bytes escaped."""
    text = os.fspath(path)
    if text.isprintable() and not (_BIDI & set(text)):
        return text
    return ascii(text)[1:-1]


def path_problem(path: str | os.PathLike) -> str | None:
    """Why ``path`` cannot name a file (or folder) here, or None: empty, bytes that are not
    UTF-8 text, a control or text-direction character, a name longer than NAME_MAX bytes or a
    path of PATH_MAX bytes or more (the system's ENAMETOOLONG, said before any work)."""
    text = os.fspath(path)
    if not text:
        return "is empty"
    if any(0xD800 <= ord(c) <= 0xDFFF for c in text):  # undecodable bytes, as os.fsdecode keeps them
        return "holds bytes that are not UTF-8 text"
    if any(unicodedata.category(c) == "Cc" or c in _BIDI for c in text):
        return "holds a control or text-direction character"
    raw = os.fsencode(text)
    if len(raw) >= PATH_MAX:
        return f"is {len(raw)} bytes long; a path holds at most {PATH_MAX - 1}"
    longest = max(raw.split(b"/"), key=len)
    if len(longest) > NAME_MAX:
        return f"has a name of {len(longest)} bytes; a name holds at most {NAME_MAX}"
    return None
