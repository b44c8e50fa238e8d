"""The streaming stitch's held tubes: closed tubes wait here, group by group, until nothing still
to come can change their fate; then they are linked, judged and turned into Arrow rows, and only
what the sequence-wide steps at the end need of them stays (``Settled``).

Why a group is enough. Every step after the chains is a function of a group of tubes that touch:

* fragment links (``mining.tubes.link``): a candidate link needs frames both tubes observed with
  boxes that meet (box IoU > 0 in every common frame); ``one_to_one`` is greedy over a total order
  (most common frames, higher IoU, then the tubes' indices), and a link's fate depends only on links
  sharing one of its tubes: the same greedy within a group, its tubes in the batch's relative order;
* score and call (``mining.score``): each tube's own;
* co-selection's terms: one per pair of tubes whose boxes pass the gate in a frame both span
  (box IoU or intersection over the smaller box > ``select.box_iou_gate`` ≥ 0: boxes that meet).

So tubes are grouped by "their boxes meet in a frame both span" (``touch``). The co-selection
itself is NOT left to the groups: its sums (``overlap_matrix``: scipy sums a pair's terms in an
order that depends on every term of the row) and its solver (the dense path below ``DENSE_MAX``
tubes, the free tubes' kept-neighbour sums) depend on the whole sequence's tube order and count, so
the groups keep their pair terms and the selection runs once at the end over all of them, in the
batch's order: the same bits as before.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa

from mining.boxes import box_iou
from mining.catalog.rows import RunInfo, frame_rows, to_table, tube_row
from mining.config import JobConfig
from mining.pipeline.mine import judge_each
from mining.select.coselect import FramePairs, frame_pairs, overlap_matrix, select_over
from mining.tubes.link import link_fragments
from mining.types import MinedTube, Tube

ROWS_PER_CHUNK = 4096  # ours: tube-frame rows held as dicts before they go into Arrow (a few MB)
INT_BIAS = 1 << 63  # shifts a signed 64-bit integer to an unsigned one of the same order (inlier keys as bytes)


def batch_key_chain(name: str) -> tuple:
    """Where a chain's tube stood in the batch stitch's list: chains by their first piece's name."""
    return (0, name)


def batch_key_joined(first_frame: int, start: str) -> tuple:
    """Where a joined tube stood: after every chain, by its first fragment's first frame, then that
    fragment's place (``link_fragments`` orders chains of links so)."""
    return (1, first_frame, start)


def inlier_bytes(tube: Tube) -> bytes:
    """``Tube.inlier_key`` as bytes that sort as the tuple does (big-endian, biased, fixed width: a
    prefix sorts first), 16 bytes an inlier instead of a tuple of tuples."""
    key = np.array([(f.frame, f.obs_index) for f in tube.frames if f.observed], np.int64).reshape(-1)
    return (key.astype(np.uint64) + np.uint64(INT_BIAS)).astype(">u8").tobytes()


@dataclass
class Settled:
    """What the end needs of the tubes of the sequence once they are rows."""

    keys: list[tuple] = field(default_factory=list)  # batch order key per tube
    inliers: list[bytes] = field(default_factory=list)
    score: list[float] = field(default_factory=list)
    base: list[str] = field(default_factory=list)  # the id before a "-n" suffix
    frame_rows: list[int] = field(default_factory=list)  # tube-frame rows per tube, in row order
    offered: dict[tuple, tuple[float, np.ndarray]] = field(default_factory=dict)  # key → cost, frames
    pairs: list[tuple[list[tuple], list[FramePairs]]] = field(default_factory=list)  # per group: offered keys, terms
    model: str = "reference"


