"""`mine export`: the tubes matching a SQL predicate, in formats other tools read.

The formats (``registry.FORMATS``, one module each): ``kitti`` and ``kitti-mots``
(``kitti.py``), ``crops`` (``crops.py``), ``youtube-vis`` and ``tao`` (``video_json.py``), ``burst``
(``burst.py``), whose dataset and results files TrackEval reads; ``fiftyone`` (``fiftyone_video.py``)
and ``rerun`` (``rerun_rrd.py``).
Boxes: the catalogue keeps x1, y1, x2, y2; COCO-style formats (YouTube-VIS, TAO, the crops
index's ``bbox_xywh``) get x, y, width, height.

DEST follows ``dest.py``'s rules for a folder: empty, or with ``--overwrite`` an earlier
export's (its record names what is replaced); the writer fills a private folder that is
moved in only when it has finished. A predicate that matches no tube writes and removes
nothing and exits 1.

A bad tube fails only itself: a tube whose ``tube_frames`` rows hold a malformed mask, or one
of another size than the sequence's frames (``selection.without_bad_masks``), is left out of
every format that writes masks (``kitti`` writes boxes only), named with the table in one
line on standard error and in DEST's record (``left_out``); the others are written and the
command exits 1. When every tube asked for is bad, nothing is written (exit 2).

Names read from the catalogue are data: the dataset and sequence names and the tube ids
must pass ``mining/names.py`` before a file name is made from them, two tubes may not
share a folder, and every file written must resolve inside DEST.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import duckdb
import pyarrow as pa
import pyarrow.compute as pc

from mining.catalog import safe_files
from mining.catalog.labels import VERDICTS, utc_text
from mining.catalog.views import connect
from mining.errors import InputError, MiningError, NothingMatched
from mining.export.dest import check_folder, publish_folder
from mining.export.frame_plan import check_tube_frames
from mining.export.registry import FORMATS, VIDEO_FORMATS
from mining.export.selection import (frame_rates, frame_sizes, left_out_line, mined_frames, read_job,
                                     selected_rows, sequence_frames, without_bad_masks)

LABELS_FILE = "tube_labels.json"  # beside every format's files: the exported tubes' labels
CATEGORY_FROM = ("category", "tag")  # --category-from: the mined category, or the user's tag where there is one
ROWS_PASSED = ("video_frames", "video_rates", "frame_rows")  # options that carry catalogue rows, not the user's choices
LEFT_OUT = 1  # exit status: written, but tubes with a bad mask were left out (as `mine submit` with a failed window)


def export(out: str | Path, where: str, fmt: str, dest: str | Path, margin: float | None = None,
           images: bool = False, overwrite: bool = False,
           unknown_class: int | None = None, category_from: str = "category") -> tuple[int, int, dict[str, str]]:
    """Export the tubes of catalogue ``out`` matching ``where``; (tubes, items written, tubes
    left out for a bad mask: tube id → why).

    DEST must be empty (or absent); with ``overwrite`` the entries an earlier export
    recorded in DEST's record are replaced (nothing else in DEST, nothing outside it), once
    the new export is complete in a private folder (``dest.py``). NothingMatched,
    before anything is written or removed, when no tube matches."""
    if fmt not in FORMATS:
        raise InputError(f"unknown export format {fmt!r}; one of {', '.join(FORMATS)}")
    if category_from not in CATEGORY_FROM:
        raise InputError(f"--category-from {category_from!r}: one of {', '.join(CATEGORY_FROM)}")
    form = FORMATS[fmt]
    options: dict = {}
    if margin is not None:
        if "margin" not in form.options:
            raise InputError("--margin applies to --format crops only")
        options["margin"] = margin
    if unknown_class is not None:
        if "unknown_class" not in form.options:
            raise InputError("--unknown-class applies to --format kitti-mots only")
        options["unknown_class"] = unknown_class
    if images:
        if not form.video:
            raise InputError(f"--images applies to --format {', '.join(VIDEO_FORMATS)} only")
        options["images"] = True
    dest = Path(dest)
    replaced = check_folder(dest, overwrite)
    job = read_job(out)
    con = connect(out)
    try:
        tubes, frames = selected_rows(con, where)
        if not tubes.num_rows:
            raise NothingMatched(f"no tube matches --where {where!r}; nothing written")
        check_tube_frames(con, out, job, frames)  # before DEST is touched: a frame the source lacks is refused
        if category_from == "tag":
            tubes = category_from_tag(tubes)
        left_out: dict[str, str] = {}
        if form.masks:
            sizes = frame_sizes(con, tubes)
            tubes, frames, left_out = without_bad_masks(tubes, frames, lambda d, s: sizes.get((d, s)))
        if form.video:
            options["video_frames"] = mined_frames(con, tubes)
        if "video_rates" in form.options:
            options["video_rates"] = frame_rates(con, tubes)
        if "frame_rows" in form.options:
            options["frame_rows"] = sequence_frames(con, tubes)
    finally:
        con.close()
    write = form.load()

    def record(n: int) -> dict:
        return {"format": fmt, "catalogue": str(out), "where": where, "tubes": tubes.num_rows, "items": n,
                "options": {k: v for k, v in options.items() if k not in ROWS_PASSED}} | (
                    {"left_out": left_out} if left_out else {})

    def write_all(staging: Path) -> int:
        n = write(tubes, frames, job, staging, **options)
        safe_files.write_atomic(staging, LABELS_FILE, labels_json(tubes))
        return n

    n = publish_folder(dest, replaced, write_all, record)
    return tubes.num_rows, n, left_out


def category_from_tag(tubes: pa.Table) -> pa.Table:
    """``tubes`` whose tagged rows carry their tag (``tube_labels.tag``, the most recent) as the
    category, as a known class: the user's decision is the label the formats write."""
    tagged = pc.is_valid(tubes.column("tag"))
    category = pc.if_else(tagged, tubes.column("tag"), tubes.column("category"))
    known = pc.if_else(tagged, pa.scalar(True), tubes.column("known"))
    tubes = tubes.set_column(tubes.schema.get_field_index("category"), "category", category)
    if "call" in tubes.schema.names:
        call = pc.if_else(tagged, pa.scalar("known"), tubes.column("call"))
        tubes = tubes.set_column(tubes.schema.get_field_index("call"), "call", call)
    return tubes.set_column(tubes.schema.get_field_index("known"), "known", known)


