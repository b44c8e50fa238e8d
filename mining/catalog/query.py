"""Read-only SQL over the catalogue (``mine query``, ``commands/query.py``), as a table, CSV,
JSON or Parquet.

One query may take at most ``memory_limit`` of memory (DuckDB spills the rest to its
private temporary folder), ``threads`` threads and ``timeout_s`` seconds: a timer
thread interrupts the connection (``con.interrupt()``) when the time is up, so a shared
machine is not held by a runaway join. The defaults are the command's flag defaults.
"""

from __future__ import annotations

import io
import json
import math
import sys
import threading
from pathlib import Path

import duckdb
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from mining.catalog import safe_files
from mining.catalog.views import connect, execute_read_only, file_refused
from mining.errors import MiningError

FORMATS = ("table", "csv", "json", "parquet")
MEMORY_LIMIT = "2GB"  # ours: `mine query --memory-limit` default; a shared login node keeps the rest
THREADS = 2  # ours: `mine query --threads` default
TIMEOUT_S = 60.0  # ours: `mine query --timeout` default; catalogue queries take well under a second (`mine bench pipeline`)
MAX_CELL = 60  # ours: longer cells (RLE strings, posteriors) are cut in table output
LIMIT = 50  # ours: `mine query --limit` default: table output shows this many rows and the total (0 = all)


class QueryTimeout(MiningError):
    """A query stopped because it ran past its time limit."""


def query_table(sql: str, out: str | Path, memory_limit: str | None = MEMORY_LIMIT, threads: int | None = THREADS,
                timeout_s: float | None = TIMEOUT_S) -> pa.Table:
    """The result of a read-only query as an Arrow table, within the given limits (None: DuckDB's own)."""
    con = connect(out, memory_limit=memory_limit, threads=threads)
    timer = threading.Timer(timeout_s, con.interrupt) if timeout_s is not None else None
    try:
        if timer is not None:
            timer.daemon = True
            timer.start()
        rel = execute_read_only(con, sql)
        return rel.to_arrow_table() if rel is not None else pa.table({})
    except duckdb.PermissionException as e:  # a file function on a file the views do not vouch for
        raise file_refused(con, e) from None
    except duckdb.InterruptException:
        raise QueryTimeout(f"the query ran past --timeout {timeout_s:g} s and was stopped") from None
    finally:
        if timer is not None:
            timer.cancel()
        con.close()


def _cell(v) -> str:
    if v is None:
        return "NULL"
    if isinstance(v, float):
        return "NaN" if math.isnan(v) else f"{v:.6g}"
    if isinstance(v, list):
        s = "[" + ", ".join(_cell(x) for x in v) + "]"
    else:
        s = str(v)
    return s if len(s) <= MAX_CELL else s[: MAX_CELL - 1] + "…"


def format_table(t: pa.Table, limit: int = 0) -> str:
    """Aligned text: a header, a rule, one line per row (numbers right-aligned); at most
    ``limit`` rows (0: all), then the total."""
    shown = t.slice(0, limit) if limit and t.num_rows > limit else t
    rows = [[_cell(v) for v in row.values()] for row in shown.to_pylist()]
    names = t.column_names
    widths = [max([len(n)] + [len(r[i]) for r in rows]) for i, n in enumerate(names)]
    numeric = [pa.types.is_integer(f.type) or pa.types.is_floating(f.type) for f in t.schema]

    def line(cells):
        return "  ".join(c.rjust(w) if num else c.ljust(w) for c, w, num in zip(cells, widths, numeric)).rstrip()

    out = [line(names), line(["-" * w for w in widths])] + [line(r) for r in rows]
    if shown.num_rows < t.num_rows:
        out.append(f"({shown.num_rows} of {t.num_rows} rows shown; --limit N for more, --limit 0 for all, "
                   f"--format csv/json/parquet for every row)")
    else:
        out.append(f"({t.num_rows} row{'s' if t.num_rows != 1 else ''})")
    return "\n".join(out) + "\n"


def _json_value(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None  # JSON has no NaN / Infinity
    if isinstance(v, list):
        return [_json_value(x) for x in v]
    if isinstance(v, dict):
        return {k: _json_value(x) for k, x in v.items()}
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    if hasattr(v, "isoformat"):
        return v.isoformat()
    return v


def format_json(t: pa.Table) -> str:
    """A JSON list of records, one object per row."""
    return json.dumps([{k: _json_value(v) for k, v in r.items()} for r in t.to_pylist()], indent=1) + "\n"


def format_csv(t: pa.Table) -> str:
    # CSV has no lists: nested values are written as JSON text.
    cols = []
    for name, col in zip(t.column_names, t.columns):
        if pa.types.is_nested(col.type):
            col = pa.array([None if v is None else json.dumps(_json_value(v)) for v in col.to_pylist()], pa.string())
        cols.append(col)
    buf = io.BytesIO()
    pacsv.write_csv(pa.table(cols, names=t.column_names), buf)
    return buf.getvalue().decode()


def write_result(t: pa.Table, fmt: str, output: str | Path | None, limit: int = 0, overwrite: bool = False) -> None:
    """Write ``t``; ``limit`` cuts table output only (csv, json and parquet are for programs:
    every row). A file ``output`` keeps the destination rule (``safe_files.write_file``:
    atomic, never through a link, an existing file replaced only with ``overwrite``)."""
    if fmt == "parquet":
        safe_files.write_file(output, lambda f: pq.write_table(t, f, compression="zstd"), overwrite)
        return
    text = format_table(t, limit) if fmt == "table" else {"csv": format_csv, "json": format_json}[fmt](t)
    if output is None:
        sys.stdout.write(text)
    else:
        safe_files.write_file(output, text.encode(), overwrite)