class Held:
    """Closed tubes not yet settled, in groups of tubes that touch (union-find), and the rows of
    the settled ones (``settle``)."""

    def __init__(self, cfg: JobConfig, run: RunInfo, position: dict[int, int]):
        self.cfg, self.run, self.position = cfg, run, position
        self.tubes: dict[str, tuple[Tube, set[str], int]] = {}  # name → tube, windows, last position
        self.parent: dict[str, str] = {}
        self.by_frame: dict[int, list[tuple[str, np.ndarray]]] = defaultdict(list)
        self.done = Settled()
        self.tube_tables, self.frame_tables = [], []
        self.tube_rows, self.frame_rows_ = [], []

    def _root(self, name: str) -> str:
        while self.parent[name] != name:
            self.parent[name] = self.parent[self.parent[name]]
            name = self.parent[name]
        return name

    def add(self, name: str, tube: Tube, windows: set[str]) -> None:
        """A closed chain's tube; it joins the group of every held tube it touches."""
        self.tubes[name] = (tube, windows, max(self.position[f.frame] for f in tube.frames))
        self.parent[name] = name
        any_shared = self.cfg.select.box_iou_gate < 0  # a negative gate pairs tubes whose boxes do not meet
        for f in tube.frames:
            bucket = self.by_frame[f.frame]
            if bucket:
                meet = box_iou(np.array([b for _, b in bucket]), f.box)[:, 0] > 0
                for (other, _), m in zip(bucket, meet):
                    if m or any_shared:
                        self.parent[self._root(other)] = self._root(name)
            bucket.append((name, f.box))

    def settle_before(self, horizon: float) -> None:
        """Settle every group whose tubes all end before plan position ``horizon``: no tube still
        to come (they all start at or after it) can share a frame with them."""
        groups: dict[str, list[str]] = defaultdict(list)
        for name in self.tubes:
            groups[self._root(name)].append(name)
        for names in groups.values():
            if max(self.tubes[n][2] for n in names) < horizon:
                self._settle(sorted(names))

    def _settle(self, names: list[str]) -> None:
        """Link, judge and write one group's tubes as rows, then drop them (module docstring)."""
        tubes = [self.tubes[n][0] for n in names]
        windows = [self.tubes[n][1] for n in names]
        keys = [batch_key_chain(n) for n in names]
        for joined, parts in link_fragments(tubes, self.cfg.tubes, first_id=1):
            keys.append(batch_key_joined(tubes[parts[0]].first_frame, names[parts[0]]))
            tubes.append(joined)
            windows.append(set().union(*(windows[i] for i in parts)))
        each = judge_each(tubes, self.cfg)
        self.done.model = each.model
        idx = np.flatnonzero(each.offered)
        if len(idx):
            sel = self.cfg.select
            terms = frame_pairs([tubes[i] for i in idx], sel.box_iou_gate, sel.overlap, sel.overlap_floor)
            self.done.pairs.append(([keys[i] for i in idx], terms))
        for i, (t, key) in enumerate(zip(tubes, keys)):
            if each.offered[i]:
                self.done.offered[key] = (float(each.cost[i]), np.array([f.frame for f in t.frames], np.int64))
            self._rows(MinedTube(t, each.scores[i], each.calls[i], False), key, len(windows[i]))
        for n in names:
            tube = self.tubes.pop(n)[0]
            del self.parent[n]
            for f in tube.frames:
                bucket = [e for e in self.by_frame.pop(f.frame) if e[0] != n]
                if bucket:
                    self.by_frame[f.frame] = bucket

    def _rows(self, mt: MinedTube, key: tuple, n_windows: int) -> None:
        """One tube's rows, its id and selection left blank (``finish`` fills them in)."""
        first = mt.tube.frames[0]
        d = self.done
        d.keys.append(key)
        d.inliers.append(inlier_bytes(mt.tube))
        d.score.append(mt.score.total)
        d.base.append(f"{self.run.dataset}/{self.run.sequence}/{first.frame:07d}.{first.obs_index:03d}")
        self.tube_rows.append(tube_row(mt, "", self.run, n_windows))
        rows = frame_rows(mt, "")
        d.frame_rows.append(len(rows))
        self.frame_rows_.extend(rows)
        if len(self.frame_rows_) >= ROWS_PER_CHUNK:  # into Arrow as it goes
            self.frame_tables.append(to_table(self.frame_rows_, "tube_frames"))
            self.tube_tables.append(to_table(self.tube_rows, "tubes"))
            self.frame_rows_, self.tube_rows = [], []

    def tables(self) -> tuple[list, list]:
        """Every settled tube's rows (tubes, tube frames), in the order they were settled."""
        self.frame_tables.append(to_table(self.frame_rows_, "tube_frames"))
        self.tube_tables.append(to_table(self.tube_rows, "tubes"))
        self.frame_rows_, self.tube_rows = [], []
        return self.tube_tables, self.frame_tables


