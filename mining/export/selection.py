"""What every product reads of a catalogue: the job that made it, the rows a predicate
selects, and the groupings the formats share.

* ``read_job`` — the typed config of ``OUT/job.json`` (``JobRecord.job_config``), None for a
  catalogue without one; ``job_source`` opens its source (images are re-read through it)
  and ``export_settings`` gives its ``[export]`` section.
* ``selected_rows`` — (tubes, tube_frames) of the tubes matching a ``--where`` predicate,
  through the read-only checks of ``catalog/views.py``; ``mined_frames`` — the frames the
  catalogue mined per sequence (the videos of YouTube-VIS, TAO and BURST), ``frame_rates``
  their rate.
* ``frame_sizes`` and ``without_bad_masks`` — a bad tube fails only itself: a tube with a
  ``tube_frames`` row whose mask is malformed or not of its frames' size (``rows.mask_rle``)
  is left out of what is written and named (``left_out_line``); when every tube asked for
  is bad, nothing is written.
* ``by_sequence``, ``frames_by_tube``, ``tube_call``, ``category_label``, ``frame_digits`` — the groupings
  and names the formats share.
* ``Video``, ``videos``, ``video_tubes`` — the tubes grouped as videos, one per sequence, its
  frames the ones the catalogue mined (YouTube-VIS, TAO, BURST, FiftyOne, Rerun).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import duckdb
import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from mining.catalog.layout import JOB
from mining.catalog.predicate import PREDICATE_ERRORS, tubes_query
from mining.catalog.records import JobRecord
from mining.catalog.rows import MASK_TABLE, BadMask, mask_rle
from mining.catalog.store import Store
from mining.catalog.views import execute_read_only
from mining.config import ExportConfig, JobConfig
from mining.errors import InputError
from mining.names import check_name
from mining.sources.base import Source

MIN_FRAME_DIGITS = 6  # ours: frame numbers in file names are zero-padded to at least this width


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


def frame_rates(con: duckdb.DuckDBPyConnection, tubes: pa.Table) -> dict[tuple[str, str], float]:
    """Frames per second per (dataset, sequence) of ``tubes``: one over the median interval
    of the mined frames' timestamps (``frames.t_ns``); a sequence with fewer than two
    increasing timestamps has none."""
    seqs = {(d, s) for d, s in zip(tubes.column("dataset").to_pylist(), tubes.column("sequence").to_pylist())}
    times: dict[tuple[str, str], list[int]] = {}
    for d, s, t in con.execute("SELECT dataset, sequence, t_ns FROM frames WHERE t_ns IS NOT NULL "
                               "ORDER BY dataset, sequence, frame").fetchall():
        if (d, s) in seqs:
            times.setdefault((d, s), []).append(t)
    out = {}
    for key, t in times.items():
        dt = np.diff(np.asarray(t, np.int64))
        dt = dt[dt > 0]
        if dt.size:
            out[key] = float(1e9 / np.median(dt))
    return out


def sequence_frames(con: duckdb.DuckDBPyConnection, tubes: pa.Table) -> dict[tuple[str, str], list[dict]]:
    """The ``frames`` rows (frame, t_ns, segment, pose) per (dataset, sequence) of ``tubes``,
    in frame order."""
    seqs = {(d, s) for d, s in zip(tubes.column("dataset").to_pylist(), tubes.column("sequence").to_pylist())}
    out: dict[tuple[str, str], list[dict]] = {}
    try:
        rows = con.execute("SELECT dataset, sequence, frame, t_ns, segment, pose FROM frames "
                           "ORDER BY dataset, sequence, frame").fetchall()
    except duckdb.Error as e:  # a damaged file (the message names it)
        raise InputError(f"cannot read the catalogue: {e}") from None
    for d, s, frame, t_ns, segment, pose in rows:
        if (d, s) in seqs:
            out.setdefault((d, s), []).append({"frame": frame, "t_ns": t_ns, "segment": segment, "pose": pose})
    return out


def frame_sizes(con: duckdb.DuckDBPyConnection, tubes: pa.Table) -> dict[tuple[str, str], tuple[int, int]]:
    """The catalogue's frame size (height, width) per (dataset, sequence) of ``tubes``: the
    size most of the sequence's masks share, over all its ``tube_frames`` rows (the catalogue
    records no image size; every mask of a sequence is drawn on its frames)."""
    seqs = {(d, s) for d, s in zip(tubes.column("dataset").to_pylist(), tubes.column("sequence").to_pylist())}
    counted: dict[tuple[str, str], tuple[int, int, int]] = {}
    try:
        rows = con.execute(f"SELECT dataset, sequence, rle_h, rle_w, count(*) FROM {MASK_TABLE} "
                           "GROUP BY ALL ORDER BY ALL").fetchall()
    except duckdb.Error as e:  # a damaged file (the message names it)
        raise InputError(f"cannot read the catalogue: {e}") from None
    for d, s, h, w, n in rows:
        if (d, s) in seqs and n > counted.get((d, s), (0, 0, 0))[0]:
            counted[(d, s)] = (n, h, w)
    return {k: (h, w) for k, (_, h, w) in counted.items()}


def _fault(e: BadMask, row: dict, size: tuple[int, int] | None) -> str:
    """Why a row's mask cannot be drawn, in a few words: the frame and the size or problem."""
    if e.mismatch and size is not None:
        return f"frame {row['frame']}: a {row['rle_h']}×{row['rle_w']} mask on the sequence's {size[0]}×{size[1]} frames"
    return f"frame {row['frame']}: a malformed mask ({e.problem})"


