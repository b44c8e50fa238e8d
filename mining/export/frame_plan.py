"""Every tube frame an export writes is one its source has: checked before DEST is touched.

A catalogue's markers vouch that its files are as the job wrote them, not that its rows agree
with the source: a ``tube_frames`` row moved to a frame the sequence never had (a tampered
file whose marker was written again) would otherwise be written by every format (YouTube-VIS
and TAO invented ``999999.jpg``). The plan of a sequence is its source's frame list
(``Source.survey``, which lists and decodes nothing); where that source is not reachable from
the root ``job.json`` records (a catalogue copied away from its data), the catalogue's own
``frames`` table stands in for it. A sequence with neither has nothing to check against.
"""

from __future__ import annotations

from pathlib import Path

import duckdb
import pyarrow as pa
import pyarrow.parquet as pq

from mining.catalog.layout import catalog_dir
from mining.catalog.store import Store
from mining.config import JobConfig
from mining.errors import InputError, MiningError
from mining.sources.base import Source

SOURCE, TABLE = "source", "frames table"  # where a sequence's plan came from (the message says which)


def _source(job: JobConfig | None) -> Source | None:
    """The job's source, or None when there is no job or its root is not reachable here."""
    if job is None:
        return None
    try:
        return job.source.open()
    except (MiningError, OSError):  # the recorded root is not here (or unreadable): the frames table stands in
        return None


def _table_frames(con: duckdb.DuckDBPyConnection, dataset: str, sequence: str) -> set[int] | None:
    try:
        rows = con.execute("SELECT frame FROM frames WHERE dataset = ? AND sequence = ?",
                           [dataset, sequence]).fetchall()
    except duckdb.Error as e:  # a damaged file (the message names it)
        raise InputError(f"cannot read the catalogue: {e}") from None
    return {r[0] for r in rows} or None


def sequence_plans(con: duckdb.DuckDBPyConnection, job: JobConfig | None,
                   sequences: set[tuple[str, str]]) -> dict[tuple[str, str], tuple[set[int], str]]:
    """(the frames, SOURCE or TABLE) per (dataset, sequence) that has a plan to check against."""
    source = _source(job)
    out: dict[tuple[str, str], tuple[set[int], str]] = {}
    for d, s in sorted(sequences):
        if source is not None and d == job.source.dataset:
            try:
                out[d, s] = set(source.survey(s).frames), SOURCE
                continue
            except (MiningError, OSError):  # the source has no such sequence here: the catalogue's table
                pass
        frames = _table_frames(con, d, s)
        if frames is not None:
            out[d, s] = frames, TABLE
    return out


def _row_file(out: str | Path, dataset: str, sequence: str, tube: str, frame: int) -> str:
    """The catalogue file that holds the ``tube_frames`` row (tube, frame): the one the message
    names; the sequence's folder when no file reads so."""
    store = Store(out)
    folders = [catalog_dir("tube_frames", dataset, sequence), catalog_dir("tube_frames", dataset, sequence, hive=True)]
    for rel in (r for f in folders for r in store.list(f)):
        try:
            with store.fs.open_input_file(store.full(rel)) as fh:
                rows = pq.read_table(fh, columns=["tube_id", "frame"])
        except (pa.ArrowInvalid, OSError, KeyError):
            continue
        if any(t == tube and f == frame for t, f in zip(rows.column("tube_id").to_pylist(),
                                                         rows.column("frame").to_pylist())):
            return store.full(rel)
    return store.full(folders[0])


def check_tube_frames(con: duckdb.DuckDBPyConnection, out: str | Path, job: JobConfig | None,
                      frames: pa.Table) -> None:
    """Refuse, naming the catalogue file, the frame, the tube and the sequence, the first
    ``tube_frames`` row among ``frames`` whose frame its sequence's plan lacks."""
    keys = set(zip(frames.column("dataset").to_pylist(), frames.column("sequence").to_pylist()))
    plans = sequence_plans(con, job, keys)
    for d, s, tube, frame in zip(*(frames.column(c).to_pylist() for c in ("dataset", "sequence", "tube_id", "frame"))):
        plan = plans.get((d, s))
        if plan is None or frame in plan[0]:
            continue
        have, where = plan
        whose = (f"the source's sequence {d}/{s} ({job.source.root or job.source.dataset})" if where == SOURCE
                 else f"the catalogue's frames table for {d}/{s} (the source is not reachable here)")
        span = f"frames {min(have)}–{max(have)}, {len(have)} in all" if have else "no frames"
        raise InputError(f"tube {tube!r} of sequence {d}/{s} has a tube_frames row on frame {frame}, which "
                         f"{whose} lacks ({span}); nothing written", _row_file(out, d, s, tube, frame), frame)
