"""Catalogue conventions an outside reader meets: column descriptions and units in the Parquet
files and in DuckDB; ``sequence`` a string with every reader's default options (schema v3), and
a catalogue of the hive layout before it still read."""

from __future__ import annotations

from pathlib import Path

import duckdb
import pandas as pd
import polars as pl
import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq
import pytest

from _jobs import SEQ, copy_of, mine, tables, to_hive_layout
from _run import cli
from mining.catalog import views
from mining.catalog.integrity import catalogue_damage
from mining.catalog.schema import SCHEMAS, column_doc
from mining.catalog.store import Store
from mining.errors import InputError

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


def test_sequence_reads_as_a_string_in_every_reader_by_default(base_catalogue):
    """Schema v3: every compacted table's files hold ``dataset`` / ``sequence`` and its folders have
    plain names, so the all-digit sequence "0000" reads as that string with each reader's DEFAULT
    options (hive folders ``sequence=0000`` read as the integer 0 unless a reader was told otherwise)."""
    out = base_catalogue[0]
    for table in ("tubes", "tube_frames", "frames", "windows"):
        folder = out / "catalog" / table
        assert [p.relative_to(folder).parts[:2] for p in folder.rglob("*.parquet")] == [("synthetic", SEQ)], table
        glob = str(folder / "**" / "*.parquet")
        frames = {
            "pandas": pd.read_parquet(folder),
            "pyarrow.dataset": ds.dataset(folder).to_table().to_pandas(),
            "pyarrow.parquet": pq.read_table(folder).to_pandas(),
            "polars": pl.read_parquet(glob).to_pandas(),
            "duckdb": duckdb.sql(f"SELECT * FROM read_parquet('{folder}/*/*/*.parquet')").to_arrow_table().to_pandas(),
        }
        for reader, df in frames.items():
            assert len(df), (table, reader)
            assert list(df["sequence"].unique()) == [SEQ], (table, reader, df["sequence"].unique())
            assert list(df["dataset"].unique()) == ["synthetic"], (table, reader)
    schema = pq.read_schema(next((out / "catalog" / "tubes").rglob("*.parquet")))
    assert schema.field("sequence").type == pa.string() and schema.field("dataset").type == pa.string()


def test_a_catalogue_in_the_hive_layout_of_v2_is_still_read(base_catalogue, tmp_path, capsys):
    """A catalogue schema v2 wrote (hive folders, no dataset / sequence in the files) answers ``mine
    query`` as before, its files checked against its markers (a flipped bit is an error naming the
    file); resuming it is refused naming --new-run, which moves it aside and mines a v3 one."""
    out = copy_of(base_catalogue, tmp_path / "old")
    to_hive_layout(out)
    hive = sorted(str(p.relative_to(out)) for p in (out / "catalog").glob("*/*/*/*.parquet"))
    assert hive and all(p.split("/")[2] == "dataset=synthetic" and p.split("/")[3] == f"sequence={SEQ}" for p in hive)
    assert "dataset" not in pq.read_schema(out / hive[0]).names
    assert pd.read_parquet(out / "catalog" / "tubes")["sequence"].unique().tolist() == [int(SEQ)]  # why v3 moved

    got = tables(out)
    version = [n for n in SCHEMAS["tubes"].names if n != "run_id"].index("schema_version")
    base = base_catalogue[1]
    assert got["tube_frames"] == base["tube_frames"] and got["frames"] == base["frames"]
    assert [r[:version] + r[version + 1:] for r in got["tubes"]] == [r[:version] + r[version + 1:] for r in base["tubes"]]
    assert {r[version] for r in got["tubes"]} == {2}
    rc, o, e = cli(capsys, "query", "SELECT DISTINCT dataset, sequence FROM tube_tracks", "--out", str(out),
                   "--format", "csv")
    assert rc == 0 and o.replace('"', "").split() == ["dataset,sequence", f"synthetic,{SEQ}"], e
    assert catalogue_damage(Store(out), verify=True) == {}

    # Integrity holds for the old layout too: a file in either layout's folder of the sequence that
    # its marker does not record is a left-over that fails its table; a flipped bit too, naming the file.
    tubes_file = next(p for p in hive if p.startswith("catalog/tubes/"))
    stray = out / "catalog" / "tubes" / "synthetic" / SEQ / "part-0.parquet"
    stray.parent.mkdir(parents=True)
    stray.write_bytes((out / tubes_file).read_bytes())
    (damage,) = catalogue_damage(Store(out))["tubes"]
    assert damage.path == str(stray.relative_to(out)) and "left over" in damage.reason
    rc, o, e = cli(capsys, "query", "SELECT count(*) FROM tubes", "--out", str(out))
    assert rc != 0 and str(stray) in e, e
    stray.unlink()
    data = bytearray((out / tubes_file).read_bytes())
    data[len(data) // 2] ^= 1
    (out / tubes_file).write_bytes(bytes(data))
    rc, o, e = cli(capsys, "query", "SELECT count(*) FROM tubes", "--out", str(out))
    assert rc != 0 and tubes_file in e and "sha256" in e, e
    rc, o, e = cli(capsys, "query", "SELECT count(*) FROM frames", "--out", str(out), "--format", "csv")
    assert rc == 0 and o.replace('"', "").split()[-1] == "16", e

    # Resuming or extending it is refused, naming the reason and the fix; --new-run mines a v3 catalogue.
    with pytest.raises(InputError, match="hive folders.*--new-run") as err:
        mine(out)
    assert "dataset=" in str(err.value)
    s = mine(out, (0, 8), mode="new")
    assert s.ok == 1 and not s.failed, s.lines()
    assert sorted(p.relative_to(out / "catalog").parts[1:3] for p in (out / "catalog").glob("*/*/*/*.parquet")) == \
        [("synthetic", SEQ)] * 4
    assert len(tables(out)["frames"]) == 8
