"""What the viewer asks the catalogue: gallery pages, facets, one tube with its frames and track.

Every query runs on the read-only connection of ``mining.catalog.views.connect``, one at a
time (a lock: the connection's registered tables — empty tables, non-local catalogues — are
not visible to ``cursor()`` copies, and each query takes milliseconds), with user values as
bound parameters only (``filters.py``). A tube id from a URL is looked up by parameter
before anything else uses it; an id the catalogue does not hold is simply not found.

A request reads at most ``MAX_TUBE_FRAMES`` frames of a tube (a longer tube is TooLarge,
answered 413), and only the columns it shows: masks are read one frame at a time.
"""

from __future__ import annotations

import math
import os
import re
import shlex
import threading
from pathlib import Path

import duckdb

import pyarrow.fs as pafs

from mining.catalog import derived, labels
from mining.catalog.layout import JOB, LABELS
from mining.catalog.records import JobRecord
from mining.catalog.store import Store
from mining.catalog.views import connect, refresh_labels, register_derived, sql_string
from mining.config import JobConfig
from mining.discovery.similar import SHOWN, similar_embedding_rows, similar_rows
from mining.errors import InputError
from mining.formats.coco import COCO_CLASSES
from mining.score.call import class_mode
from mining.types import CALLS, UNKNOWN_CLASS
from mining.view.filters import CALL_SQL, CARD_COLUMNS, RANGE_COLUMNS, TooLarge, TubeFilter
from mining.view.images import best_frame

CLASS_NAMES = (*COCO_CLASSES, "unknown")
assert len(CLASS_NAMES) == UNKNOWN_CLASS + 1
TOP_CLASSES = 5  # ours: posterior entries a tube page lists
FRAME_COLUMNS = ("frame", "t_ns", "observed", "bbox", "objectness", "position_world", "position_cam", "mask_iou",
                 "motion_density", "rle_h", "rle_w")
CHOICE_COLUMNS = ("frame", "observed", "bbox", "rle_h", "rle_w")  # what images.best_frame looks at
# ours: a tube page shows at most this many frames (17 minutes at 10 fps); mine query and mine export
# read a longer tube whole.
MAX_TUBE_FRAMES = 10_000
_SAFE_SHELL = re.compile(r"[A-Za-z0-9_@%+=:,./' <>()*-]*")  # needs no quoting inside "…" in a POSIX shell


def shell_word(text: str) -> str:
    """``text`` quoted for a POSIX shell: double quotes where they suffice (readable SQL), else shlex."""
    if _SAFE_SHELL.fullmatch(text):
        return text if text and shlex.quote(text) == text else f'"{text}"'
    return shlex.quote(text)


def export_command(out: str, where: str, dest: str) -> str:
    """The ``mine export`` line that writes crops of the tubes matching ``where``."""
    return f"mine export --out {shell_word(out)} --where {shell_word(where)} --format crops {shell_word(dest)}"


def _clean(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, list):
        return [_clean(x) for x in v]
    return v


def _rows(cur: duckdb.DuckDBPyConnection) -> list[dict]:
    names = [d[0] for d in cur.description]
    return [{n: _clean(v) for n, v in zip(names, row)} for row in cur.fetchall()]


def _f(v: float | None, digits: int = 2) -> str:
    return "–" if v is None else f"{v:.{digits}f}"


