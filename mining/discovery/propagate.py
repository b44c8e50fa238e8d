"""Label once, propagate with care: the tubes a decision reaches beyond the ones a person chose.

* ``like``: the unlabelled tubes within cosine distance D of a source tube's descriptor
  (``mine label --like TUBE --within D``). Unlabelled: no verdict and no tag (views.sql
  ``tube_labels``), so a propagation never overrides what a person decided. The events written
  are ``via`` propagated and carry their source tube and each tube's distance to it
  (``labels.LABEL_SCHEMA``), so ``tube_labels`` / ``labelled_tubes`` can be filtered by them
  (``labelled_via``, ``source_tube``, ``source_distance``).
* ``undo_like``: take a propagation back (``mine label --undo-like TUBE``): for every tube whose
  current verdict or tag was last set by a propagation from TUBE, an ``unset`` event; a decision
  taken since (by a person, or another propagation) is left alone.
* ``in_group``: the tubes of one group of the unknown set (``tube_groups``; ``mine label --group G``).
"""

from __future__ import annotations

from pathlib import Path

import duckdb
import numpy as np

from mining.catalog.store import Store
from mining.catalog.triage import matching_tubes
from mining.catalog.views import connect
from mining.discovery.similar import descriptor_of, open_index
from mining.errors import InputError, MiningError

Tube = tuple[str, str, str]  # (dataset, sequence, tube_id)


def _rows(out: str | Path, sql: str, params: list) -> list[tuple]:
    con = connect(out)
    try:
        return con.execute(sql, params).fetchall()
    except duckdb.Error as e:  # a damaged catalogue or labels file: the message names it
        raise MiningError(str(e).removeprefix("Invalid Input Error: ")) from None
    finally:
        con.close()


def like(out: str | Path, source: str, within: float, where: str | None = None) -> list[tuple[Tube, float]]:
    """The unlabelled tubes (but ``source``) within cosine distance ``within`` of ``source``,
    nearest first, among those ``where`` selects (None: all); each with its distance."""
    store = Store(out)
    index = open_index(store)
    query = descriptor_of(store, index, source)
    labelled = {r[0] for r in _rows(out, "SELECT tube_id FROM tube_labels", [])}
    allowed = None if where is None else {t[2] for t in matching_tubes(out, where)}
    keep = np.array([k for k, t in enumerate(index.tube_ids) if t != source and t not in labelled
                     and (allowed is None or t in allowed)], np.int64)
    rows, dist = index.exact.within(query, within, keep)
    return [(index.tube(k), float(d)) for k, d in zip(rows, dist)]


# The (tube, kind, value) whose newest event is a set by a propagation from the source tube.
_PROPAGATED_NOW = """
WITH ordered AS (
    SELECT *, row_number() OVER (PARTITION BY dataset, sequence, tube_id, kind, CASE WHEN kind = 'tag' THEN value END
                                 ORDER BY "at" DESC, label_id DESC) AS newest
    FROM labels
)
SELECT dataset, sequence, tube_id, kind, value, distance FROM ordered
WHERE newest = 1 AND op = 'set' AND via = 'propagated' AND source_tube = ?
ORDER BY kind, value, dataset, sequence, tube_id
"""


def propagated_from(out: str | Path, source: str) -> dict[tuple[str, str | None], list[tuple[Tube, float]]]:
    """(kind, value) → the tubes (with their distance) whose current decision of that kind and
    value is a propagation from ``source``: what ``--undo-like`` takes back."""
    found: dict[tuple[str, str | None], list[tuple[Tube, float]]] = {}
    for d, s, t, kind, value, dist in _rows(out, _PROPAGATED_NOW, [source]):
        found.setdefault((kind, value), []).append(((d, s, t), float(dist) if dist is not None else float("nan")))
    return found


def in_group(out: str | Path, group: int, where: str | None = None) -> list[Tube]:
    """The tubes of group ``group`` of ``tube_groups`` (−1: the noise), in id order, among those
    ``where`` selects (None: all). InputError when the unknown set was never grouped."""
    if not _rows(out, "SELECT count(*) FROM tube_groups", [])[0][0]:
        raise InputError(f"{out}: the unknown set is not grouped: run `mine group --out {out}` first")
    tubes = [tuple(r) for r in _rows(out, 'SELECT dataset, sequence, tube_id FROM tube_groups WHERE "group" = ? '
                                          "ORDER BY dataset, sequence, tube_id", [group])]
    if where is not None:
        allowed = set(matching_tubes(out, where))
        tubes = [t for t in tubes if t in allowed]
    return tubes
