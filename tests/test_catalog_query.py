"""`mine query`: DuckDB views over real Parquet files, read-only, every output format."""

from __future__ import annotations

import csv
import io
import json

import duckdb
import pyarrow.parquet as pq
import pytest

from _catalog_data import DATASET, SEQUENCE
from mining.catalog.schema import SCHEMAS
from mining.catalog.views import ReadOnlyError, check_read_only, connect
from mining.commands.query import run_query
from mining.errors import ConfigError, MiningError


def test_tables_carry_dataset_and_sequence_as_text(catalogue):
    out, tables = catalogue
    con = connect(out)
    for table in ("tubes", "tube_frames", "frames", "windows"):
        assert [c[0] for c in con.sql(f"DESCRIBE {table}").fetchall()] == SCHEMAS[table].names
        assert con.sql(f"SELECT DISTINCT dataset, sequence FROM {table}").fetchall() == [(DATASET, SEQUENCE)]
    assert con.sql("SELECT count(*) FROM tubes").fetchone()[0] == tables["tubes"].num_rows
    assert con.sql("SELECT count(*) FROM tube_frames").fetchone()[0] == tables["tube_frames"].num_rows
    got = con.sql("SELECT tube_id, score FROM tubes ORDER BY tube_id").fetchall()
    want = sorted(zip(tables["tubes"]["tube_id"].to_pylist(), tables["tubes"]["score"].to_pylist()))
    assert got == want


def test_views(catalogue):
    out, tables = catalogue
    con = connect(out)
    tubes = tables["tubes"].to_pylist()
    sel = sorted(t["tube_id"] for t in tubes if t["selected"])
    assert sel and [r[0] for r in con.sql("SELECT tube_id FROM selected_tubes ORDER BY 1").fetchall()] == sel
    unknown = sorted(t["tube_id"] for t in tubes if t["selected"] and not t["known"])
    assert [r[0] for r in con.sql("SELECT tube_id FROM unknown_tubes ORDER BY 1").fetchall()] == unknown
    # Re-ranking by another weighting of the stored components is one SELECT.
    rerank = con.sql("SELECT tube_id FROM tube_scores ORDER BY score_mask - score_motion DESC, tube_id").fetchall()
    assert [r[0] for r in rerank] == [t["tube_id"] for t in sorted(tubes, key=lambda t: (-(t["score_mask"] - t["score_motion"]),
                                                                                          t["tube_id"]))]
    n_tracks = con.sql("SELECT count(*), count(DISTINCT category) FROM tube_tracks").fetchone()
    assert n_tracks[0] == tables["tube_frames"].num_rows
    by_tube = dict(con.sql("SELECT tube_id, count(*) FROM tube_tracks WHERE selected GROUP BY 1").fetchall())
    assert by_tube == {t["tube_id"]: t["n_frames"] for t in tubes if t["selected"]}


def test_the_call_views_partition_the_selected_tubes(catalogue, tmp_path):
    """known_tubes / unknown_tubes / clutter_tubes / unclassified_tubes: one per call, nothing in two; rows
    written before the call column (call null) read known false as unknown and null as unclassified."""
    import pyarrow as pa

    from mining.catalog.store import Store, write_sequence

    _, tables = catalogue
    tubes = tables["tubes"]
    n = tubes.num_rows
    call = [("known", "unknown", "clutter", "unclassified", None, None)[i % 6] for i in range(n)]
    known = [{"known": True, "unknown": False, "clutter": False, "unclassified": None}.get(c, (False, None)[i % 2])
             for i, c in enumerate(call)]
    category = ["car" if k else "unknown" if k is False else None for k in known]
    for name, values, kind in (("known", known, pa.bool_()), ("category", category, pa.string()),
                               ("call", call, pa.string())):
        tubes = tubes.set_column(tubes.schema.get_field_index(name), SCHEMAS["tubes"].field(name), pa.array(values, kind))
    write_sequence(Store(tmp_path), "tubes", DATASET, SEQUENCE, tubes)
    con = connect(tmp_path)
    legacy = {False: "unknown", None: "unclassified"}
    sel = {t["tube_id"]: c or legacy[k] for t, c, k in zip(tubes.to_pylist(), call, known) if t["selected"]}
    views = {c: {r[0] for r in con.sql(f"SELECT tube_id FROM {c}_tubes").fetchall()}
             for c in ("known", "unknown", "clutter", "unclassified")}
    for c, got in views.items():
        assert got == {t for t, v in sel.items() if v == c}, c
    assert sum(map(len, views.values())) == len(sel)


