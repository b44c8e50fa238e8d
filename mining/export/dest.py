"""Where a product goes: the rules for DEST, for `mine export` (a folder) and `mine render`
(a file), and the export record. Every write goes through ``catalog/safe_files.py``.

A folder (export): an export refuses a DEST that is not empty, unless ``--overwrite`` and
DEST holds the record (``RECORD``, ``.mine-export.json``) of an earlier export: then exactly
the entries that record lists are replaced (files, and folders with what is in them; links
are removed, not followed), anything else in DEST is kept, and nothing outside DEST is
touched.

Links: an export never writes a link, so a DEST that holds one (at any depth) holds
something it did not write; it is refused, naming the link, before anything is removed
or written (a link at ``index.json`` or ``JPEGImages`` would send the files elsewhere).
The writer fills a private folder inside DEST (``mine-export-partial-<random>``, made by
``mkdir`` under an unpredictable name: no link can be planted in it beforehand); only when
it has finished are the earlier export's entries removed and the new ones renamed into
DEST (``safe_files.move_in``: never onto an existing entry). So a failed export (bad data,
a full disk) leaves the earlier one as it was. The record is written first listing the old
entries, the new ones and the private folder, so even an export killed half-way leaves a
record that a later ``--overwrite`` cleans up (``publish_folder``).

A file (render): the destination rule of every single file a command writes
(``safe_files.check_output_file`` and ``publish_file``): an existing DEST is replaced only
with ``--overwrite``, and only when it is a plain file (a link or a folder there is refused,
whatever the flag). The file is written
in a private folder beside DEST (``.<DEST name, cut when long>.partial-<random>``, made by ``mkdir`` under
an unpredictable name, so no link can be planted where the writer writes), then moved onto
DEST (``safe_files.publish_file``: without ``--overwrite`` the name is claimed atomically,
never replaced). A failed write leaves DEST as it was (``publish_file``).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from mining.catalog import safe_files
from mining.errors import InputError
from mining.files import read_text
from mining.names import NAME_MAX, name_problem

RECORD = ".mine-export.json"  # in DEST: what the export wrote there, so --overwrite replaces exactly that
STAGING_PREFIX = "mine-export-partial-"  # the exporters' private folder in DEST (a safe name: a record may list it)
T = TypeVar("T")


def entries(dest: Path) -> list[str]:
    """The names in folder ``dest``, sorted (none when it does not exist)."""
    return sorted(p.name for p in dest.iterdir()) if dest.is_dir() else []


def recorded(dest: Path) -> list[str]:
    """The top-level names in ``dest`` an earlier export recorded (RECORD), checked to be
    plain names inside ``dest``."""
    try:
        names = json.loads(read_text(dest / RECORD))["written"]
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise TypeError("'written' is not a list of names")
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InputError(f"not a record of an earlier export ({e}); remove DEST's contents yourself or choose "
                         "another folder", dest / RECORD) from None
    bad = [n for n in names if n == RECORD or name_problem(n, NAME_MAX) is not None]  # a crops folder joins names: longer than one
    if bad:
        raise InputError(f"the record names {bad!r}, which are not entries of DEST; remove DEST's contents yourself",
                         dest / RECORD)
    return names


def check_folder(dest: Path, overwrite: bool) -> list[str]:
    """Refuse a DEST that is not an empty or absent folder, unless ``overwrite`` and DEST
    holds an earlier export's RECORD and no link; returns the entries that replacing will
    remove."""
    if dest.exists() and not dest.is_dir():
        raise InputError("DEST is not a folder", dest)
    present = entries(dest)
    if not present:
        return []
    if not overwrite:
        raise InputError(f"DEST is not empty ({len(present)} entries: {', '.join(present[:5])}"
                         f"{', …' if len(present) > 5 else ''}); choose an empty folder, or pass --overwrite to replace "
                         "an earlier export there", dest)
    links = safe_files.links_under(dest)
    if links:
        raise InputError(f"DEST holds links, which no export writes: {safe_files.describe_links(links, dest)}; an "
                         "export never writes through a link (the files would land elsewhere) and nothing was "
                         "removed: remove the links yourself or choose another folder", dest)
    if RECORD not in present:
        raise InputError(f"--overwrite replaces only what an earlier `mine export` recorded in {RECORD}, and DEST "
                         f"has none ({len(present)} other entries): remove them yourself or choose another folder", dest)
    return [n for n in recorded(dest) if n in present]


def write_record(dest: Path, record: dict) -> None:
    """DEST's RECORD, written atomically and never through a link (``safe_files``)."""
    safe_files.write_atomic(dest, RECORD, (json.dumps(record, indent=1) + "\n").encode())


