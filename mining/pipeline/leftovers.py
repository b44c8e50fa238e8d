"""What a job leaves in its working folders, swept or reported: nothing stays unsaid.

* Observation caches (``_cache/obs/dataset=D/sequence=S/<window>.npz.zst``, ``cache.py``) are
  removed as soon as no track needs them (``submit.run_job``). A run killed mid-job leaves the
  caches of the windows it had observed; the resubmission skips those windows, so nothing
  would serve them: ``sweep_caches`` removes every cache of a sequence once it is stitched,
  and at job end (a resubmission of a finished job included) those of every stitched sequence.
  A sequence not stitched yet keeps its caches for the next run.
* Temporaries of unfinished writes (``Store.temporaries``) are removed by the next submit
  (``resume.sweep_temporaries``).
* Anything else in the cache folders no job wrote (``foreign``): never removed, only named.

``mine status`` lists all three with counts and sizes (``leftover_lines``), and says so when
nothing is left.
"""

from __future__ import annotations

import os
import posixpath
import re
import stat
from dataclasses import dataclass, field

import pyarrow.fs as pafs

from mining.catalog.layout import CACHE, CACHE_SUFFIX, LEGACY_CACHE_SUFFIX
from mining.catalog.records import SequenceMarker
from mining.catalog.store import LEFTOVER, Store

CACHE_ROOT = CACHE.split("/")[0]  # "_cache": every cache folder a job makes is under it
# A cache file of ours: its sequence's folder, a window's name, our suffix (or the pickle of old).
_CACHE_FILE = re.compile(rf"{re.escape(CACHE)}/dataset=([^/]+)/sequence=([^/]+)/[^/.][^/]*"
                         rf"(?:{re.escape(CACHE_SUFFIX)}|{re.escape(LEGACY_CACHE_SUFFIX)})")


@dataclass
class Leftovers:
    """The files under the cache folders, by kind: relative path → bytes."""

    caches: dict[str, int] = field(default_factory=dict)
    temporaries: dict[str, int] = field(default_factory=dict)
    foreign: dict[str, int] = field(default_factory=dict)


def _cache_entries(store: Store) -> list[tuple[str, int, bool]]:
    """(relative path, bytes, a plain file) of every entry under CACHE_ROOT that is not a folder;
    no link is followed (a link is an entry, not a folder)."""
    if not store.local:
        infos = store.fs.get_file_info(pafs.FileSelector(store.full(CACHE_ROOT), recursive=True,
                                                         allow_not_found=True))
        return [(posixpath.relpath(i.path, store.root), i.size or 0, i.type == pafs.FileType.File)
                for i in infos if i.type != pafs.FileType.Directory]
    start = store.full(CACHE_ROOT)
    try:
        if not stat.S_ISDIR(os.lstat(start).st_mode):
            return [(CACHE_ROOT, 0, False)]  # a file or a link where the folder should be
    except FileNotFoundError:
        return []
    out = []
    for where, dirs, names in os.walk(start, followlinks=False):
        for name in names + [d for d in dirs if os.path.islink(os.path.join(where, d))]:
            path = os.path.join(where, name)
            st = os.lstat(path)
            out.append((posixpath.relpath(path, store.root), st.st_size, stat.S_ISREG(st.st_mode)))
    return sorted(out)


def job_leftovers(store: Store) -> Leftovers:
    """Every file under the job's cache folders, as a cache, a temporary or a foreign file."""
    out = Leftovers()
    for rel, size, plain in _cache_entries(store):
        if plain and _CACHE_FILE.fullmatch(rel):
            out.caches[rel] = size
        elif plain and LEFTOVER.fullmatch(posixpath.basename(rel)):
            out.temporaries[rel] = size
        else:
            out.foreign[rel] = size
    return out


def stitched(store: Store, dataset: str, planned: dict[str, list[str]]) -> list[str]:
    """The sequences of ``planned`` (sequence → its windows' names) whose finished marker holds
    every planned window: no track of theirs is left to need a cache."""
    out = []
    for sequence, windows in sorted(planned.items()):
        marker = SequenceMarker.load(store, dataset, sequence)
        if isinstance(marker, SequenceMarker) and set(windows) <= set(marker.windows):
            out.append(sequence)
    return out


def sweep_caches(store: Store, dataset: str, sequences: list[str]) -> list[str]:
    """Remove the observation caches of ``sequences`` of ``dataset``; the paths removed,
    relative. Only our cache files: a foreign file in the folder stays. Call it holding the
    catalogue's lock (or from the driver that holds it)."""
    wanted = {(dataset, s) for s in sequences}
    removed = []
    for rel in job_leftovers(store).caches:
        m = _CACHE_FILE.fullmatch(rel)
        if (m.group(1), m.group(2)) in wanted:
            store.remove(rel)  # the file itself: a link on the way is refused, never followed
            removed.append(rel)
    return removed


def _size(n: int) -> str:
    for unit, scale in (("GB", 1 << 30), ("MB", 1 << 20), ("KB", 1 << 10)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} B"


def _count(files: dict[str, int], store: Store) -> str:
    """``N (size), e.g. <the first>``."""
    return f"{len(files)} ({_size(sum(files.values()))}), e.g. {store.full(min(files))}"


def leftover_lines(store: Store, writing: bool = False) -> list[str]:
    """``mine status``'s lines on the caches, temporaries and foreign files a job left (one
    line each kind present; one line saying nothing is left otherwise). ``writing``: a writer
    holds the lock, so some may be its writes in flight."""
    left = job_leftovers(store)
    temporaries = store.temporaries()  # the job's every folder, not only the cache's
    sizes = store.fs.get_file_info([store.full(r) for r in temporaries]) if temporaries else []
    temps = {r: (i.size or 0) for r, i in zip(temporaries, sizes)}
    lines = []
    if left.caches:
        lines.append(f"observation caches: {_count(left.caches, store)} (the next `mine submit` "
                     "removes those of stitched sequences; one not stitched yet keeps them for its windows)")
    if temps:
        lines.append(f"temporary files: {len(temps)} left by unfinished writes ({_size(sum(temps.values()))}), e.g. "
                     f"{store.full(temporaries[0])} (readers skip them; the next `mine submit` removes them"
                     + ("; some may be the writes in flight" if writing else "") + ")")
    if left.foreign:
        lines.append(f"foreign files in the cache folders: {_count(left.foreign, store)} (no job wrote them and "
                     "none removes them: remove them yourself)")
    return lines or [f"left over: nothing (no observation cache, temporary or foreign file under {store.root})"]