def _terms_in_batch_order(d: Settled, offered: list[tuple]) -> list[FramePairs]:
    """Every group's co-selection terms as ``frame_pairs`` gives them for all the sequence's offered
    tubes at once: frames in the order the tubes (in batch order) first meet them, each frame's
    pairs in row-major order of the tubes' places among the offered ones."""
    place = {k: j for j, k in enumerate(offered)}
    by_frame: dict[int, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = defaultdict(list)
    for keys, terms in d.pairs:
        to_place = np.array([place[k] for k in keys], np.int64)
        for frame, a, b, v in terms:
            by_frame[frame].append((to_place[a], to_place[b], v))
    spans: dict[int, int] = {}  # frame → offered tubes spanning it, frames in first-met order
    for k in offered:
        for f in d.offered[k][1].tolist():
            spans[f] = spans.get(f, 0) + 1
    out = []
    for frame, count in spans.items():
        if count < 2:
            continue
        parts = by_frame.get(frame, [])
        a = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0, np.int64)
        b = np.concatenate([p[1] for p in parts]) if parts else np.zeros(0, np.int64)
        v = np.concatenate([p[2] for p in parts]) if parts else np.zeros(0)
        order = np.lexsort((b, a))
        out.append((frame, a[order], b[order], v[order]))
    return out


def finish(held: Held, cfg: JobConfig) -> tuple[pa.Table, pa.Table]:
    """The sequence's tubes and tube frames: co-selection over every offered tube at once, then the
    batch stitch's order (first inlier key, then -score, ties in the batch's list order) and ids."""
    tube_tables, frame_tables = held.tables()
    d = held.done
    offered = sorted(d.offered)  # the batch's list order
    chosen: set[tuple] = set()
    if offered:
        overlap = overlap_matrix(_terms_in_batch_order(d, offered), len(offered))
        cost = np.array([d.offered[k][0] for k in offered], np.float64)
        chosen = {k for k, m in zip(offered, select_over(overlap, cost, cfg.select, d.model)) if m}
    order = sorted(range(len(d.keys)), key=lambda i: (d.inliers[i], -d.score[i], d.keys[i]))
    used: dict[str, int] = defaultdict(int)
    ids = []
    for i in order:
        base = d.base[i]
        ids.append(base if used[base] == 0 else f"{base}-{used[base]}")
        used[base] += 1
    tubes = pa.concat_tables(tube_tables).take(pa.array(order, pa.int64()))
    tubes = _set(tubes, "tube_id", ids)
    tubes = _set(tubes, "selected", [d.keys[i] in chosen for i in order]).combine_chunks()
    counts = np.asarray(d.frame_rows, np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]) if len(counts) else counts
    rows = [np.arange(starts[i], starts[i] + counts[i]) for i in order]
    take = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    frames = pa.concat_tables(frame_tables).take(pa.array(take, pa.int64()))
    frames = _set(frames, "tube_id", np.repeat(np.array(ids, object), counts[order]).tolist() if ids else [])
    return tubes, frames.combine_chunks()


def _set(table: pa.Table, column: str, values: list) -> pa.Table:
    i = table.schema.get_field_index(column)
    f = table.schema.field(i)
    return table.set_column(i, f, pa.array(values, f.type))