def test_empty_catalogue_has_every_table_and_view(tmp_path):
    con = connect(tmp_path)
    for table in ("tubes", "tube_frames", "frames", "windows"):
        assert con.sql(f"SELECT * FROM {table}").fetchall() == []
        assert con.sql(f"SELECT * FROM {table}").columns == SCHEMAS[table].names
    for view in ("selected_tubes", "unknown_tubes", "known_tubes", "unclassified_tubes", "tube_scores", "tube_tracks"):
        assert con.sql(f"SELECT count(*) FROM {view}").fetchone()[0] == 0


def test_pyarrow_filesystem_path_reads_the_same(catalogue):
    out, _ = catalogue
    native, arrow = connect(out), connect(f"file://{out}", native=False)
    q = "SELECT tube_id, dataset, sequence, frame, rle_counts, bbox FROM tube_tracks ORDER BY tube_id, frame"
    assert native.sql(q).fetchall() == arrow.sql(q).fetchall()
    assert native.sql("SELECT * FROM windows").fetchall() == arrow.sql("SELECT * FROM windows").fetchall()


def test_read_only(catalogue, capsys):
    out, _ = catalogue
    before = sorted(p for p in out.rglob("*"))
    target = out / "catalog" / "x.parquet"
    for sql in (f"COPY (SELECT 1) TO '{target}'", "CREATE TABLE t AS SELECT 1", "INSERT INTO tubes SELECT * FROM tubes",
                f"ATTACH '{out}/db.duckdb'", "SET enable_external_access = true", f"EXPLAIN ANALYZE COPY tubes TO '{target}'",
                "SELECT 1; DROP VIEW tubes"):
        with pytest.raises(ReadOnlyError):
            check_read_only(sql)
        with pytest.raises(MiningError, match="read-only"):
            run_query(sql, str(out), "table", None)
    for sql in ("SELECT 1", "WITH a AS (SELECT 1) SELECT * FROM a", "DESCRIBE tubes", "SUMMARIZE tubes", "SHOW TABLES",
                "EXPLAIN SELECT * FROM tubes", "FROM tubes"):
        check_read_only(sql)
    # Below the statement check, the connection itself can reach no file outside the catalogue …
    con = connect(out)
    with pytest.raises(duckdb.PermissionException):
        con.sql("SELECT * FROM read_csv('/etc/hostname')").fetchall()
    with pytest.raises(duckdb.Error):
        con.execute("SET enable_external_access = true")
    assert sorted(p for p in out.rglob("*")) == before, "nothing was written"


def test_formats(catalogue, capsys, tmp_path):
    out, tables = catalogue
    sql = "SELECT tube_id, n_frames, score, bbox, category_prob FROM tubes JOIN (SELECT tube_id, bbox FROM tube_frames " \
          "WHERE frame = 5) USING (tube_id) ORDER BY tube_id"
    ref = connect(out).sql(sql).fetchall()
    assert ref

    assert run_query(sql, str(out), "table", None) == 0
    text = capsys.readouterr().out.splitlines()
    assert text[0].split() == ["tube_id", "n_frames", "score", "bbox", "category_prob"]
    assert set(text[1]) <= {"-", " "} and text[-1] == f"({len(ref)} row{'s' if len(ref) != 1 else ''})"
    assert [line.split()[0] for line in text[2:-1]] == [r[0] for r in ref]
    widths = {len(line) for line in text[:2]}
    assert len(widths) == 1 or max(len(line) for line in text[2:-1]) <= max(widths)

    assert run_query(sql, str(out), "csv", None) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert [r["tube_id"] for r in rows] == [r[0] for r in ref]
    assert [json.loads(r["bbox"]) for r in rows] == [pytest.approx(list(r[3])) for r in ref]
    assert [float(r["score"]) for r in rows] == pytest.approx([r[2] for r in ref])

    dest = tmp_path / "q.json"
    assert run_query(sql, str(out), "json", str(dest)) == 0
    recs = json.loads(dest.read_text())
    assert [(r["tube_id"], r["n_frames"]) for r in recs] == [(r[0], r[1]) for r in ref]

    with pytest.raises(ConfigError, match="^--format parquet needs --output FILE$"):
        run_query(sql, str(out), "parquet", None)
    pq_dest = tmp_path / "q.parquet"
    assert run_query(sql, str(out), "parquet", str(pq_dest)) == 0
    t = pq.read_table(pq_dest)
    assert t.column_names == ["tube_id", "n_frames", "score", "bbox", "category_prob"]
    assert t["tube_id"].to_pylist() == [r[0] for r in ref]
    in_frame_5 = {r["tube_id"] for r in tables["tube_frames"].to_pylist() if r["frame"] == 5}
    assert t.num_rows == len(in_frame_5)


