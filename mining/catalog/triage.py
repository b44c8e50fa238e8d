"""`mine label`: scripted triage — one decision for every tube a predicate selects.

    mine label --out OUT --where "known = false AND n_frames < 5" --verdict not_object
    mine label --out OUT --where "tube_id IN ('kitti/0005/0000012.003')" --tag barrier
    mine label --out OUT --compact

The predicate is ``mine export``'s (``predicate.tubes_query``: one SQL expression over the
tubes and their labels, parsed, never pasted), run on the read-only catalogue; the decision
is appended as one new labels part (``labels.append``), so it never waits for, or is lost
beside, a viewer or a running job. ``--compact`` merges the label files under the writer lock.
"""

from __future__ import annotations

import sys
from pathlib import Path

import duckdb

from mining.catalog import labels
from mining.catalog.predicate import PREDICATE_ERRORS, tubes_query
from mining.catalog.store import Store
from mining.catalog.views import connect, execute_read_only
from mining.errors import MiningError, NothingMatched


def matching_tubes(out: str | Path, where: str) -> list[tuple[str, str, str]]:
    """(dataset, sequence, tube_id) of every tube matching ``where``, in id order."""
    sql = tubes_query(where)
    con = connect(out)
    try:
        rel = execute_read_only(con, f"SELECT dataset, sequence, tube_id FROM ({sql}) ORDER BY dataset, sequence, tube_id")
        return [tuple(r) for r in rel.fetchall()]
    except PREDICATE_ERRORS as e:
        raise MiningError(f"bad --where predicate {where!r}: {e}") from None
    except duckdb.Error as e:  # a damaged catalogue or labels file: the message names it
        raise MiningError(str(e).removeprefix("Invalid Input Error: ")) from None
    finally:
        con.close()


def decision(verdict: str | None, clear_verdict: bool, tag: str | None, untag: str | None) -> tuple[str, str | None, str]:
    """(kind, value, op) of the one action given; MiningError unless exactly one is."""
    given = [(k, v) for k, v in (("--verdict", verdict), ("--clear-verdict", clear_verdict or None),
                                 ("--tag", tag), ("--untag", untag)) if v is not None]
    if len(given) != 1:
        raise MiningError("give exactly one of --verdict V, --clear-verdict, --tag T, --untag T"
                          + (f" (got {', '.join(k for k, _ in given)})" if given else "") + ", or --compact")
    if verdict is not None:
        return "verdict", verdict, "set"
    if clear_verdict:
        return "verdict", None, "unset"
    if tag is not None:
        return "tag", tag, "set"
    return "tag", untag, "unset"


def run_label(out: str, where: str | None, verdict: str | None = None, clear_verdict: bool = False,
              tag: str | None = None, untag: str | None = None, author: str | None = None,
              dry_run: bool = False, compact: bool = False, lock_wait_s: float = 0.0) -> int:
    """`mine label`: 0 when labelled (or compacted); NothingMatched (exit 1) when no tube
    matches; 2 with one line on standard error otherwise."""
    try:
        store = Store(out)
        if not store.root_exists():
            raise MiningError(f"--out {out}: catalogue folder not found")
        if compact:
            if where is not None or verdict or clear_verdict or tag or untag:
                raise MiningError("--compact takes no --where and no decision")
            merged, kept = labels.compact(store, lock_wait_s)
            print(f"mine label: {out}: merged {merged} label files into one ({kept} events)" if merged
                  else f"mine label: {out}: nothing to compact ({kept} events in at most one file)")
            return 0
        if where is None:
            raise MiningError("give --where PREDICATE (the tubes to label), e.g. --where \"known = false\"")
        kind, value, op = decision(verdict, clear_verdict, tag, untag)
        tubes = matching_tubes(out, where)
        if not tubes:
            raise NothingMatched(f"no tube matches --where {where!r}; nothing labelled")
        table = labels.events(tubes, kind, value, op, author, via="cli")
        value = table["value"][0].as_py()
        what = ((f"verdict {value}" if op == "set" else "verdict cleared") if kind == "verdict"
                else f"tag {value!r} " + ("added" if op == "set" else "removed"))
        if dry_run:
            print(f"mine label: would label {len(tubes)} tubes: {what} (nothing written: --dry-run)")
            return 0
        rel = labels.append(store, table)
        print(f"mine label: {len(tubes)} tubes: {what} by {table['author'][0].as_py()} → {store.full(rel)}")
        return 0
    except NothingMatched:
        raise
    except MiningError as e:
        print(f"mine label: {e}", file=sys.stderr)
        return 2
