"""`mine render`: one sequence's source frames with its selected tubes drawn, as a video.

Each frame is re-read through the source named in ``OUT/job.json`` (as the crops export
does) and every selected tube present in it is drawn: its mask filled semi-transparently
in its own colour (``draw.tube_colours``: hues spread over the rendered tubes, fixed for a
tube through the video), the mask's outline, and a label with the short id and the category by the rule of
the tube's call (a known tube's COCO class, ``unknown``, ``clutter``, ``unclassified``). Frames where
the tube is only predicted (a gap between observations) get the outline and label without
the fill.

``--depth`` puts a depth panel beside each frame: the stereo depth of the job's own
geometry stage (its disparity step with the job's ``[geometry]``: ``depth.stereo_depth``), colour-mapped with
OpenCV's turbo map on a fixed logarithmic range (near red, far blue; no depth black) with
its legend, and the tubes' outlines. The video is then twice as wide.

The painter is ``mining/draw.py`` (the viewer's too); the container and codec are
``video.py``'s (``.mp4``: H.264 with PyAV, ``.webm``: VP8), and the written file is read back
before the command reports success. DEST follows ``dest.py``'s rules for a file: replaced
only with ``--overwrite`` and only when it is a plain file; written in a private folder beside
it and moved on; a failed render leaves DEST as it was. A bad tube fails only itself: one
whose ``tube_frames`` rows hold a malformed mask, or one of another size than the
sequence's frames (its calibration), is not drawn, and is named with the table in one line
(exit 1); when no selected tube is left, nothing is written (exit 2). A sequence with no selected
tube at all renders its frames alone, and says so (so one can see what was missed); with
``--where`` matching nothing, nothing is written (exit 1).

``--all-candidates`` draws the candidates co-selection left out too (``selected = false``),
dimmed: outline and label only, in a colour halfway to grey, under the selected tubes; so
that a new dataset's misses can be told from tubes that were never proposed.
"""

from __future__ import annotations

import contextlib
import math
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import duckdb
import numpy as np
import pyarrow as pa

from mining.catalog import safe_files
from mining.catalog.rows import decode_mask
from mining.catalog.views import connect, sql_string
from mining.checks import clamped_note
from mining.draw import Drawn, caption, draw_tubes, tube_colours
from mining.errors import InputError, MiningError, NothingMatched
from mining.export.depth import depth_colours, depth_legend, stereo_depth
from mining.export.dest import check_file, publish_file
from mining.export.selection import (category_label, job_source, left_out_line, read_job, selected_rows,
                                     without_bad_masks)
from mining.export.video import check_container, check_video, codec_note, open_video
from mining.names import check_name
from mining.progress import Ticker

DEFAULT_FPS = 10.0  # ours: frame rate when the plan's timestamps give none (KITTI records at 10 Hz)
MAX_FPS = 1000.0  # ours: `mine render --fps` at most (video containers store a rational rate)
DIM = 0.5  # ours: a candidate's colour is this far from its own hue towards DIM_GREY (dimmed, still told apart)
DIM_GREY = 128  # ours: mid grey, the dimmed colours' end


_TUBE_NAME = re.compile(r"(?P<frame>[0-9]+)\.(?P<obs>[0-9]+)(?:-(?P<dup>[0-9]+))?")  # stitch.py's FRAME.OBS[-k]


def short_id(tube_id: str) -> str:
    """``kitti/0005/0000012.003`` → ``#12:3`` (``…003-1`` → ``#12:3-1``): the first frame and
    observation, without the sequence (a render shows one sequence) or leading zeros. The ``#``
    and the colon keep it from reading as a number (12.3 as a confidence, 3.9 and 3.90 alike)."""
    last = tube_id.rsplit("/", 1)[-1]
    m = _TUBE_NAME.fullmatch(last)
    if m is None:
        return f"#{last}"
    return f"#{int(m['frame'])}:{int(m['obs'])}" + (f"-{m['dup']}" if m["dup"] else "")


