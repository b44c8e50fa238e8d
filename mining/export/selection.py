"""What every product reads of a catalogue: the job that made it, the rows a predicate
selects, and the groupings the formats share.

* ``read_job`` — the typed config of ``OUT/job.json`` (``JobRecord.job_config``), None for a
  catalogue without one; ``job_source`` opens its source (images are re-read through it)
  and ``export_settings`` gives its ``[export]`` section.
* ``selected_rows`` — (tubes, tube_frames) of the tubes matching a ``--where`` predicate,
  through the read-only checks of ``catalog/views.py``; ``mined_frames`` — the frames the
  catalogue mined per sequence (the videos of YouTube-VIS and TAO).
* ``by_sequence``, ``frames_by_tube``, ``category_label``, ``frame_digits`` — the groupings
  and names the formats share.
"""

from __future__ import annotations

from pathlib import Path

import duckdb
import pyarrow as pa

from mining.catalog.layout import JOB, JobRecord
from mining.catalog.predicate import tubes_query
from mining.catalog.store import Store
from mining.catalog.views import execute_read_only
from mining.config import ExportConfig, JobConfig
from mining.errors import InputError
from mining.names import check_name
from mining.sources.base import Source

MIN_FRAME_DIGITS = 6  # ours: frame numbers in file names are zero-padded to at least this width
# What a predicate can cause: unknown names, wrong types, a value that does not convert. The rest
# (a damaged table, a full disk) is the catalogue's, not the predicate's.
PREDICATE_ERRORS = (duckdb.ParserException, duckdb.BinderException, duckdb.CatalogException,
                    duckdb.ConversionException, duckdb.TypeMismatchException, duckdb.OutOfRangeException)


def read_job(out: str | Path) -> JobConfig | None:
    """The typed config of the job recorded in ``OUT/job.json``, or None when the catalogue
    has none; ``UnreadableRecord`` (an InputError naming the file) when it does not read, and
    an InputError when ``out`` is no folder at all (as ``views.connect`` says)."""
    store = Store(out)
    if not store.root_exists():
        raise InputError("catalogue folder not found", out)
    record = JobRecord.load(store)
    return None if record is None else record.job_config(store.full(JOB))


def job_source(job: JobConfig | None, what: str) -> Source:
    """The source adapter of the job that made a catalogue (``SourceConfig.open``): images
    are re-read through it. ``what`` names the product that needs it, for the message."""
    if job is None:
        raise InputError(f"{what} needs the source named in job.json (source.dataset, source.root)")
    return job.source.open()


def export_settings(job: JobConfig | None) -> ExportConfig:
    """The job's ``[export]`` section; ExportConfig's defaults without a job record."""
    return ExportConfig() if job is None else job.export


def selected_rows(con: duckdb.DuckDBPyConnection, where: str) -> tuple[pa.Table, pa.Table]:
    """(tubes, tube_frames) of the tubes matching ``where``, frames in (tube, frame) order.

    ``where`` is parsed as one expression (``predicate.tubes_query``) and both queries run
    through the read-only checks on ``con`` (a ``views.connect`` connection)."""
    tubes_sql = tubes_query(where)
    try:
        tubes = execute_read_only(con, f"SELECT * FROM ({tubes_sql}) ORDER BY dataset, sequence, t_start, tube_id")
        frames = execute_read_only(con, f"SELECT f.* FROM tube_frames AS f SEMI JOIN ({tubes_sql}) AS t "
                                        "USING (dataset, sequence, tube_id) ORDER BY f.dataset, f.sequence, f.tube_id, f.frame")
        return tubes.to_arrow_table(), frames.to_arrow_table()
    except PREDICATE_ERRORS as e:
        raise InputError(f"bad --where predicate {where!r}: {e}") from None
    except duckdb.Error as e:  # a damaged or missing file (the message names it), out of memory, …
        raise InputError(f"cannot read the catalogue: {e}") from None


def mined_frames(con: duckdb.DuckDBPyConnection, tubes: pa.Table) -> dict[tuple[str, str], list[int]]:
    """The frames the catalogue mined, per (dataset, sequence) of ``tubes``, in frame order."""
    seqs = {(d, s) for d, s in zip(tubes.column("dataset").to_pylist(), tubes.column("sequence").to_pylist())}
    out: dict[tuple[str, str], list[int]] = {}
    for d, s, f in con.execute("SELECT dataset, sequence, frame FROM frames ORDER BY dataset, sequence, frame").fetchall():
        if (d, s) in seqs:
            out.setdefault((d, s), []).append(f)
    return out


def category_label(tube: dict) -> str:
    """A tube's category by the rule of its ``known`` flag: a known tube's COCO class,
    ``unknown`` when classified as none of them, ``unclassified`` when no classifier looked."""
    if tube["known"] is None:
        return "unclassified"
    return tube["category"] if tube["known"] else "unknown"


def by_sequence(tubes: pa.Table) -> dict[tuple[str, str], list[dict]]:
    """The tubes per (dataset, sequence), both checked names (they become file names)."""
    out: dict[tuple[str, str], list[dict]] = {}
    checked: set[tuple[str, str]] = set()
    for t in tubes.to_pylist():
        key = (t["dataset"], t["sequence"])
        if key not in checked:
            check_name(key[0], "dataset", "the catalogue")
            check_name(key[1], "sequence", "the catalogue")
            checked.add(key)
        out.setdefault(key, []).append(t)
    return out


def frames_by_tube(frames: pa.Table) -> dict[str, list[dict]]:
    """The tube_frames rows per tube id, in the order given."""
    out: dict[str, list[dict]] = {}
    for f in frames.to_pylist():
        out.setdefault(f["tube_id"], []).append(f)
    return out


def frame_digits(frames) -> int:
    """Width of zero-padded frame numbers in file names: the largest frame's digits, at least
    MIN_FRAME_DIGITS (so names sort in frame order)."""
    return max(MIN_FRAME_DIGITS, len(str(max(frames, default=0))))