def test_errors(catalogue, tmp_path, capsys):
    out, _ = catalogue
    with pytest.raises(MiningError, match="(?i)parse"):
        run_query("SELEC nonsense", str(out), "table", None)
    with pytest.raises(MiningError, match="no_such_column"):
        run_query("SELECT no_such_column FROM tubes", str(out), "table", None)
    with pytest.raises(MiningError, match="catalogue folder not found"):
        run_query("SELECT 1", str(tmp_path / "missing"), "table", None)
    # … and on the command line each is one line in the command's name, exit status 2
    from mining.cli import main

    capsys.readouterr()
    assert main(["query", "SELECT no_such_column FROM tubes", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("mine query: Binder Error: ") and "no_such_column" in err, err
    for options, said in (([], "--threads must be ≥ 1 and --timeout > 0, got 0 and 60.0"),
                          (["fmt"], "unknown format 'xml'; one of table, csv, json, parquet")):
        with pytest.raises(ConfigError, match=f"^{said}$"):
            run_query("SELECT 1", str(out), "xml", threads=2) if options else run_query("SELECT 1", str(out), threads=0)


def test_bench_catalog_small(tmp_path, shared_data):
    """The catalogue bench on a small catalogue: real distinct RLEs, every example query answered."""
    from mining.bench.catalog import bench_catalog

    r = bench_catalog(tmp_path, n_rows=4000, repeats=1)
    con = connect(tmp_path / "bench_catalog")
    n, distinct = con.sql("SELECT count(*), count(DISTINCT rle_counts) FROM tube_frames").fetchone()
    assert n == r["tube_frame_rows"] == 4000 and distinct > 0.9 * n
    assert 20 < r["bytes_per_tube_frame"] < 1000
    assert set(r["query_s"]) == {"unknown_long_tubes", "tubes_by_category", "rerank", "one_tube_masks"}
    n_selected = con.sql("SELECT count(*) FROM selected_tubes").fetchone()[0]
    assert r["query_rows"]["rerank"] == min(100, n_selected) > 0 and r["query_rows"]["one_tube_masks"] > 0
    assert r["query_rows"]["unknown_long_tubes"] == con.sql(r["queries"]["unknown_long_tubes"]).fetchall().__len__() > 0
    # the bench catalogue is vouched for like a mined one: its readers check every file's checksum
    from mining.catalog.integrity import mined, vouched_files
    from mining.catalog.store import Store

    store = Store(str(tmp_path / "bench_catalog"))
    v = vouched_files(store)
    assert mined(store) and v.marked and not v.damage and all(v.files[t] for t in ("tubes", "tube_frames", "frames"))


def test_table_output_shows_at_most_limit_rows_with_the_total(catalogue, capsys):
    out, tables = catalogue
    n = tables["tube_frames"].num_rows
    assert n > 5
    assert run_query("SELECT tube_id, frame FROM tube_frames ORDER BY ALL", str(out), limit=5) == 0
    text = capsys.readouterr().out.splitlines()
    assert len(text) == 2 + 5 + 1 and text[-1].startswith(f"(5 of {n} rows shown")
    assert run_query("SELECT tube_id, frame FROM tube_frames", str(out), limit=0) == 0
    assert capsys.readouterr().out.splitlines()[-1] == f"({n} rows)"
    assert run_query("SELECT tube_id, frame FROM tube_frames", str(out), "csv") == 0  # programs get every row
    assert len(capsys.readouterr().out.splitlines()) == n + 1
    from mining.catalog.query import LIMIT

    assert LIMIT == 50
    with pytest.raises(ConfigError, match=r"^--limit must be ≥ 0 \(0 = all rows\), got -1$"):
        run_query("SELECT 1", str(out), limit=-1)
