"""Safe SQL over a real catalogue (issue 11, item 8): ``mine export --where`` is one SQL
expression (DuckDB's parser decides, not string pasting), DuckDB's temporary folder
exposes no file of the caller's, and ``mine query`` runs within memory, thread and time
limits. The catalogue is the real KITTI 0005 one of ``tests/_catalog_data.py``; commands
run through ``mining.cli.main``."""

from __future__ import annotations

import gc
import json
import stat
import time
from pathlib import Path

import pytest

from _run import cli
from mining.catalog.views import connect


def _export(capsys, cat: Path, dest: Path, where: str) -> tuple[int, str, str]:
    return cli(capsys, "export", str(dest), "--format", "kitti", "--where", where, "--out", str(cat))


def _exported_rows(dest: Path) -> int:
    return sum(len(p.read_text().splitlines()) for p in dest.glob("*.txt"))


def test_where_injection_is_refused(catalogue, tmp_path, capsys):
    cat, tables = catalogue
    rc, stdout, _ = _export(capsys, cat, tmp_path / "all", "true")
    assert rc == 0 and f"{tables['tubes'].num_rows} tubes" in stdout
    everything = _exported_rows(tmp_path / "all")
    # Before: pasted into SQL, this turned 14 tubes into 108.
    rc, stdout, stderr = _export(capsys, cat, tmp_path / "injected", "true) UNION ALL SELECT * FROM tubes WHERE (true")
    assert rc == 2, (stdout, stderr)
    assert "not one SQL expression over the tubes table" in stderr and "set operation" in stderr
    assert _exported_rows(tmp_path / "injected") == 0 < everything


@pytest.mark.parametrize("where, why", [
    ("selected) LIMIT 1 --", "ORDER BY, LIMIT or DISTINCT"),
    ("selected) ORDER BY score --", "ORDER BY, LIMIT or DISTINCT"),
    ("true) GROUP BY ALL HAVING (true", "HAVING"),
    ("selected); SELECT (1", "not one SQL expression"),
    ("tube_id IN (SELECT tube_id FROM tube_frames)", "subquery"),
    ("EXISTS (SELECT * FROM windows)", "subquery"),
], ids=["limit", "order-by", "having", "two-statements", "in-subquery", "exists"])
def test_where_that_adds_anything_is_refused(catalogue, tmp_path, capsys, where, why):
    cat, _ = catalogue
    rc, stdout, stderr = _export(capsys, cat, tmp_path / "dest", where)
    assert rc == 2 and why in stderr and "Traceback" not in stderr, (stdout, stderr)


def test_ordinary_predicates_still_work(catalogue, tmp_path, capsys):
    cat, tables = catalogue
    tubes = tables["tubes"].to_pylist()
    want = sum(1 for t in tubes if t["selected"] and t["score"] > 0 and (t["known"] is None or t["known"]))
    rc, stdout, stderr = _export(capsys, cat, tmp_path / "d",
                                 "selected AND score > 0 -- a comment\n AND (known IS NULL OR known)")
    assert rc == 0, stderr
    assert f"{want} tubes" in stdout


def test_duckdb_temp_folder_is_private_and_exposes_no_file(catalogue, tmp_path, capsys, monkeypatch):
    cat, _ = catalogue
    # Before: DuckDB's default temporary folder <cwd>/.tmp was allowed for reading.
    (tmp_path / ".tmp").mkdir()
    (tmp_path / ".tmp" / "secret.csv").write_text("token\nhunter2\n")
    monkeypatch.chdir(tmp_path)
    rc, stdout, stderr = cli(capsys, "query", "SELECT * FROM read_csv('.tmp/secret.csv')", "--out", str(cat))
    assert rc == 2 and "hunter2" not in stdout, stdout
    assert "Permission" in stderr or "disabled" in stderr, stderr
    # The folder it spills to instead is its own: mode 0700, gone with the connection.
    con = connect(cat)
    spill = Path(con.sql("SELECT current_setting('temp_directory')").fetchone()[0])
    parent = spill.parent
    assert parent.is_dir() and stat.S_IMODE(parent.stat().st_mode) == 0o700 and parent.owner() == Path.home().owner()
    assert not str(spill).startswith(str(tmp_path))
    con.close()
    del con
    gc.collect()
    assert not parent.exists()


def test_query_stops_at_its_time_limit(catalogue, capsys):
    cat, _ = catalogue
    t0 = time.perf_counter()
    rc, stdout, stderr = cli(capsys, "query", "SELECT count(*) FROM range(10000000000000) t(i) WHERE i % 7 = 3",
                             "--out", str(cat), "--timeout", "1")
    elapsed = time.perf_counter() - t0
    assert rc == 2 and "ran past --timeout 1 s" in stderr, (stdout, stderr)
    assert elapsed < 30, elapsed


def test_query_memory_and_thread_limits(catalogue, capsys):
    cat, _ = catalogue
    sql = "SELECT current_setting('threads') AS threads, current_setting('memory_limit') AS memory"
    rc, stdout, _ = cli(capsys, "query", sql, "--out", str(cat), "--format", "json")
    assert rc == 0
    row = json.loads(stdout)[0]
    assert row["threads"] == 2 and row["memory"].endswith("GiB") and float(row["memory"].split()[0]) < 2.0
    rc, stdout, _ = cli(capsys, "query", sql, "--out", str(cat), "--format", "json", "--threads", "1",
                        "--memory-limit", "500MB")
    row = json.loads(stdout)[0]
    assert rc == 0 and row["threads"] == 1 and row["memory"].endswith("MiB")
    # A query cannot lift its limits (SET is not a read; the configuration is locked anyway).
    rc, _, stderr = cli(capsys, "query", "SET threads = 8", "--out", str(cat))
    assert rc == 2 and "read-only" in stderr