def tube_caption(t: dict) -> str:
    """A render's label: the short id, then the tube's call (its class when known), with the
    posterior of the class named (``#12:3 car 0.37``, ``#4:1 unknown 0.91``, ``#7:2 unclassified``);
    clutter with its P(object) (``#5:2 clutter P(obj) 0.31``)."""
    name = category_label(t)
    if name == "clutter":
        p = t.get("object_prob")
        return f"{short_id(t['tube_id'])} clutter" + ("" if p is None or p != p else f" P(obj) {p:.2f}")
    p = t.get("category_prob")
    prob = "" if t.get("known") is None or p is None or p != p else f" {p:.2f}"
    return f"{short_id(t['tube_id'])} {name}{prob}"


def dimmed(colour: tuple[int, int, int]) -> tuple[int, int, int]:
    """``colour`` halfway to mid grey: a candidate co-selection left out."""
    return tuple(int(c + (DIM_GREY - c) * DIM) for c in colour)  # type: ignore[return-value]


def _fps(t_ns: tuple[int, ...]) -> float:
    dt = np.diff(np.asarray(t_ns, np.int64))
    dt = dt[dt > 0]
    return float(1e9 / np.median(dt)) if dt.size else DEFAULT_FPS


@dataclass
class RenderResult:
    dest: Path
    frames: int
    tubes: int  # selected tubes drawn in at least one rendered frame
    width: int
    height: int
    codec: str  # h264, avc1, mp4v or VP80
    fps: float
    seconds: float
    left_out: dict[str, str]  # tubes not drawn for a bad mask: tube id → why
    candidates: int = 0  # unselected candidates drawn (--all-candidates)
    clamped: str | None = None  # --frames past the sequence's end: what was asked and rendered (checks.clamped_note)


def check_dest(dest: Path, overwrite: bool) -> None:
    """Refuse a DEST this render may not write: a container other than ``video.CODECS``', an
    existing entry without ``overwrite``, a link or a folder at DEST (``dest.check_file``)."""
    check_container(dest)
    check_file(dest, overwrite)


def _frame_range(sequence: str, plan, frames: tuple[int, int | None] | None, mined: tuple,
                 tube_frames: pa.Table | None) -> tuple[int, int, str | None]:
    """Plan positions [start, stop) to render and the note of a clamped --frames: the range
    asked for, else the frames the catalogue mined, else those the tubes span, else all."""
    if frames is not None:
        start, stop = frames
        stop = len(plan) if stop is None else min(stop, len(plan))
        return start, stop, clamped_note(sequence, frames, len(plan), "rendered")
    if mined[2]:
        return int(mined[0]), min(int(mined[1]) + 1, len(plan)), None
    if tube_frames is None:  # no tube to draw: the whole sequence
        return 0, len(plan), None
    position = {f: p for p, f in enumerate(plan.frames)}
    spans = [p for f in tube_frames.column("frame").to_pylist() if (p := position.get(f)) is not None]
    return min(spans), max(spans) + 1, None


