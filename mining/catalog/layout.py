"""Where everything of a catalogue lives under ``--out``, and the job record ``job.json``.

One owner for every relative path a mining job reads or writes (``schemas/README.md``
draws the same tree); ``store.py`` does the I/O on them::

    job.json                                                  the job record (JobRecord)
    catalog/<table>/dataset=D/sequence=S/part-<k>.parquet     compacted tables (tubes, tube_frames, frames, windows)
    catalog/_sequences/dataset=D/sequence=S.json              a finalized sequence: which windows its catalogue holds
    manifest/dataset=D/sequence=S/<window>.parquet            the windows table, one row per window
    manifest/dataset=D/sequence=S/stitch.parquet              a sequence whose stitch failed (its row, until one succeeds)
    running/dataset=D/sequence=S/<window>.json                a window a driver has started and not finished
    parts/<table>/dataset=D/sequence=S/<window>.parquet       a window's parts before stitching
    cache/obs/dataset=D/sequence=S/<window>.pkl               a window's observations, until no track needs them

``job.json`` records the resolved config, its ``params_hash``, the run id and every
window planned so far; a job with other params is refused (``JobRecord.check``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import TYPE_CHECKING

from mining.errors import ConfigError, InputError
from mining.types import Window

if TYPE_CHECKING:
    from mining.catalog.store import Store

JOB = "job.json"
CATALOG = "catalog"
MANIFEST = "manifest"
PARTS = "parts"
CACHE = "cache/obs"
RUNNING = "running"
STITCH_ROW = "stitch"  # the ``window`` of a sequence's failed-stitch row (no window is named so: windows are S-start-end)
PART_TABLES = ("tubes", "tube_frames", "frames")  # what a tracked window writes, and a sequence stitches
# The folder of each table a query reads: the compacted tables, and the manifest as ``windows``.
TABLE_DIRS = {"tubes": f"{CATALOG}/tubes", "tube_frames": f"{CATALOG}/tube_frames", "frames": f"{CATALOG}/frames",
              "windows": MANIFEST}


def part_path(table: str, dataset: str, sequence: str, window: str) -> str:
    """A window's part of ``table`` (one of ``PART_TABLES``)."""
    return f"{PARTS}/{table}/dataset={dataset}/sequence={sequence}/{window}.parquet"


def manifest_path(dataset: str, sequence: str, window: str) -> str:
    """A window's manifest row (its row of the ``windows`` table)."""
    return f"{MANIFEST}/dataset={dataset}/sequence={sequence}/{window}.parquet"


def stitch_path(dataset: str, sequence: str) -> str:
    """The manifest row of a sequence whose stitch (finalize) failed; removed when one succeeds."""
    return f"{MANIFEST}/dataset={dataset}/sequence={sequence}/{STITCH_ROW}.parquet"


def running_path(dataset: str, sequence: str, window: str) -> str:
    """The marker of a window a driver has started (its observe or track step) and not finished."""
    return f"{RUNNING}/dataset={dataset}/sequence={sequence}/{window}.json"


def catalog_dir(table: str, dataset: str, sequence: str) -> str:
    """The folder of one sequence's compacted files of ``table``."""
    return f"{CATALOG}/{table}/dataset={dataset}/sequence={sequence}"


def catalog_file(table: str, dataset: str, sequence: str, k: int) -> str:
    """The ``k``-th compacted file of one sequence's ``table``."""
    return f"{catalog_dir(table, dataset, sequence)}/part-{k}.parquet"


def done_path(dataset: str, sequence: str) -> str:
    """The marker a finalized sequence leaves: which windows its catalogue holds."""
    return f"{CATALOG}/_sequences/dataset={dataset}/sequence={sequence}.json"


def cache_path(w: Window) -> str:
    """A window's observation cache (its core frames' observations, pickled)."""
    return f"{CACHE}/dataset={w.dataset}/sequence={w.sequence}/{w.name}.pkl"


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
            return cls(d["run_id"], d["params_hash"], d["config"], windows)
        except (ValueError, KeyError, TypeError) as e:
            raise InputError(f"job.json is not a job record ({e})", store.full(JOB)) from None

    def check(self, params_hash: str, out: str) -> None:
        """Refuse a job of other params than the catalogue at ``out`` was made with."""
        if self.params_hash != params_hash:
            raise ConfigError(f"{out} holds a catalogue made with params {self.params_hash}; this job has "
                              f"{params_hash}. Use another --out, or the same config to resume.")

    def save(self, store: Store) -> None:
        record = {"run_id": self.run_id, "params_hash": self.params_hash, "config": self.config,
                  "windows": [_window_entry(w) for w in self.windows]}
        store.write_bytes(JOB, json.dumps(record, indent=1, default=str).encode())
