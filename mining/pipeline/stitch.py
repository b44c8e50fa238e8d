"""Stitch a sequence's window parts into one catalogue: one tube per object across borders.

Each window tracked over its context, so neighbouring windows both hold a *piece* of
any tube that crosses their border, and the pieces took the same observations in the
frames both windows saw. Pieces of adjacent windows are matched one-to-one by how
many (frame, observation) inliers they share (Hungarian, at least
``window.stitch_min_shared``), and a chain of matched pieces is one tube. A window owns
its core frames; a chain hands over from one piece to the next at the shared inlier
nearest their border, so the tube is continuous where the windows meet. Score and category are
recomputed over the whole tube, and co-selection runs again over the sequence's stitched
tubes (group by group of overlapping tubes, so its cost grows with the sequence, not
with its square): selection then does not depend on where the borders fell.

Worlds: each window chained poses from its own first frame, so pieces store footpoints
in camera coordinates; here they move into the sequence's world, chained over all
frames, one world per pose segment.

The parts meet in ``concat_parts``: parts of different schemas (a part written by other
code, or planted) fail the stitch naming the part file and each column that differs.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
from scipy.optimize import linear_sum_assignment

from mining.catalog.rows import RunInfo, frame_rows, part_tube_frame, to_table, tube_row
from mining.catalog.schema import hive_file_schema, part_schema
from mining.config import JobConfig
from mining.errors import InputError
from mining.geometry.poses import chain_poses
from mining.pipeline.mine import judge
from mining.tubes.link import link_fragments
from mining.types import Tube, Window


@dataclass
class SequencePoses:
    pose: dict[int, np.ndarray]  # frame index → camera-to-world of its segment
    segment: dict[int, int]
    position: dict[int, int]  # frame index → plan position (windows count positions)


def chain_sequence(frames: pa.Table) -> tuple[pa.Table, SequencePoses]:
    """The sequence's frames table with poses chained over all frames it holds.

    A frame starts a new segment when its egomotion failed or is absent, or when the
    frame before it in the plan is missing (a failed window).
    """
    frames = frames.sort_by("position")
    cols = frames.to_pydict()
    motions = [None if T is None else np.asarray(T, np.float64).reshape(4, 4) for T in cols["T_cur_prev"]]
    chained = chain_poses(cols["position"], motions)
    poses, segments = [p for p, _ in chained], [s for _, s in chained]
    out = {k: v for k, v in cols.items() if k not in ("T_cur_prev", "segment", "pose")}
    out["segment"] = segments
    out["pose"] = [p.ravel().tolist() for p in poses]
    table = pa.Table.from_pydict(out, schema=hive_file_schema("frames"))  # write_sequence adds dataset / sequence
    return table, SequencePoses(dict(zip(cols["frame"], poses)), dict(zip(cols["frame"], segments)),
                                dict(zip(cols["frame"], cols["position"])))


def schema_differences(schema: pa.Schema, reference: pa.Schema) -> list[str]:
    """How ``schema`` ("here") differs from ``reference`` ("there"), column by column (type,
    nullability, a column missing or added, the order); empty when a table of it
    concatenates with one of ``reference``."""
    ref = {f.name: f for f in reference}
    own = {f.name: f for f in schema}
    out = [f"column {n} is missing here" for n in ref if n not in own]
    out += [f"column {n} is only here" for n in own if n not in ref]
    for n, f in own.items():
        if n in ref and not f.type.equals(ref[n].type):
            out.append(f"column {n} is {f.type} here, {ref[n].type} there")
        elif n in ref and f.nullable != ref[n].nullable:
            out.append(f"column {n} is {'' if f.nullable else 'not '}nullable here, {'' if ref[n].nullable else 'not '}"
                       "there")
    if not out and schema.names != reference.names:
        out.append("the columns are in another order")
    return out


def concat_parts(table: str, parts: list[tuple[str, pa.Table]]) -> pa.Table:
    """The windows' parts of ``table`` (each with its file's path) as one table. Parts whose
    schemas differ cannot be stitched: an InputError names a part that differs (one that
    differs from the schema this code writes, else the first that differs from the first
    part) and each column that differs."""
    if not parts:
        return to_table([], table, part=True)
    first_path, first = parts[0]
    odd = [(path, t) for path, t in parts[1:] if schema_differences(t.schema, first.schema)]
    if not odd:
        return pa.concat_tables([t for _, t in parts])
    written = part_schema(table)
    fits = {p for p, t in parts if not schema_differences(t.schema, written)}
    path, t = next(((p, t) for p, t in parts if p not in fits), odd[0])  # the odd one out
    other_path, other = next(((p, u) for p, u in parts if p in fits), (first_path, first))  # what it should match
    if other_path == path:
        other_path, other = odd[0]
    diff = "; ".join(schema_differences(t.schema, other.schema))
    raise InputError(f"this {table} part cannot be stitched with the others (there: {other_path}): {diff}; "
                     "remove it and resubmit to run its window again", path)


ROWS_PER_CHUNK = 4096  # ours: tube-frame rows held as dicts before they go into Arrow (a few MB)


class _Pieces:
    """A sequence's part tube-frame rows by piece (the part's ``tube_id``), in frame order within each
    (a stable sort, as before). A piece's rows become dicts only when its chain is built (``rows``): the
    whole sequence's rows as dicts at once were a large share of the stitch's memory (issue 42)."""

    def __init__(self, tube_frames: pa.Table):
        self.table = tube_frames
        code: dict[str, int] = {}  # piece → its number, in order of first appearance
        ids = np.array([code.setdefault(t, len(code)) for t in tube_frames.column("tube_id").to_pylist()], np.int64)
        frame = tube_frames.column("frame").to_pylist()
        self.order = np.lexsort((np.asarray(frame, np.int64), ids)) if len(ids) else np.zeros(0, np.int64)
        starts = np.flatnonzero(np.r_[True, np.diff(ids[self.order]) != 0]) if len(ids) else np.zeros(0, np.int64)
        names = list(code)
        self.span = {names[ids[self.order[a]]]: (int(a), int(b)) for a, b in zip(starts, np.r_[starts[1:], len(ids)])}
        window = tube_frames.column("window").to_pylist()
        obs, observed = tube_frames.column("obs_index").to_pylist(), tube_frames.column("observed").to_pylist()
        self.window = {p: window[self.order[a]] for p, (a, _) in self.span.items()}
        self.keys = {p: {(frame[i], obs[i]) for i in self.order[a:b] if observed[i]} for p, (a, b) in self.span.items()}

    def rows(self, piece: str) -> list[dict]:
        a, b = self.span[piece]
        return self.table.take(pa.array(self.order[a:b])).to_pylist()


def _match(a_pieces: list[str], b_pieces: list[str], keys: dict[str, set], min_shared: int) -> list[tuple[str, str]]:
    """One-to-one matches between two windows' pieces by shared inliers."""
    if not a_pieces or not b_pieces:
        return []
    owner: dict[tuple, list[int]] = defaultdict(list)
    for j, b in enumerate(b_pieces):
        for k in keys[b]:
            owner[k].append(j)
    shared = np.zeros((len(a_pieces), len(b_pieces)))
    for i, a in enumerate(a_pieces):
        for k in keys[a]:
            for j in owner.get(k, ()):
                shared[i, j] += 1
    rows, cols = linear_sum_assignment(-shared)
    return [(a_pieces[i], b_pieces[j]) for i, j in zip(rows, cols) if shared[i, j] >= min_shared]


def _splice(a: str, b: str, keys: dict[str, set], border: int, position: dict[int, int]) -> int:
    """The frame where a tube passes from piece ``a`` to the next window's piece ``b``.

    The shared inlier nearest the windows' border: both pieces took that observation, so
    the tube is continuous there, and ``b`` is past its own first inlier after it.
    """
    shared = sorted(position[f] for f, _ in keys[a] & keys[b])
    return min(shared, key=lambda p: (abs(p - border), -p))


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


def stitch_sequence(windows: list[Window], tubes: pa.Table, tube_frames: pa.Table, frames: pa.Table,
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