def labels_json(tubes: pa.Table) -> bytes:
    """LABELS_FILE: each exported tube's id with its labels (views.sql ``tube_labels``), so the
    decisions travel with every format; tubes without labels are listed too (verdict null)."""
    # labelled_via / source_tube / source_distance: a propagated label's origin (mine label --like)
    rows = tubes.select(["tube_id", "verdict", "tags", "tag", "labelled_at", "labelled_by", "labelled_via",
                         "source_tube", "source_distance"]).to_pylist()
    for r in rows:
        r["labelled_at"] = utc_text(r["labelled_at"])
    return (json.dumps({"about": "mine export: the labels of the exported tubes (tube_labels in the catalogue); "
                                 "verdict one of " + ", ".join(VERDICTS) + "; times UTC",
                        "tubes": rows}, indent=1) + "\n").encode()


def run_export(out: str | Path, where: str, fmt: str, dest: str | Path, margin: float | None = None,
               images: bool = False, overwrite: bool = False, unknown_class: int | None = None,
               category_from: str = "category") -> int:
    """`mine export`: 0 on success; LEFT_OUT (1) when tubes with a bad mask were left out (one
    line on standard error names them); NothingMatched (``cli.main``: exit 1) when no tube
    matches; a MiningError otherwise (``cli.main``: one line, exit status 2)."""
    try:
        n_tubes, n_items, left_out = export(out, where, fmt, dest, margin, images, overwrite, unknown_class,
                                            category_from)
    except MiningError:
        raise
    except duckdb.Error as e:  # a damaged catalogue: DuckDB's message names it
        raise MiningError(str(e)) from None
    except OSError as e:  # a writer that raised the system's error (a full disk…): one line naming the file
        raise safe_files.write_error(e, e.filename or dest) from None
    print(f"mine export: {n_tubes} tubes, {n_items} {FORMATS[fmt].items} → {dest}")
    if left_out:
        print(f"mine export: {left_out_line(left_out, str(dest))}", file=sys.stderr)
        return LEFT_OUT
    return 0
