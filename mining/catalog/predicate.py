"""``mine export --where``: one SQL expression over the tubes table, checked by DuckDB's parser.

The predicate is never pasted into SQL as text. It is wrapped as ``SELECT * FROM tubes
WHERE (<expr>)`` and parsed by DuckDB (``json_serialize_sql``, the parser's own syntax
tree as JSON); the tree must be exactly one plain SELECT of ``*`` from ``tubes`` whose
only addition is the WHERE clause — no set operation (``true) UNION ALL SELECT …
WHERE (true``), no ORDER BY / LIMIT / GROUP BY / HAVING / QUALIFY / SAMPLE / CTE smuggled
in after a closing parenthesis, no second statement. Decision: subqueries are refused
anywhere in the expression (they could read other tables and views); export by
``tube_id IN (…)`` with ids found by ``mine query`` instead.

The expression may name the labels' columns too (``verdict``, ``tags``, ``tag``,
``labelled_at``, ``labelled_by``): the checked tree reads the view ``labelled_tubes`` (the tubes
with their labels, views.sql) in place of ``tubes``.

What runs is the statement DuckDB renders back from that tree (``json_deserialize_sql``),
never the user's text, and only if rendering it again parses to the same tree: comments
and stray quotes cannot change what it means when it is embedded in the export's other
queries. Those run on the read-only catalogue connection (``views.connect``) through
``views.execute_read_only``.
"""

from __future__ import annotations

import json
from typing import Any

import duckdb

from mining.errors import InputError

_WRAP = "SELECT * FROM tubes WHERE ({})"
LABELLED = "labelled_tubes"  # what the checked statement reads: tubes and their labels (views.sql)
# The parts of a SELECT node that must be empty: anything here was added around the predicate.
_EMPTY = {"modifiers": ([], "ORDER BY, LIMIT or DISTINCT"), "group_expressions": ([], "GROUP BY"),
          "group_sets": ([], "GROUP BY"), "having": (None, "HAVING"), "sample": (None, "USING SAMPLE"),
          "qualify": (None, "QUALIFY")}


# What a predicate can cause when it runs: unknown names, wrong types, a value that does not convert.
# The rest (a damaged table, a full disk) is the catalogue's, not the predicate's.
PREDICATE_ERRORS = (duckdb.ParserException, duckdb.BinderException, duckdb.CatalogException,
                    duckdb.ConversionException, duckdb.TypeMismatchException, duckdb.OutOfRangeException)


class PredicateError(InputError):
    """A ``--where`` that is not one plain SQL expression over the tubes table."""


def _parse(con: duckdb.DuckDBPyConnection, sql: str) -> dict[str, Any]:
    return json.loads(con.execute("SELECT json_serialize_sql(?)", [sql]).fetchone()[0])


def _strip_locations(node: Any) -> Any:
    if isinstance(node, dict):
        return {k: _strip_locations(v) for k, v in node.items() if k != "query_location"}
    if isinstance(node, list):
        return [_strip_locations(v) for v in node]
    return node


def _has_subquery(node: Any) -> bool:
    if isinstance(node, dict):
        return node.get("class") == "SUBQUERY" or any(_has_subquery(v) for v in node.values())
    if isinstance(node, list):
        return any(_has_subquery(v) for v in node)
    return False


def _shape_problem(tree: dict[str, Any]) -> str | None:
    """Why a parsed wrapper is not ``SELECT * FROM tubes WHERE (<one expression>)``, or None."""
    statements = tree.get("statements", [])
    if len(statements) != 1:
        return f"it makes {len(statements)} SQL statements"
    node = statements[0]["node"]
    if node.get("type") != "SELECT_NODE":
        return f"it turns the query into a {node.get('type', '?').replace('_NODE', '').replace('_', ' ').lower()}"
    if node.get("cte_map", {}).get("map"):
        return "it adds a WITH clause"
    for key, (empty, clause) in _EMPTY.items():
        if node.get(key, empty) != empty:
            return f"it adds {clause} to the query"
    if node.get("aggregate_handling", "STANDARD_HANDLING") != "STANDARD_HANDLING":
        return "it changes the query's aggregation"
    select = node.get("select_list", [])
    if len(select) != 1 or select[0].get("class") != "STAR" or select[0].get("exclude_list") or \
            select[0].get("replace_list") or select[0].get("rename_list") or select[0].get("expr"):
        return "it changes the selected columns"
    src = node.get("from_table") or {}
    if src.get("type") != "BASE_TABLE" or src.get("table_name") != "tubes" or src.get("schema_name") or \
            src.get("catalog_name") or src.get("alias") or src.get("sample") or src.get("at_clause"):
        return "it changes the table read"
    if node.get("where_clause") is None:
        return "it holds no expression"
    if _has_subquery(node["where_clause"]):
        return "it holds a subquery (refused: --where may read the tubes table only)"
    return None


def tubes_query(where: str) -> str:
    """The statement selecting the tubes matching ``where`` (see the module docstring);
    PredicateError naming the predicate and what is wrong with it."""
    if "\x00" in where:
        raise PredicateError(f"--where {where!r}: holds a NUL character")
    con = duckdb.connect(":memory:")  # parsing only: nothing is executed on it
    try:
        tree = _parse(con, _WRAP.format(where))
        if tree.get("error"):
            raise PredicateError(f"--where {where!r} is not one SQL expression: {tree.get('error_message', '')}")
        if (problem := _shape_problem(tree)) is not None:
            raise PredicateError(f"--where {where!r} is not one SQL expression over the tubes table: {problem}")
        # The expression reads the tubes with their labels (views.sql ``labelled_tubes``): a
        # predicate may say ``verdict = 'object'`` or ``list_contains(tags, 'barrier')``.
        tree["statements"][0]["node"]["from_table"]["table_name"] = LABELLED
        sql = con.execute("SELECT json_deserialize_sql(?)", [json.dumps(tree)]).fetchone()[0]
        again = _parse(con, sql)
        if again.get("error") or _strip_locations(again) != _strip_locations(tree):
            raise PredicateError(f"--where {where!r}: DuckDB does not render it back unchanged; simplify it")
        return sql
    except duckdb.Error as e:
        raise PredicateError(f"--where {where!r} cannot be parsed: {e}") from None
    finally:
        con.close()
