"""The stitch as it was before it streamed (``stitch_sequence`` up to 683372a, verbatim but for
its name): the whole sequence's chains built at once, linked, judged and sorted. The tests hold
the streaming stitch to its output, table for table (``tests/test_stitch_stream.py``)."""

from __future__ import annotations

from collections import defaultdict

import pyarrow as pa

from mining.catalog.rows import RunInfo, frame_rows, part_tube_frame, to_table, tube_row
from mining.config import JobConfig
from mining.pipeline.mine import judge
from mining.pipeline.stitch import _match, _Pieces, _splice, chain_sequence
from mining.pipeline.stitch_held import ROWS_PER_CHUNK
from mining.tubes.link import link_fragments
from mining.types import Tube, Window


def _chains(windows: list[Window], piece_window: dict[str, str], keys: dict[str, set],
            min_shared: int, position: dict[int, int]) -> list[list[tuple[str, int, int]]]:
    """Chains of matched pieces; each link (piece, first, last plan position) it contributes.

    The first piece starts at its window's core, the last ends with its window's core,
    and neighbours hand over at their splice frame (the earlier piece keeps it).
    """
    nxt: dict[str, tuple[str, int]] = {}
    has_prev: set[str] = set()
    by_window: dict[str, list[str]] = defaultdict(list)
    for p, w in sorted(piece_window.items()):
        by_window[w].append(p)
    order = sorted(windows, key=lambda w: w.core[0])
    window_of = {w.name: w for w in windows}
    for a, b in zip(order, order[1:]):
        if a.core[1] != b.core[0]:
            continue  # a failed window between them: nothing to stitch across
        for pa_, pb in _match(by_window[a.name], by_window[b.name], keys, min_shared):
            nxt[pa_] = (pb, _splice(pa_, pb, keys, a.core[1], position))
            has_prev.add(pb)
    chains = []
    for p in sorted(piece_window):
        if p in has_prev:
            continue
        first = window_of[piece_window[p]].core[0]
        chain = []
        while p in nxt:
            q, splice = nxt[p]
            chain.append((p, first, splice))
            p, first = q, splice + 1
        chain.append((p, first, window_of[piece_window[p]].core[1] - 1))
        chains.append(chain)
    return chains


def reference_stitch(windows: list[Window], tubes: pa.Table, tube_frames: pa.Table, frames: pa.Table,
                    cfg: JobConfig, run: RunInfo) -> dict[str, pa.Table]:
    """The catalogue tables of one sequence from its windows' parts."""
    frames_table, poses = chain_sequence(frames)
    pieces = _Pieces(tube_frames)
    piece_window, keys = pieces.window, pieces.keys
    tubes, windows_of = [], []
    pos = poses.position
    for links in _chains(windows, piece_window, keys, cfg.window.stitch_min_shared, pos):
        # A frame without a position lies in no stitched window's core (a failed window's
        # core, seen as a neighbour's context): no window owns it.
        rows = [r for p, lo, hi in links for r in pieces.rows(p) if r["frame"] in pos and lo <= pos[r["frame"]] <= hi]
        while rows and not rows[-1]["observed"]:
            rows.pop()
        while rows and not rows[0]["observed"]:
            rows.pop(0)
        if not rows:
            continue  # owned by no window's core: a neighbour's tube seen from the context
        windows_of.append({r["window"] for r in rows})
        tframes = [part_tube_frame(r, poses.pose[r["frame"]]) for r in rows]
        tubes.append(Tube(tube_id=0, segment=poses.segment[rows[0]["frame"]], frames=tframes))
    # Judged again (score, category, co-selection) over the whole sequence's stitched tubes:
    # a window chose among tubes cut at its context's ends, whose scores (sums over frames)
    # were cut with them.
    # Fragments of one object are linked here, over the sequence (``mining.tubes.link``), so
    # where window borders fell does not matter.
    for joined, parts in link_fragments(tubes, cfg.tubes, first_id=1):
        tubes.append(joined)
        windows_of.append(set().union(*(windows_of[i] for i in parts)))
    stitched = list(zip(judge(tubes, cfg), (len(w) for w in windows_of)))
    # Stable ids: the first inlier names the tube; ties (one observation can start several) by inliers.
    stitched.sort(key=lambda x: (x[0].tube.inlier_key(), -x[0].score.total))
    used: dict[str, int] = defaultdict(int)
    tube_rows, frame_rows_, frame_tables = [], [], []
    for mt, n_windows in stitched:
        first = mt.tube.frames[0]
        base = f"{run.dataset}/{run.sequence}/{first.frame:07d}.{first.obs_index:03d}"
        tube_id = base if used[base] == 0 else f"{base}-{used[base]}"
        used[base] += 1
        tube_rows.append(tube_row(mt, tube_id, run, n_windows))
        frame_rows_.extend(frame_rows(mt, tube_id))
        if len(frame_rows_) >= ROWS_PER_CHUNK:  # into Arrow as it goes: never every tube frame as a dict at once
            frame_tables.append(to_table(frame_rows_, "tube_frames"))
            frame_rows_ = []
    frame_tables.append(to_table(frame_rows_, "tube_frames"))
    return {"tubes": to_table(tube_rows, "tubes"), "tube_frames": pa.concat_tables(frame_tables).combine_chunks(),
            "frames": frames_table}
