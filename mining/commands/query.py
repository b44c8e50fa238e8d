"""``mine query``: read-only SQL (DuckDB) over the catalogue's tables and views, as a table, CSV,
JSON or Parquet (``catalog/query.py`` runs and writes it)."""

from __future__ import annotations

import argparse
from pathlib import Path

from mining.checks import count, memory_size, output_file, path_text, time_limit
from mining.errors import ConfigError, MiningError
from mining.pipeline.arguments import add_overwrite_option


def add_arguments(qry: argparse.ArgumentParser) -> None:
    qry.add_argument("sql")
    qry.add_argument("--out", type=path_text, default="out/catalog", help="catalogue folder or URI")
    qry.add_argument("--format", choices=["table", "csv", "json", "parquet"], default="table")
    qry.add_argument("--output", type=output_file, help="write here instead of standard output (required for parquet)")
    add_overwrite_option(qry, "--output")
    qry.add_argument("--memory-limit", type=memory_size, help="most memory the query may use, e.g. 4GB; beyond it DuckDB spills to "
                                            "a private temporary folder (default: query.MEMORY_LIMIT, 2GB)")
    qry.add_argument("--threads", type=count(1, 1024), help="threads the query may use (default: query.THREADS, 2)")
    qry.add_argument("--timeout", type=time_limit, metavar="SECONDS",
                     help="stop the query after this many seconds (default: query.TIMEOUT_S, 60)")
    qry.add_argument("--limit", type=count(0, 10**12), metavar="N",
                     help="table output shows at most N rows and the total count (default: query.LIMIT, 50; 0 = all)")


def run(args: argparse.Namespace) -> int:
    return run_query(args.sql, args.out, args.format, args.output, args.memory_limit, args.threads, args.timeout,
                     args.limit, overwrite=args.overwrite)


def run_query(sql: str, out: str | Path, fmt: str = "table", output: str | Path | None = None,
              memory_limit: str | None = None, threads: int | None = None, timeout_s: float | None = None,
              limit: int | None = None, overwrite: bool = False) -> int:
    """`mine query`: 0 on success. A limit left None is ``catalog/query.py``'s default
    (``MEMORY_LIMIT``, ``THREADS``, ``TIMEOUT_S``, ``LIMIT``). ConfigError for options that do
    not fit; MiningError for bad SQL, a missing catalogue, a statement that would write, a
    query past its limits or an ``output`` that may not be written (checked before the query
    runs), or that could not be (``cli.main``: one line, exit status 2)."""
    import duckdb  # here, as the query module: DuckDB and Arrow take a while to load

    from mining.catalog import safe_files
    from mining.catalog.query import FORMATS, LIMIT, MEMORY_LIMIT, THREADS, TIMEOUT_S, query_table, write_result

    memory_limit = MEMORY_LIMIT if memory_limit is None else memory_limit
    threads, timeout_s = THREADS if threads is None else threads, TIMEOUT_S if timeout_s is None else timeout_s
    limit = LIMIT if limit is None else limit
    if limit < 0:
        raise ConfigError(f"--limit must be ≥ 0 (0 = all rows), got {limit}")
    if threads < 1 or not timeout_s > 0:
        raise ConfigError(f"--threads must be ≥ 1 and --timeout > 0, got {threads} and {timeout_s}")
    if fmt not in FORMATS:
        raise ConfigError(f"unknown format {fmt!r}; one of {', '.join(FORMATS)}")
    if fmt == "parquet" and not output:
        raise ConfigError("--format parquet needs --output FILE")
    try:
        if output is not None:
            safe_files.check_output_file(output, overwrite, "--output")
        t = query_table(sql, out, memory_limit, threads, timeout_s)
        write_result(t, fmt, output, limit, overwrite)
    except MiningError:
        raise
    except duckdb.Error as e:  # bad SQL, a damaged file: DuckDB's message names it
        raise MiningError(str(e)) from None
    except OSError as e:
        raise MiningError(f"cannot write {output}: {e}") from None
    return 0
