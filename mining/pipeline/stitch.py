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

The stitch streams (``stitch_windows``): the tube-frame parts are read one window at a time in
core order, a chain the next window does not extend becomes a tube, and tubes are linked, judged and
turned into rows group by group once no tube still to come can touch them (``stitch_held``); the
co-selection and the final order run over the rows at the end. Its peak no longer grows with the
sequence's tubes and their frames as objects, only with their rows (docs/RESULTS.md, issue 42).

The parts meet in ``concat_parts`` / ``check_parts``: parts of different schemas (a part written by other
code, or planted) fail the stitch naming the part file and each column that differs.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from scipy.optimize import linear_sum_assignment

from mining.catalog.rows import RunInfo, part_tube_frame, to_table
from mining.catalog.schema import hive_file_schema, part_schema
from mining.config import JobConfig
from mining.errors import InputError
from mining.geometry.poses import chain_poses
from mining.pipeline.stitch_held import Held, finish
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
    part) and each column that differs (``check_parts``)."""
    if not parts:
        return to_table([], table, part=True)
    check_parts(table, [(path, t.schema) for path, t in parts])
    return pa.concat_tables([t for _, t in parts])


def check_parts(table: str, parts: list[tuple[str, pa.Schema]]) -> None:
    """``concat_parts``' check on the parts' schemas alone (each with its file's path): the stitch
    reads the tube-frame parts one window at a time, after every schema has passed."""
    if not parts:
        return
    first_path, first = parts[0]
    odd = [(path, t) for path, t in parts[1:] if schema_differences(t, first)]
    if not odd:
        return
    written = part_schema(table)
    fits = {p for p, t in parts if not schema_differences(t, written)}
    path, t = next(((p, t) for p, t in parts if p not in fits), odd[0])  # the odd one out
    other_path, other = next(((p, u) for p, u in parts if p in fits), (first_path, first))  # what it should match
    if other_path == path:
        other_path, other = odd[0]
    diff = "; ".join(schema_differences(t, other))
    raise InputError(f"this {table} part cannot be stitched with the others (there: {other_path}): {diff}; "
                     "remove it and resubmit to run its window again", path)


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


@dataclass
class _Chain:
    """A chain of matched pieces whose last piece the next window may still extend."""

    name: str  # its first piece: the batch stitch ordered chains by it
    start: int  # the plan position it starts at, its first window's core start: none of its rows is earlier
    first: int  # the plan position its last piece's share starts at
    last: str  # its last piece
    rows: list[dict] = field(default_factory=list)  # its earlier pieces' shares


def stitch_sequence(windows: list[Window], tubes: pa.Table, tube_frames: pa.Table, frames: pa.Table,
                    cfg: JobConfig, run: RunInfo) -> dict[str, pa.Table]:
    """The catalogue tables of one sequence from its windows' parts, all given at once
    (``stitch_windows`` reads them one window at a time; ``tubes`` is not needed)."""
    by_window = tube_frames.column("window")
    return stitch_windows(windows, lambda w: tube_frames.filter(pc.equal(by_window, w.name)), frames, cfg, run)


def stitch_windows(windows: list[Window], read_part: Callable[[Window], pa.Table], frames: pa.Table,
                   cfg: JobConfig, run: RunInfo) -> dict[str, pa.Table]:
    """The catalogue tables of one sequence, its windows' tube-frame parts read in core order
    (``read_part``), each dropped once the next window's pieces are matched against it.

    A chain that the next window does not extend is closed into a tube; tubes wait in
    ``stitch_held.Held`` until no tube still to come can start before they end, then are linked,
    judged and turned into rows group by group; the co-selection and the order run at the end
    over the rows (``stitch_held.finish``). The output is the batch stitch's, bit for bit
    (``tests/test_stitch_stream.py``).
    """
    frames_table, poses = chain_sequence(frames)
    held = Held(cfg, run, poses.position)
    order = sorted(windows, key=lambda w: w.core[0])
    chains: dict[str, _Chain] = {}  # open chains by their last piece
    prev, prev_pieces = None, None
    for k, w in enumerate(order):
        pieces = _Pieces(read_part(w))
        matched: dict[str, tuple[str, int]] = {}
        if prev is not None and prev.core[1] == w.core[0]:  # else a failed window between: nothing to stitch across
            keys = {**prev_pieces.keys, **pieces.keys}
            for a, b in _match(sorted(prev_pieces.span), sorted(pieces.span), keys, cfg.window.stitch_min_shared):
                matched[a] = (b, _splice(a, b, keys, prev.core[1], poses.position))
        chains = _advance(chains, matched, prev, prev_pieces, poses, held)
        extended = {b for b, _ in matched.values()}
        chains.update((p, _Chain(p, w.core[0], w.core[0], p)) for p in sorted(pieces.span) if p not in extended)
        after = order[k + 1].core[0] if k + 1 < len(order) else math.inf
        held.settle_before(min([after, *(c.start for c in chains.values())]))
        prev, prev_pieces = w, pieces
    _advance(chains, {}, prev, prev_pieces, poses, held)
    held.settle_before(math.inf)
    tubes, tube_frames = finish(held, cfg)
    return {"tubes": tubes, "tube_frames": tube_frames, "frames": frames_table}


def _advance(chains: dict[str, _Chain], matched: dict[str, tuple[str, int]], window: Window | None,
             pieces: _Pieces | None, poses: SequencePoses, held: Held) -> dict[str, _Chain]:
    """The open chains after ``window``'s pieces were matched with the next window's: a matched
    chain takes its last piece's share up to the splice frame (the earlier piece keeps it) and
    goes on; the others end with ``window``'s core and are closed into tubes (given to ``held``)."""
    out = {}
    for chain in chains.values():
        rows = pieces.rows(chain.last)
        if chain.last in matched:
            nxt, splice = matched[chain.last]
            chain.rows += _share(rows, chain.first, splice, poses.position)
            chain.last, chain.first = nxt, splice + 1
            out[nxt] = chain
        else:
            chain.rows += _share(rows, chain.first, window.core[1] - 1, poses.position)
            _close(chain, poses, held)
    return out


def _share(rows: list[dict], lo: int, hi: int, position: dict[int, int]) -> list[dict]:
    """A piece's rows between plan positions ``lo`` and ``hi``. A frame without a position lies
    in no stitched window's core (a failed window's core, seen as a neighbour's context): no
    window owns it."""
    return [r for r in rows if r["frame"] in position and lo <= position[r["frame"]] <= hi]


def _close(chain: _Chain, poses: SequencePoses, held: Held) -> None:
    rows = chain.rows
    while rows and not rows[-1]["observed"]:
        rows.pop()
    start = next((i for i, r in enumerate(rows) if r["observed"]), len(rows))
    rows = rows[start:]
    if not rows:
        return  # owned by no window's core: a neighbour's tube seen from the context
    tframes = [part_tube_frame(r, poses.pose[r["frame"]]) for r in rows]
    held.add(chain.name, Tube(tube_id=0, segment=poses.segment[rows[0]["frame"]], frames=tframes),
             {r["window"] for r in rows})
