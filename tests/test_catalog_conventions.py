"""Catalogue conventions an outside reader meets: column descriptions and units in the Parquet
files and in DuckDB; the documented reader options that keep ``sequence`` a string."""

from __future__ import annotations

from pathlib import Path

import duckdb
import pandas as pd
import polars as pl
import pyarrow.dataset as ds
import pyarrow.parquet as pq
import pytest

from _jobs import SEQ
from mining.catalog import views
from mining.catalog.schema import column_doc, partitioning

pytestmark = pytest.mark.slow  # the session's small mined catalogue


def test_descriptions_and_units_in_parquet_and_duckdb(base_catalogue):
    out = base_catalogue[0]
    f = sorted((out / "catalog" / "tubes").rglob("*.parquet"))[0]
    field = pq.read_schema(f).field("speed")
    desc, unit = column_doc("tubes", "speed")
    assert desc and unit == "m/s"
    assert field.metadata[b"description"].decode() == desc and field.metadata[b"unit"] == b"m/s"
    con = views.connect(out)
    comment = con.execute("SELECT comment FROM duckdb_columns() WHERE table_name = 'tubes' AND column_name = 'speed'").fetchone()[0]
    assert desc in comment and "m/s" in comment


def test_sequence_reads_as_a_string_in_four_readers(base_catalogue):
    folder = base_catalogue[0] / "catalog" / "tubes"
    glob = str(folder / "**" / "*.parquet")
    got = {
        "pandas": set(pd.read_parquet(folder, partitioning=partitioning())["sequence"]),
        "pyarrow": set(ds.dataset(folder, partitioning=partitioning()).to_table().column("sequence").to_pylist()),
        "polars": set(pl.read_parquet(glob, hive_partitioning=True,
                                      hive_schema={"dataset": pl.String, "sequence": pl.String})["sequence"]),
        "duckdb": {r[0] for r in duckdb.sql(
            f"SELECT DISTINCT sequence FROM read_parquet('{glob}', hive_partitioning = true, "
            "hive_types = {'dataset': VARCHAR, 'sequence': VARCHAR})").fetchall()},
    }
    assert got == {k: {SEQ} for k in got}, got
    # Without the options, the folder name reads as a number: why the options are documented.
    assert set(ds.dataset(folder, partitioning="hive").to_table().column("sequence").to_pylist()) == {int(SEQ)}