def render(out: str | Path, sequence: str, dest: str | Path, where: str | None = None, depth: bool = False,
           fps: float | None = None, frames: tuple[int, int | None] | None = None,
           progress: bool = True, overwrite: bool = False, all_candidates: bool = False) -> RenderResult:
    """Render ``sequence`` of catalogue ``out`` with its selected tubes (those matching
    ``where`` too, when given) to ``dest``; ``frames`` are plan positions [a, b) (default:
    the positions the catalogue mined). An existing ``dest`` is replaced only with
    ``overwrite`` (module docstring)."""
    t0 = time.perf_counter()
    dest = Path(dest)
    if fps is not None and not (math.isfinite(fps) and 0 < fps <= MAX_FPS):
        raise InputError(f"--fps must be > 0 and ≤ {MAX_FPS:g}, got {fps}")  # never "0 means the default"
    check_dest(dest, overwrite)
    check_name(sequence, "sequence", "--sequence")
    job = read_job(out)
    source = job_source(job, "render")
    dataset, root = job.source.dataset, job.source.root
    con = connect(out)
    try:
        # The selection goes through the export's predicate helper; sequence and selection
        # are checked again below whatever the predicate did.
        pred = f"dataset = {sql_string(dataset)} AND sequence = {sql_string(sequence)}"
        pred = pred if all_candidates else f"selected AND {pred}"
        tubes, tube_frames = selected_rows(con, pred if where is None else f"{pred} AND ({where})")
        mined = con.execute("SELECT min(position), max(position), count(*) FROM frames "
                            "WHERE dataset = ? AND sequence = ?", [dataset, sequence]).fetchone()
        n_tubes = con.execute("SELECT count(*) FROM tubes WHERE dataset = ? AND sequence = ?",
                              [dataset, sequence]).fetchone()[0]
        if not mined[2] and not n_tubes:
            known = [r[0] for r in con.execute("SELECT DISTINCT sequence FROM tubes UNION "
                                               "SELECT DISTINCT sequence FROM frames ORDER BY 1").fetchall()]
            raise InputError(f"sequence {sequence!r} of {dataset} is not in the catalogue (sequences: "
                             f"{', '.join(known) or 'none'})", out)
    except duckdb.Error as e:
        raise InputError(f"cannot read the catalogue: {e}", out) from None
    finally:
        con.close()
    tube_rows = [t for t in tubes.to_pylist() if (t["selected"] or all_candidates) and t["sequence"] == sequence
                 and t["dataset"] == dataset]
    if not tube_rows and where is not None:  # a sequence with no selected tube renders its frames alone
        raise NothingMatched(f"no {'candidate' if all_candidates else 'selected'} tube of sequence {sequence!r} matches"
                             + ("" if where is None else f" --where {where!r}") + "; nothing written")
    plan = source.survey(sequence)
    start, stop, clamped = _frame_range(sequence, plan, frames, mined, tube_frames if tube_rows else None)
    start = max(0, start)
    if stop <= start:
        raise InputError(f"--frames {start}:{stop} holds no frame of {sequence!r} (the plan has {len(plan)})")
    plan = source.plan(sequence, start, stop)  # refuses a frame in the range the source cannot read
    fps = _fps(plan.t_ns[start:stop]) if fps is None else fps
    h, w = plan.calib.height, plan.calib.width
    left_out: dict[str, str] = {}
    if tube_rows:  # without_bad_masks refuses when no tube is left
        tubes, tube_frames, left_out = without_bad_masks(tubes, tube_frames, lambda d, s: (h, w))
    tube_rows = [t for t in tube_rows if t["tube_id"] not in left_out]
    keep = {t["tube_id"] for t in tube_rows}

    selected = {t["tube_id"] for t in tube_rows if t["selected"]}
    colours = tube_colours(sorted(selected)) | {k: dimmed(c) for k, c in tube_colours(sorted(keep - selected)).items()}
    info = {t["tube_id"]: (tube_caption(t) if t["selected"] else f"{short_id(t['tube_id'])} candidate",
                           colours[t["tube_id"]]) for t in tube_rows}
    by_frame: dict[int, list[dict]] = {}
    for f in tube_frames.to_pylist():
        if f["tube_id"] in keep:
            by_frame.setdefault(f["frame"], []).append(f)

    matcher = far = None
    if depth:
        from mining.geometry.disparity import StereoMatcher

        matcher, far = StereoMatcher(job.geometry.stereo, plan.calib.bf), job.geometry.stereo.max_depth_m

    # 4:2:0 video needs even sides: an odd one gets a black row / column (KITTI's 375 rows → 376).
    width = 2 * w if depth else w
    size = (width + width % 2, h + h % 2)
    drawn: set[str] = set()  # the tubes present in the rendered frames

    def paint(img: np.ndarray, items: list[Drawn], fill: bool = True) -> np.ndarray:
        """The candidates (outlines only) first, the selected tubes over them."""
        img = draw_tubes(img, [it for it in items if it.tube_id not in selected], fill=False)
        return draw_tubes(img, [it for it in items if it.tube_id in selected], fill=fill)

    def write(tmp: Path) -> str:
        """The video into ``tmp``, read back; its codec."""
        writer = open_video(tmp, fps, size)
        bar = Ticker(f"mine render {sequence}", stop - start) if progress else None
        try:
            for k, pos in enumerate(range(start, stop)):
                frame = source.read_frame(plan, pos)
                if frame.left.shape[:2] != (h, w):
                    raise InputError(f"image of {frame.left.shape[1]}×{frame.left.shape[0]} where the calibration "
                                     f"says {w}×{h}", root, frame.index)
                items = []
                for f in by_frame.get(frame.index, []):
                    label, colour = info[f["tube_id"]]
                    mask = decode_mask(f, (h, w), root)
                    items.append(Drawn(f["tube_id"], label, colour, mask, tuple(f["bbox"]), f["observed"]))
                    drawn.add(f["tube_id"])
                left = paint(cv2.cvtColor(frame.left, cv2.COLOR_RGB2BGR), items)
                n_sel = sum(it.tube_id in selected for it in items)
                more = f", {len(items) - n_sel} candidates" if all_candidates else ""
                caption(left, f"{dataset}/{sequence} frame {frame.index}  {n_sel} tubes{more}")
                if matcher is not None:
                    panel = paint(depth_colours(stereo_depth(matcher, frame, far), far), items, fill=False)
                    depth_legend(panel, far)
                    left = np.hstack([left, panel])
                writer.write(cv2.copyMakeBorder(left, 0, size[1] - left.shape[0], 0, size[0] - left.shape[1],
                                                cv2.BORDER_CONSTANT, value=(0, 0, 0)))
                if bar is not None:
                    bar.tick(k + 1)
        except BaseException:
            with contextlib.suppress(Exception):
                writer.close()
            raise
        if bar is not None:
            bar.close()
        try:
            writer.close()
        except Exception as e:
            raise MiningError(f"the video for {dest} did not finish writing: {e}") from None
        check_video(tmp, stop - start, size)
        return writer.codec

    codec = publish_file(dest, overwrite, write)
    return RenderResult(dest, stop - start, len(drawn & selected), size[0], size[1], codec, fps,
                        time.perf_counter() - t0, left_out, len(drawn - selected), clamped)


