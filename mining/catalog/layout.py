"""Where everything of a catalogue lives under ``--out``, and the job record ``job.json``.

One owner for every relative path a mining job reads or writes (``schemas/README.md``
draws the same tree); ``store.py`` does the I/O on them::

    job.json                                                  the job record (JobRecord)
    catalog/<table>/dataset=D/sequence=S/part-<k>.parquet     compacted tables (tubes, tube_frames, frames, windows)
    catalog/_sequences/dataset=D/sequence=S.json              a finalized sequence: which windows its catalogue holds
    manifest/dataset=D/sequence=S/<window>.parquet            the windows table, one row per window
    parts/<table>/dataset=D/sequence=S/<window>.parquet       a window's parts before stitching
    cache/obs/dataset=D/sequence=S/<window>.npz.zst           a window's observations, until no track needs them

Every path is built from names checked by ``mining/names.py`` (dataset, sequence, window),
so no name can leave ``--out`` or make two tables share a file; ``job.json``'s names are
checked when it is read.

``job.json`` records the resolved config, its ``params_hash``, the run id and every
window planned so far; a job with other params is refused (``JobRecord.check``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import TYPE_CHECKING

from mining.errors import ConfigError, InputError
from mining.names import check_name
from mining.types import Window

if TYPE_CHECKING:
    from mining.catalog.store import Store

JOB = "job.json"
CATALOG = "catalog"
MANIFEST = "manifest"
PARTS = "parts"
CACHE = "cache/obs"
CACHE_SUFFIX = ".npz.zst"  # the observation cache's format: mining/pipeline/cache.py
LEGACY_CACHE_SUFFIX = ".pkl"  # caches before issue 11 (pickle): never read, removed with their window's
PART_TABLES = ("tubes", "tube_frames", "frames")  # what a tracked window writes, and a sequence stitches
# The folder of each table a query reads: the compacted tables, and the manifest as ``windows``.
TABLE_DIRS = {"tubes": f"{CATALOG}/tubes", "tube_frames": f"{CATALOG}/tube_frames", "frames": f"{CATALOG}/frames",
              "windows": MANIFEST}


def _where(dataset: str, sequence: str, window: str | None = None) -> str:
    """``dataset=D/sequence=S`` (and ``/<window>``) from checked names."""
    origin = "a path under --out"
    where = f"dataset={check_name(dataset, 'dataset', origin)}/sequence={check_name(sequence, 'sequence', origin)}"
    return where if window is None else f"{where}/{check_name(window, 'window', origin)}"


def part_path(table: str, dataset: str, sequence: str, window: str) -> str:
    """A window's part of ``table`` (one of ``PART_TABLES``)."""
    if table not in PART_TABLES:
        raise ValueError(f"no part table {table!r}")
    return f"{PARTS}/{table}/{_where(dataset, sequence, window)}.parquet"


def manifest_path(dataset: str, sequence: str, window: str) -> str:
    """A window's manifest row (its row of the ``windows`` table)."""
    return f"{MANIFEST}/{_where(dataset, sequence, window)}.parquet"


def catalog_dir(table: str, dataset: str, sequence: str) -> str:
    """The folder of one sequence's compacted files of ``table``."""
    if table not in TABLE_DIRS:
        raise ValueError(f"no catalogue table {table!r}")
    return f"{CATALOG}/{table}/{_where(dataset, sequence)}"


def catalog_file(table: str, dataset: str, sequence: str, k: int) -> str:
    """The ``k``-th compacted file of one sequence's ``table``."""
    return f"{catalog_dir(table, dataset, sequence)}/part-{int(k)}.parquet"


def done_path(dataset: str, sequence: str) -> str:
    """The marker a finalized sequence leaves: which windows its catalogue holds."""
    return f"{CATALOG}/_sequences/{_where(dataset, sequence)}.json"


def cache_path(w: Window, suffix: str = CACHE_SUFFIX) -> str:
    """A window's observation cache (its core frames' observations; ``pipeline/cache.py``)."""
    return f"{CACHE}/{_where(w.dataset, w.sequence, w.name)}{suffix}"


def _window_entry(w: Window) -> dict:
    return {"dataset": w.dataset, "sequence": w.sequence, "window": w.name, "core": list(w.core),
            "context": list(w.context)}


@dataclass
class JobRecord:
    """``job.json``: the job a catalogue belongs to."""

    run_id: str
    params_hash: str
    config: dict  # the resolved JobConfig, as JobConfig.to_dict()
    windows: list[Window]  # every window planned for this catalogue, in planning order

    @classmethod
    def load(cls, store: Store) -> JobRecord | None:
        """The record in ``store``, or None when it has none."""
        if not store.exists(JOB):
            return None
        try:
            d = json.loads(store.read_bytes(JOB))
            windows = [Window(w["dataset"], w["sequence"], tuple(w["core"]), tuple(w["context"])) for w in d["windows"]]
            record = cls(d["run_id"], d["params_hash"], d["config"], windows)
        except (ValueError, KeyError, TypeError) as e:
            raise InputError(f"job.json is not a job record ({e})", store.full(JOB)) from None
        for w in windows:
            check_name(w.dataset, "dataset", "job.json", store.full(JOB))
            check_name(w.sequence, "sequence", "job.json", store.full(JOB))
        return record

    def check(self, params_hash: str, out: str) -> None:
        """Refuse a job of other params than the catalogue at ``out`` was made with."""
        if self.params_hash != params_hash:
            raise ConfigError(f"{out} holds a catalogue made with params {self.params_hash}; this job has "
                              f"{params_hash}. Use another --out, or the same config to resume.")

    def save(self, store: Store) -> None:
        record = {"run_id": self.run_id, "params_hash": self.params_hash, "config": self.config,
                  "windows": [_window_entry(w) for w in self.windows]}
        store.write_bytes(JOB, json.dumps(record, indent=1, default=str).encode())
