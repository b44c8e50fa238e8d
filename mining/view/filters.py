"""The gallery's filter: URL query parameters → one parameterised SQL predicate over the tubes
and their labels (views.sql ``labelled_tubes``).

A filter reads only parameters it knows and checks each one (a bad value is a FilterError,
which the server answers with 400 and the message). User values reach DuckDB as bound
parameters (``?``), never as SQL text; the sort column comes from a fixed list. The same
filter is also written out with literal values (``export_where``), quoted here, for the user
to paste into ``mine export --where`` — that text is shown, never executed by the viewer.

Parameters (each may repeat where it says so):

* ``set``: ``selected`` (default: the mined result) or ``all`` (every candidate tube)
* ``call``: one of ``CALLS`` — known, unknown, clutter, unclassified (``mining/score/call.py``;
  repeat for several), matched on ``CALL_SQL``: the ``call`` column, and for a row written before
  it the reading of ``known`` (true known, false unknown, null unclassified), as the exports read
  it. The old ``known`` parameter is refused, naming ``call`` (its three values do not tell
  unknown from clutter).
* ``category``: one of ``CATEGORIES``, the 80 COCO class names or ``unknown`` (repeat for several)
* ``seq``: ``DATASET/SEQUENCE``, both safe names (``mining/names.py``; repeat for several)
* ``min_C`` / ``max_C`` for C in ``RANGE_COLUMNS``: inclusive bounds
* ``verdict``: one of ``labels.VERDICTS`` or ``none`` (no verdict yet) (repeat for several)
* ``tag``: a tag the tube carries (repeat: any of them)
* ``group``: a group of the unknown set (``mine group``; −1: in no group) (repeat: any of them)
* ``sort``: one of ``SORT_COLUMNS`` (default score), ``order``: ``desc`` (default) or ``asc``
* ``offset`` in 0..``MAX_OFFSET`` and ``limit`` in 1..``MAX_LIMIT`` (default ``DEFAULT_LIMIT``): the page

A value outside its vocabulary is an error, never ignored: a shared address that the
server does not understand must say so rather than show other tubes than it names.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from mining.catalog.labels import MAX_TAG_CHARS, VERDICTS, check_text
from mining.catalog.views import sql_string
from mining.errors import InputError
from mining.names import NAME_RULE, name_problem
from mining.formats.coco import COCO_CLASSES
from mining.types import CALLS

RANGE_COLUMNS = ("score", "score_motion", "score_mask", "score_objectness", "n_frames", "n_observed",
                 "category_prob", "object_prob", "class_evidence", "speed", "moving_speed_mps", "path_length")
INT_COLUMNS = frozenset({"n_frames", "n_observed"})
SORT_COLUMNS = (*RANGE_COLUMNS, "tube_id", "sequence", "frame_start", "category")
# A row's call (mining/score/call.py) as SQL over the tubes' columns: ``call``, and for a row written
# before that column its old reading of ``known`` (export/selection.py tube_call, views.sql). A fixed
# text: the filter binds the values it is compared with.
CALL_SQL = "coalesce(call, CASE WHEN known THEN 'known' WHEN NOT known THEN 'unknown' ELSE 'unclassified' END)"
DEFAULT_LIMIT = 48  # ours: tubes per gallery page (a 6 × 8 grid)
MAX_LIMIT = 500  # ours: the most one request may ask for
MAX_OFFSET = 1_000_000_000  # ours: far past any catalogue, and inside DuckDB's BIGINT OFFSET
# What tube_category writes into the category column (mining/score/category.py).
CATEGORIES = frozenset((*COCO_CLASSES, "unknown"))
# The columns a gallery card shows (the whole row is one `mine query` away).
CARD_COLUMNS = ("tube_id", "dataset", "sequence", "frame_start", "frame_end", "n_frames", "n_observed", "score",
                "score_motion", "score_mask", "score_objectness", "selected", "call", "known", "category",
                "category_prob", "object_prob", "best_known", "speed", "moving_speed_mps", "path_length", "verdict",
                "tags")
VERDICT_VALUES = (*VERDICTS, "none")  # none: no verdict yet
MAX_GROUP = 2**31 - 1  # tube_groups' group is an int32


class FilterError(ValueError):
    """A query parameter the gallery cannot use; the message says which and why."""


class TooLarge(ValueError):
    """A request that would cost more than the viewer lets one request cost (answered 413);
    the message says what and the limit."""


def _one(params: dict[str, list[str]], name: str) -> str | None:
    values = params.get(name, [])
    if len(values) > 1:
        raise FilterError(f"parameter {name!r} given {len(values)} times; it takes one value")
    return values[0] if values else None


def _number(name: str, text: str, integer: bool) -> float | int:
    try:
        v = int(text) if integer else float(text)
    except ValueError:
        raise FilterError(f"parameter {name!r} must be {'an integer' if integer else 'a number'}, got {text!r}") from None
    if not math.isfinite(v):
        raise FilterError(f"parameter {name!r} must be finite, got {text!r}")
    return v


@dataclass(frozen=True)
class TubeFilter:
    """One gallery request: which tubes, in which order, which page."""

    all_tubes: bool = False
    calls: tuple[str, ...] = ()  # subset of CALLS
    categories: tuple[str, ...] = ()
    sequences: tuple[tuple[str, str], ...] = ()  # (dataset, sequence)
    ranges: tuple[tuple[str, float | int | None, float | int | None], ...] = ()  # (column, min, max)
    verdicts: tuple[str, ...] = ()  # subset of VERDICT_VALUES
    tags: tuple[str, ...] = ()
    groups: tuple[int, ...] = ()  # tube_group values (labelled_tubes)
    sort: str = "score"
    descending: bool = True
    offset: int = 0
    limit: int = DEFAULT_LIMIT

    @classmethod
    def from_query(cls, params: dict[str, list[str]]) -> TubeFilter:
        """Parse ``urllib.parse.parse_qs`` output (blank values kept); FilterError when bad."""
        if "known" in params:
            raise FilterError("parameter 'known' is no longer taken: filter by parameter 'call' "
                              f"({', '.join(CALLS)}; repeat it for several): known=true is call=known, "
                              "known=false is call=unknown&call=clutter, known=null is call=unclassified")
        allowed = {"set", "call", "category", "seq", "sort", "order", "offset", "limit", "verdict", "tag", "group",
                   *(f"{b}_{c}" for c in RANGE_COLUMNS for b in ("min", "max"))}
        unknown = sorted(set(params) - allowed)
        if unknown:
            raise FilterError(f"unknown parameter {unknown[0]!r}; the gallery takes: {', '.join(sorted(allowed))}")
        which = _one(params, "set") or "selected"
        if which not in ("selected", "all"):
            raise FilterError(f"parameter 'set' is 'selected' or 'all', got {which!r}")
        calls = tuple(dict.fromkeys(v for v in params.get("call", []) if v))
        bad = [v for v in calls if v not in CALLS]
        if bad:
            raise FilterError(f"parameter 'call' is one of {', '.join(CALLS)}, got {bad[0]!r}")
        categories = tuple(dict.fromkeys(v for v in params.get("category", []) if v))
        bad = [v for v in categories if v not in CATEGORIES]
        if bad:
            raise FilterError(f"parameter 'category' is a COCO class name (car, person, …) or 'unknown', got {bad[0]!r}")
        sequences = []
        for v in params.get("seq", []):
            if not v:
                continue
            dataset, sep, sequence = v.partition("/")
            if not sep or not dataset or not sequence:
                raise FilterError(f"parameter 'seq' is DATASET/SEQUENCE, got {v!r}")
            problem = name_problem(dataset) or name_problem(sequence)
            if problem:
                raise FilterError(f"parameter 'seq' is DATASET/SEQUENCE of names ({NAME_RULE}), got {v!r}: {problem}")
            sequences.append((dataset, sequence))
        ranges = []
        for c in RANGE_COLUMNS:
            lo, hi = _one(params, f"min_{c}"), _one(params, f"max_{c}")
            lo = None if lo in (None, "") else _number(f"min_{c}", lo, c in INT_COLUMNS)
            hi = None if hi in (None, "") else _number(f"max_{c}", hi, c in INT_COLUMNS)
            if lo is not None and hi is not None and lo > hi:
                raise FilterError(f"min_{c} = {lo} is above max_{c} = {hi}")
            if lo is not None or hi is not None:
                ranges.append((c, lo, hi))
        verdicts = tuple(dict.fromkeys(v for v in params.get("verdict", []) if v))
        bad = [v for v in verdicts if v not in VERDICT_VALUES]
        if bad:
            raise FilterError(f"parameter 'verdict' is one of {', '.join(VERDICT_VALUES)}, got {bad[0]!r}")
        try:
            tags = tuple(dict.fromkeys(check_text(v, "parameter 'tag'", MAX_TAG_CHARS) for v in params.get("tag", []) if v))
        except InputError as e:
            raise FilterError(str(e)) from None
        groups = tuple(dict.fromkeys(_number("group", v, True) for v in params.get("group", []) if v))
        if any(not -1 <= g <= MAX_GROUP for g in groups):
            raise FilterError(f"parameter 'group' is a group number of `mine group` (−1: in no group), got {groups}")
        sort = _one(params, "sort") or "score"
        if sort not in SORT_COLUMNS:
            raise FilterError(f"cannot sort by {sort!r}; one of {', '.join(SORT_COLUMNS)}")
        order = _one(params, "order") or "desc"
        if order not in ("asc", "desc"):
            raise FilterError(f"parameter 'order' is 'asc' or 'desc', got {order!r}")
        offset = _number("offset", _one(params, "offset") or "0", True)
        limit = _number("limit", _one(params, "limit") or str(DEFAULT_LIMIT), True)
        if offset < 0:
            raise FilterError(f"parameter 'offset' must be ≥ 0, got {offset}")
        if offset > MAX_OFFSET:
            raise FilterError(f"parameter 'offset' must be at most {MAX_OFFSET}, got {offset}")
        if not 1 <= limit <= MAX_LIMIT:
            raise FilterError(f"parameter 'limit' must be in 1..{MAX_LIMIT}, got {limit}")
        return cls(which == "all", calls, categories, tuple(sequences), tuple(ranges), verdicts, tags,
                   tuple(int(g) for g in groups), sort, order == "desc", int(offset), int(limit))

    def _terms(self, literal: bool) -> tuple[list[str], list]:
        """The predicate's AND-ed terms, with ``?`` and their values, or with literals."""
        terms: list[str] = []
        values: list = []

        def bind(v) -> str:
            if literal:
                return sql_string(v) if isinstance(v, str) else repr(v)
            values.append(v)
            return "?"

        if not self.all_tubes:
            terms.append("selected")
        if self.calls:  # CALL_SQL is a fixed text; the calls (checked against CALLS) are bound
            values_sql = [bind(c) for c in self.calls]
            terms.append(f"{CALL_SQL} = {values_sql[0]}" if len(values_sql) == 1
                         else f"{CALL_SQL} IN ({', '.join(values_sql)})")
        if self.categories:
            terms.append(f"category IN ({', '.join(bind(c) for c in self.categories)})")
        if self.sequences:
            pairs = [f"(dataset = {bind(d)} AND sequence = {bind(s)})" for d, s in self.sequences]
            terms.append(pairs[0][1:-1] if len(pairs) == 1 else "(" + " OR ".join(pairs) + ")")
        if self.verdicts:
            parts = ["verdict IS NULL" if v == "none" else f"verdict = {bind(v)}" for v in self.verdicts]
            terms.append(parts[0] if len(parts) == 1 else "(" + " OR ".join(parts) + ")")
        if self.tags:
            parts = [f"list_contains(tags, {bind(t)})" for t in self.tags]
            terms.append(parts[0] if len(parts) == 1 else "(" + " OR ".join(parts) + ")")
        if self.groups:
            terms.append(f"tube_group IN ({', '.join(bind(g) for g in self.groups)})")
        for c, lo, hi in self.ranges:  # c is one of RANGE_COLUMNS: a fixed identifier
            if lo is not None:
                terms.append(f"{c} >= {bind(lo)}")
            if hi is not None:
                terms.append(f"{c} <= {bind(hi)}")
        return terms, values

    def predicate(self) -> tuple[str, list]:
        """(SQL predicate with ``?`` placeholders, its parameter values)."""
        terms, values = self._terms(literal=False)
        return " AND ".join(terms) or "true", values

    def export_where(self) -> str:
        """The same predicate with literal values, for ``mine export --where``."""
        terms, _ = self._terms(literal=True)
        return " AND ".join(terms) or "true"

    def order_by(self) -> str:
        """ORDER BY clause: the whitelisted column, nulls last, then the tube id for a stable page."""
        assert self.sort in SORT_COLUMNS
        direction = "DESC" if self.descending else "ASC"
        tie = "" if self.sort == "tube_id" else ", tube_id"
        return f"{self.sort} {direction} NULLS LAST{tie}"