def call_text(r: dict, category: str | None) -> str:
    """The tube page's explanation of a call, with the tube's numbers (``class_rule``'s ``r``):
    known / unknown by the margin inequality, clutter by the object gate, unclassified by the
    classified frames. Where the stored call is not what these numbers give (a row written by
    another rule), it says so."""
    call = r["call"]
    legacy = " (read from known: the row was written before the call column)" if r["call_from_known"] else ""
    if call == "unclassified":
        if not r["classified_frames"]:
            return f"Unclassified: no classifier looked at this tube (classified frames 0){legacy}."
        return (f"Unclassified{legacy}: recorded so by an older rule, though {r['classified_frames']} frame(s) were "
                "classified; today's rule calls a tube unclassified only where no classifier looked.")
    margin, lr = r["margin"], r["log_ratio"]
    bound = (f"{_f(margin)} ({r['margin_key']})" if margin is not None
             else "the job's margin (not known: the catalogue has no job.json)")
    out = [f"Known when ln P(best COCO class) − ln P(unknown) > {bound}."]
    wins = None  # what the posterior and the margin give: known or unknown (None: cannot tell)
    p_best, p_unknown = r["p_best"], r["p_unknown"]
    if lr is not None or p_best is not None and (p_best > 0) != (p_unknown > 0):
        # ln 0 = −∞: a posterior with P(unknown) 0 is known at any margin, one with P(best) 0 unknown
        value = _f(lr) if lr is not None else "+∞" if p_best > 0 else "−∞"
        here = (f"Here ln P({r['best_known']}) − ln P(unknown) = ln {_f(p_best, 3)} − ln {_f(p_unknown, 3)} = "
                f"{value}")
        if margin is not None:
            wins = "known" if (lr > margin if lr is not None else p_best > 0) else "unknown"
            here += f" {'>' if wins == 'known' else '≤'} {_f(margin)}"
        out.append(here + (f": known, {category}{legacy}." if call == "known" else ": unknown wins."))
    else:
        out.append((f"Known, {category}" if call == "known" else "Unknown wins") + f"{legacy}.")
    if call != "known":
        op, threshold, key = r["object_prob"], r["min_object"], r["min_object_key"]
        limit = f"{_f(threshold)} ({key})" if threshold is not None else f"the job's threshold ({key}; no job.json)"
        if call == "clutter":
            action = {"call": "still offered to co-selection", "drop": "not offered to co-selection"}.get(r["gate"])
            out.append(f"P(object) {_f(op)} < {limit}: clutter, unknown to the classifier but not an object by its "
                       "object evidence; kept out of the unknown set"
                       + (f" ({r['gate_key']} = {r['gate']}: {action})." if action else "."))
            if op is not None and threshold is not None and op >= threshold:
                out.append("The stored call is not what these numbers give: the row was written by another rule.")
        elif op is not None:
            out.append(f"P(object) {_f(op)} ≥ {limit}: an object, unknown{legacy}.")
            if threshold is not None and op < threshold:
                out.append("The stored call is not what these numbers give: the row was written by another rule.")
        elif r["call_from_known"]:
            out.append(f"No P(object) stored: unknown{legacy}.")
        elif r["gate"] == "off":
            out.append(f"No object gate ({r['gate_key']} = off): unknown{legacy}.")
        elif r["gate_weights"] is False:
            out.append(f"No object gate: the job has no object-evidence weights for proposer {r['proposer']}; "
                       f"unknown{legacy}.")
        else:
            out.append(f"No P(object) stored: unknown{legacy}.")
    if wins is not None and wins != ("known" if call == "known" else "unknown"):
        out.append(f"The stored call ({call}) is not what these numbers give: the row was written by another rule.")
    return " ".join(out)


SIMILAR_SHOWN = 8  # ours: the tube page's "similar tubes" strip, one row of thumbnails