def run_render(out: str | Path, sequence: str, dest: str | Path, where: str | None = None, depth: bool = False,
               fps: float | None = None, frames: tuple[int, int | None] | None = None, overwrite: bool = False,
               all_candidates: bool = False) -> int:
    """`mine render`: 0 on success; 1 when tubes with a bad mask were left out (one line on
    standard error names them); NothingMatched (``cli.main``: exit 1) when no tube matches; a
    MiningError otherwise (``cli.main``: one line, exit status 2)."""
    try:
        r = render(out, sequence, dest, where, depth, fps, frames, overwrite=overwrite, all_candidates=all_candidates)
    except MiningError:
        raise
    except duckdb.Error as e:  # a damaged catalogue: DuckDB's message names it
        raise MiningError(str(e)) from None
    except OSError as e:  # the system's error from a writer (a full disk…): one line naming the file
        raise safe_files.write_error(e, e.filename or dest) from None
    if r.clamped:
        print(f"mine render: {r.clamped}")
    if not r.tubes and not r.candidates:
        print(f"mine render: sequence {sequence!r} has no {'candidate' if all_candidates else 'selected'} tube: the "
              f"video shows its frames alone" + ("" if all_candidates else " (--all-candidates draws the candidates)"))
    cands = f" and {r.candidates} unselected candidates" if all_candidates else ""
    print(f"mine render: {r.frames} frames, {r.tubes} tubes{cands}, {r.width}×{r.height} {r.codec} at {r.fps:g} fps → "
          f"{r.dest} ({r.seconds:.1f} s){codec_note(r.codec)}")
    if r.left_out:
        print(f"mine render: {left_out_line(r.left_out, str(r.dest))}", file=sys.stderr)
        return 1
    return 0