def without_bad_masks(tubes: pa.Table, frames: pa.Table,
                      size_of: Callable[[str, str], tuple[int, int] | None]) -> tuple[pa.Table, pa.Table, dict[str, str]]:
    """(tubes, tube_frames, left out) without the tubes that have a ``tube_frames`` row whose
    mask is malformed or, against ``size_of(dataset, sequence)`` (height, width; None: not
    compared), of another size; left out: tube id → why (its first bad row). An InputError
    naming them when no tube is left: nothing is then written."""
    left_out: dict[str, str] = {}
    for row in frames.to_pylist():
        tube = row["tube_id"]
        if tube in left_out:
            continue
        size = size_of(row["dataset"], row["sequence"])
        try:
            mask_rle(row, size)
        except BadMask as e:
            left_out[tube] = _fault(e, row, size)
    if not left_out:
        return tubes, frames, left_out
    bad = pa.array(sorted(left_out), pa.string())
    tubes = tubes.filter(pc.invert(pc.is_in(tubes.column("tube_id"), bad)))
    frames = frames.filter(pc.invert(pc.is_in(frames.column("tube_id"), bad)))
    if not tubes.num_rows:
        raise InputError(f"{_bad_tubes(left_out)}: no tube is left to write; nothing written")
    return tubes, frames, left_out


LEFT_OUT_SHOWN = 5  # ours: tubes a left-out line names one by one (then "and N more")


def _bad_tubes(left_out: dict[str, str]) -> str:
    names = [f"{t} ({why})" for t, why in sorted(left_out.items())[:LEFT_OUT_SHOWN]]
    more = len(left_out) - len(names)
    tubes = "tube" if len(left_out) == 1 else "tubes"
    return (f"{len(left_out)} {tubes} with a bad mask in the {MASK_TABLE} table: {'; '.join(names)}"
            + (f"; and {more} more" if more else ""))


def left_out_line(left_out: dict[str, str], written: str) -> str:
    """The one line that says which tubes were left out of ``written`` (what the rest went to)
    and why."""
    return f"left out {_bad_tubes(left_out)}; the other tubes are written to {written}"


def tube_call(tube: dict) -> str:
    """A catalogue row's call (``mining.types.CALLS``; the rule: ``mining.score.call``). Rows
    written before the ``call`` column read it from ``known`` as they were written: false is
    unknown, null unclassified."""
    call = tube.get("call")
    if call is not None:
        return call
    return "unclassified" if tube["known"] is None else "known" if tube["known"] else "unknown"


def category_label(tube: dict) -> str:
    """A tube's label by its call: a known tube's COCO class, else the call itself
    (``unknown``, ``clutter`` or ``unclassified``)."""
    call = tube_call(tube)
    return tube["category"] if call == "known" else call


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


def video_name(dataset: str, sequence: str) -> str:
    """``<dataset>_<sequence>``: both are checked names (``by_sequence``), so this is one."""
    return f"{dataset}_{sequence}"


class Video:
    """One sequence as a video: its frames (the catalogue's, in frame order), size and tubes."""

    def __init__(self, vid: int, dataset: str, sequence: str, frames: list[int], tubes: list[dict],
                 per_tube: dict[str, list[dict]]):
        self.id, self.dataset, self.sequence, self.tubes = vid, dataset, sequence, tubes
        self.name = video_name(dataset, sequence)
        sizes = {(f["rle_h"], f["rle_w"]) for t in tubes for f in per_tube.get(t["tube_id"], [])}
        if len(sizes) != 1:
            raise InputError(f"{dataset}/{sequence}: the tubes' masks have {len(sizes)} sizes {sorted(sizes)}; "
                             "a video has one")
        self.height, self.width = sizes.pop()
        seen = {f["frame"] for t in tubes for f in per_tube.get(t["tube_id"], [])}
        self.frames = sorted(set(frames) | seen)
        self.digits = frame_digits(self.frames)

    def image_name(self, frame: int) -> str:
        """``<frame, zero-padded>.jpg``."""
        return f"{frame:0{self.digits}d}.jpg"

    def file_name(self, frame: int) -> str:
        return f"{self.name}/{self.image_name(frame)}"


def videos(tubes: pa.Table, frames: pa.Table, video_frames: dict[tuple[str, str], list[int]]) -> list[Video]:
    """One Video per sequence of ``tubes``, numbered from 1; a sequence the ``frames`` table
    lacks spans its tubes' frames."""
    per_tube = frames_by_tube(frames)
    out = []
    for vid, ((dataset, sequence), seq_tubes) in enumerate(by_sequence(tubes).items(), start=1):
        out.append(Video(vid, dataset, sequence, video_frames.get((dataset, sequence), []), seq_tubes, per_tube))
    return out


def annotated(frames: list[dict], observed_only: bool) -> dict[int, dict]:
    """A tube's rows by frame, the frames it is annotated on (observed ones, or all)."""
    return {f["frame"]: f for f in frames if f["observed"] or not observed_only}


def video_tubes(vids: list[Video], frames: pa.Table, job: JobConfig | None) -> Iterator[tuple[Video, dict, dict[int, dict]]]:
    """(video, tube, its annotated rows by frame) of every tube, video by video."""
    observed_only = export_settings(job).observed_only
    per_tube = frames_by_tube(frames)
    for v in vids:
        for t in v.tubes:
            yield v, t, annotated(per_tube.get(t["tube_id"], []), observed_only)