def publish_folder(dest: Path, replaced: list[str], write: Callable[[Path], int],
                   record: Callable[[int], dict]) -> int:
    """Fill a private folder in ``dest`` with ``write(folder)`` (it returns the items it
    wrote), then replace the entries ``replaced`` (``check_folder``'s) by what it wrote,
    recording them in RECORD (``record(items)`` and the names written); the items. A failed
    export removes the folders it made for DEST (an earlier DEST folder stays as it was)."""
    made = _missing_folders(dest)
    dest.mkdir(parents=True, exist_ok=True)
    try:
        n = _publish(dest, replaced, write, record)
    except BaseException:
        _remove_made(made)
        raise
    return n


def _missing_folders(dest: Path) -> list[Path]:
    """The folders ``dest.mkdir(parents=True)`` would make, deepest first."""
    out = []
    for p in (dest, *dest.parents):
        if p.exists():
            break
        out.append(p)
    return out


def _remove_made(made: list[Path]) -> None:
    """Remove the folders a failed export made (deepest first), each only while it is empty: a
    file someone else put there meanwhile is never removed."""
    for p in made:
        try:
            p.rmdir()
        except OSError:
            return


def _publish(dest: Path, replaced: list[str], write: Callable[[Path], int], record: Callable[[int], dict]) -> int:
    staging = safe_files.private_dir(dest, STAGING_PREFIX)
    try:
        n = write(staging)
        written = sorted(os.listdir(staging))
        kept = set(entries(dest)) - set(replaced) - {staging.name}
        clash = sorted(set(written) & (kept | {RECORD}))
        if clash:
            raise InputError(f"this export writes {', '.join(clash)}, which DEST holds and no earlier export recorded; "
                             "nothing was removed or written: move them away or choose another folder", dest)
        about = record(n)
        # Until the new entries are in, the record names old, new and partial alike: an export
        # killed in between leaves nothing that a later --overwrite would not remove.
        write_record(dest, about | {"written": sorted(set(replaced) | set(written) | {staging.name})})
        for name in replaced:  # the entries themselves: links removed, never followed
            safe_files.remove_tree(dest / name)
        for name in written:
            safe_files.move_in(staging, name, dest)
        write_record(dest, about | {"written": written})
    finally:
        safe_files.remove_tree(staging)
    return n


def check_file(dest: Path, overwrite: bool) -> None:
    """Refuse a file DEST that may not be written: an existing entry without ``overwrite``,
    a link or a folder at DEST, a folder where nothing can be written (the destination rule
    of every single file a command writes: ``safe_files.check_output_file``)."""
    safe_files.check_output_file(dest, overwrite, "DEST")


def publish_file(dest: Path, overwrite: bool, write: Callable[[Path], T]) -> T:
    """``write(path)`` into a private folder beside ``dest`` (``path`` has DEST's name), then
    move the file onto ``dest`` (replacing it only with ``overwrite``); ``write``'s result.
    The private folder is removed whatever happens."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    name = dest.name if len(os.fsencode(dest.name)) <= 100 else dest.name[:25]  # so the folder's name fits NAME_MAX
    work = safe_files.private_dir(dest.parent, f".{name}.partial-")
    try:
        result = write(work / dest.name)  # writers open files by path: inside a folder only this write uses
        safe_files.publish_file(work / dest.name, dest, overwrite)
    finally:
        safe_files.remove_tree(work)
    return result