class CatalogueBrowser:
    """The queries behind the viewer's JSON API, over one catalogue folder."""

    def __init__(self, out: str | Path, author: str | None = None):
        self.out = str(out)
        self.con = connect(out)  # InputError when ``out`` is not a catalogue folder
        self.store = Store(out)
        self.author = labels.check_text(labels.default_author() if author is None else author, "--author",
                                        labels.MAX_AUTHOR_CHARS)
        self._labels_seen = self._labels_stamp()
        self._groups_seen = self._groups_stamp()
        self._lock = threading.Lock()
        self.job: JobConfig | None = None  # the typed config of OUT/job.json (None: the catalogue has none)
        self.job_error: str | None = None
        try:
            store = Store(out)
            record = JobRecord.load(store)
            self.job = None if record is None else record.job_config(store.full(JOB))
        except InputError as e:  # a damaged job.json: browse the tables, say why there are no frames
            self.job_error = str(e)

    def close(self) -> None:
        self.con.close()

    def _labels_stamp(self) -> object:
        """What changes when a label file is added or removed: the folder's mtime locally (one
        stat), the listing elsewhere."""
        if self.store.local:
            try:
                return os.stat(self.store.full(LABELS)).st_mtime_ns
            except FileNotFoundError:
                return None
        return labels.label_files(self.store)

    def _groups_stamp(self) -> object:
        """What changes when `mine group` writes: its marker's mtime (one stat)."""
        info = self.store.fs.get_file_info(self.store.full(derived.GROUPS_MARKER))
        return info.mtime_ns if info.type == pafs.FileType.File else None

    def _fresh_labels(self) -> None:
        """Re-read the labels when their files changed (another viewer, `mine label`, a compaction),
        and the derived tables when `mine group` wrote. Under ``_lock``."""
        stamp = self._labels_stamp()
        if stamp != self._labels_seen:
            refresh_labels(self.con, self.store)
            self._labels_seen = stamp
        groups = self._groups_stamp()
        if groups != self._groups_seen:
            register_derived(self.con, self.store)
            self._groups_seen = groups

    def _query(self, sql: str, params: list | None = None) -> list[dict]:
        with self._lock:
            self._fresh_labels()
            self.con.execute(sql, params or [])
            return _rows(self.con)

    def label(self, tube_ids: list[str], kind: str, value: str | None, op: str) -> list[dict]:
        """Apply one decision to ``tube_ids`` (each must be a tube of the catalogue: InputError
        naming the first that is not), as one new labels part; the tubes' labels after it."""
        found = {r["tube_id"]: r for r in self._query(
            "SELECT dataset, sequence, tube_id FROM tubes WHERE tube_id IN (SELECT unnest(?))", [tube_ids])}
        missing = [t for t in tube_ids if t not in found]
        if missing:
            raise InputError(f"no tube {missing[0]!r} in this catalogue" + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
        table = labels.events([(found[t]["dataset"], found[t]["sequence"], t) for t in tube_ids], kind, value, op,
                              self.author, via="view")
        labels.append(self.store, table)
        return self._query("SELECT tube_id, verdict, tags, tag, labelled_at, labelled_by FROM labelled_tubes "
                           "WHERE tube_id IN (SELECT unnest(?)) ORDER BY tube_id", [tube_ids])

    def page(self, flt: TubeFilter) -> dict:
        """One gallery page: the total that match, and the tubes of ``flt``'s page."""
        pred, values = flt.predicate()
        total = self._query(f"SELECT count(*) AS n FROM labelled_tubes WHERE {pred}", values)[0]["n"]
        cols = ", ".join(f"{CALL_SQL} AS call" if c == "call" else c for c in CARD_COLUMNS)
        tubes = self._query(f"SELECT {cols} FROM labelled_tubes WHERE {pred} ORDER BY {flt.order_by()} LIMIT ? OFFSET ?",
                            [*values, flt.limit, flt.offset])
        where = flt.export_where()
        return {"total": total, "offset": flt.offset, "limit": flt.limit, "tubes": tubes, "where": where,
                "export_command": export_command(self.out, where, "crops")}

    def groups(self) -> dict:
        """One tile per group of the unknown set (`mine group`), largest first, the tubes in no group
        last: its number, size, spread (the median cosine distance of its tubes to its mean direction)
        and exemplar (the tube nearest that direction, with its call and category)."""
        rows = self._query(
            'WITH g AS (SELECT "group", count(*) AS size, median(centre_distance) AS spread, '
            "arg_min(tube_id, centre_distance) AS exemplar FROM tube_groups GROUP BY 1) "
            f"SELECT g.*, {CALL_SQL} AS call, t.category FROM g LEFT JOIN tubes AS t ON t.tube_id = g.exemplar "
            'ORDER BY g."group" < 0, g.size DESC, g."group"')
        return {"groups": rows, "tubes": sum(r["size"] for r in rows),
                "note": None if rows else f"the unknown set is not grouped: run `mine group --out {self.out}`"}

    def facets(self, all_tubes: bool) -> dict:
        """What the filter form offers: counts by call (``calls``: every one of CALLS, a row
        written before the call column counted by its ``known``), category and sequence, and
        each range."""
        pred = "true" if all_tubes else "selected"
        counts = self._query("SELECT count(*) AS tubes, count(*) FILTER (WHERE selected) AS selected FROM tubes")[0]
        calls = dict.fromkeys(CALLS, 0) | {r["call"]: r["n"] for r in self._query(
            f"SELECT {CALL_SQL} AS call, count(*) AS n FROM tubes WHERE {pred} GROUP BY ALL")}
        categories = self._query(f"SELECT category, count(*) AS n FROM tubes WHERE {pred} AND category IS NOT NULL "
                                 "GROUP BY category ORDER BY n DESC, category")
        sequences = self._query(f"SELECT dataset, sequence, count(*) AS n FROM tubes WHERE {pred} "
                                "GROUP BY dataset, sequence ORDER BY dataset, sequence")
        agg = ", ".join(f"min({c}) AS min_{c}, max({c}) AS max_{c}" for c in RANGE_COLUMNS)
        r = self._query(f"SELECT {agg} FROM tubes WHERE {pred}")[0]
        ranges = {c: [r[f"min_{c}"], r[f"max_{c}"]] for c in RANGE_COLUMNS}
        verdicts = {("none" if v["verdict"] is None else v["verdict"]): v["n"] for v in self._query(
            f"SELECT verdict, count(*) AS n FROM labelled_tubes WHERE {pred} GROUP BY verdict")}
        tags = self._query(f"SELECT tag, count(*) AS n FROM (SELECT unnest(tags) AS tag FROM labelled_tubes WHERE {pred}) "
                           "GROUP BY tag ORDER BY n DESC, tag")
        return {"catalogue": self.out, "tubes": counts["tubes"], "selected": counts["selected"], "calls": calls,
                "categories": categories, "sequences": sequences, "ranges": ranges, "verdicts": verdicts,
                "tags": tags, "author": self.author}

    def tube(self, tube_id: str) -> dict | None:
        """The tubes row of ``tube_id`` (looked up by parameter), or None. Its ``call`` is always
        one of CALLS (``CALL_SQL``); ``call_from_known`` says the row was written before the
        call column, its call read from ``known``."""
        rows = self._query(f"SELECT * REPLACE ({CALL_SQL} AS call), call IS NULL AS call_from_known "
                           "FROM labelled_tubes WHERE tube_id = ?", [tube_id])
        return rows[0] if rows else None

    def frames(self, tube: dict, columns: tuple[str, ...] = FRAME_COLUMNS) -> list[dict]:
        """The tube's frames in frame order (``columns`` of each, fixed names); TooLarge past MAX_TUBE_FRAMES."""
        rows = self._query(f"SELECT {', '.join(columns)} FROM tube_frames WHERE dataset = ? AND sequence = ? "
                           "AND tube_id = ? ORDER BY frame LIMIT ?",
                           [tube["dataset"], tube["sequence"], tube["tube_id"], MAX_TUBE_FRAMES + 1])
        if len(rows) > MAX_TUBE_FRAMES:
            raise TooLarge(f"tube {tube['tube_id']!r} has more than {MAX_TUBE_FRAMES} frames, more than the viewer "
                           "reads for one request; `mine query` and `mine export` read it whole")
        return rows

    def frame(self, tube: dict, frame: int) -> dict | None:
        rows = self._query("SELECT * FROM tube_frames WHERE dataset = ? AND sequence = ? AND tube_id = ? AND frame = ?",
                           [tube["dataset"], tube["sequence"], tube["tube_id"], frame])
        return rows[0] if rows else None

    def ego_path(self, tube: dict) -> list[dict]:
        """The camera's positions over the tube's frames, in the world of the tube's segment."""
        # At most one pose per frame the page may show (frame_start and frame_end come from the row).
        return self._query("SELECT frame, pose[4] AS x, pose[8] AS y, pose[12] AS z FROM frames WHERE dataset = ? "
                           "AND sequence = ? AND segment = ? AND frame BETWEEN ? AND ? ORDER BY frame LIMIT ?",
                           [tube["dataset"], tube["sequence"], tube["segment"], tube["frame_start"], tube["frame_end"],
                            MAX_TUBE_FRAMES])

    def score_line(self, tube: dict) -> str:
        """What this tube's score is, in words."""
        model, version = tube.get("score_model"), tube.get("score_version")
        of = f"; version {version}" if version else ""
        if model == "calibrated":
            return f"calibrated log-odds that the tube is an object (the θ terms add up to it; 0 = even odds{of})"
        if model == "reference":
            return ("REFERENCE's weighted total β·(α·motion + (1−α)·mask) + (1−β)·objectness (no probability scale"
                    f"{of})")
        return "not recorded: the catalogue was written before score_model (job.json's score.model says which unary ran)"

    def class_rule(self, tube: dict, posterior: list | None) -> dict:
        """What the tube page needs to explain the tube's call (mining/score/call.py) with its own
        numbers: the call; ln P[best known] − ln P[unknown] from its posterior; its classified
        frames; its P(object) (``object_prob``, where the object gate judged it). From the job
        that made it (None where the catalogue has no job.json): the margin and its key, the
        gate's threshold (``score.unknown_min_object``), its mode (``score.unknown_gate``) and
        whether the job's proposer has object-evidence weights (no weights: no gate)."""
        rule = {"call": tube.get("call"), "call_from_known": bool(tube.get("call_from_known")),
                "classified_frames": tube.get("classified_frames"), "evidence": tube.get("class_evidence"),
                "object_prob": tube.get("object_prob"), "log_ratio": None, "best_known": None, "p_best": None,
                "p_unknown": None, "margin": None, "margin_key": None, "min_object": None,
                "min_object_key": "score.unknown_min_object", "gate": None, "gate_key": "score.unknown_gate",
                "gate_weights": None, "proposer": None}
        if self.job is not None:
            s, proposer = self.job.score, self.job.proposals.proposer
            mode = class_mode(s, proposer)
            rule |= {"margin": getattr(s.known_margin, mode), "margin_key": f"score.known_margin.{mode}",
                     "min_object": s.unknown_min_object, "gate": s.unknown_gate,
                     "gate_weights": bool(s.object_evidence.get(proposer)), "proposer": proposer}
        if posterior and len(posterior) == len(CLASS_NAMES):
            known = [p or 0.0 for p in posterior[:UNKNOWN_CLASS]]
            k = max(range(len(known)), key=known.__getitem__)
            p_best, p_unknown = known[k], posterior[UNKNOWN_CLASS] or 0.0
            if p_best > 0 and p_unknown > 0:
                rule["log_ratio"] = math.log(p_best) - math.log(p_unknown)
            rule |= {"best_known": CLASS_NAMES[k], "p_best": p_best, "p_unknown": p_unknown}
        rule["text"] = call_text(rule, tube.get("category"))
        return rule

    def detail(self, tube_id: str, frame: int | None = None) -> dict | None:
        """Everything a tube page shows, or None for an id the catalogue does not hold; the page
        opens on ``frame`` when the tube has it, else on the thumbnail's (``images.best_frame``)."""
        tube = self.tube(tube_id)
        if tube is None:
            return None
        posterior = tube.pop("class_posterior")
        rule = self.class_rule(tube, posterior)
        top = []
        if posterior:
            order = sorted(range(len(posterior)), key=lambda k: -(posterior[k] or 0.0))[:TOP_CLASSES]
            top = [{"name": CLASS_NAMES[k] if k < len(CLASS_NAMES) else str(k), "p": posterior[k]} for k in order]
        frames = self.frames(tube)
        where = f"tube_id = {sql_string(tube_id)}"
        numbers = [f["frame"] for f in frames]
        start = frame if frame in numbers else (best_frame(frames)["frame"] if frames else None)
        with self._lock:  # the one connection is shared by the server's threads
            similar, note = similar_rows(self.store, self.con, tube_id, SIMILAR_SHOWN + 1)
            looks, model, looks_note = similar_embedding_rows(self.store, self.con, tube_id, SIMILAR_SHOWN + 1)
        similar = [{k: r[k] for k in SHOWN} for r in similar if r["tube_id"] != tube_id][:SIMILAR_SHOWN]
        looks = [{k: r[k] for k in SHOWN} for r in looks if r["tube_id"] != tube_id][:SIMILAR_SHOWN]
        return {"tube": tube, "top_classes": top, "class_rule": rule, "frames": frames, "ego": self.ego_path(tube),
                "similar": similar, "similar_note": note, "similar_looks": looks, "similar_looks_model": model,
                "similar_looks_note": looks_note, "start_frame": start, "score_model": self.score_line(tube),
                "where": where, "export_command": export_command(self.out, where, f"crops/{tube_id.replace('/', '_')}")}
