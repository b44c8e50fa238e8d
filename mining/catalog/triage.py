"""Scripted triage (``mine label``, ``commands/label.py``): the tubes a predicate selects, and
the one decision a command line gives.

The predicate is ``mine export``'s (``predicate.tubes_query``: one SQL expression over the
tubes and their labels, parsed, never pasted), run on the read-only catalogue; the decision
becomes label events (``labels.events``) appended as one new labels part (``labels.append``).
"""

from __future__ import annotations

from pathlib import Path

import duckdb

from mining.catalog.predicate import PREDICATE_ERRORS, tubes_query
from mining.catalog.views import connect, execute_read_only
from mining.errors import MiningError


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
