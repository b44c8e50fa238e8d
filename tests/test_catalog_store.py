"""Catalogue storage: atomic writes, compaction per sequence, the schema files."""

from __future__ import annotations

import json
import subprocess
import sys

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from _catalog_data import DATASET, SEQUENCE
from mining.catalog.layout import catalog_dir
from mining.catalog.records import JobRecord
from mining.catalog.schema import SCHEMA_VERSION, SCHEMAS, file_schema
from mining.catalog.store import TMP_MARK, Store, conform, write_sequence
from mining.catalog.views import connect
from mining.errors import ConfigError, InputError
from mining.types import Window

from conftest import REPO


def test_write_table_replaces_whole_file(tmp_path):
    store = Store(tmp_path)
    rel = "_parts/tubes/dataset=a/sequence=b/w0.parquet"
    store.write_table(rel, pa.table({"x": [1, 2, 3]}))
    store.write_table(rel, pa.table({"x": [7, 8]}))
    assert store.read_table(rel).column("x").to_pylist() == [7, 8]
    assert store.list("_parts") == [rel]
    assert [p.name for p in (tmp_path / rel).parent.iterdir()] == ["w0.parquet"], "no temporary file stays"


def test_crash_mid_write_leaves_only_an_ignored_temp_file(catalogue):
    out, tables = catalogue
    store = Store(out)
    folder = catalog_dir("tube_frames", DATASET, SEQUENCE)
    (real,) = store.list(folder)
    # A crash half-way through writing: the first half of a real Parquet file, under a temp name.
    data = (out / real).read_bytes()
    crashed = out / folder / f".part-0.parquet{TMP_MARK}deadbeef"
    crashed.write_bytes(data[: len(data) // 2])
    try:
        assert store.list(folder) == [real]
        con = connect(out)
        assert con.sql("SELECT count(*) FROM tube_frames").fetchone()[0] == tables["tube_frames"].num_rows
        # The next write of that name goes through regardless.
        store.write_table(f"{folder}/extra.parquet", pa.table({"x": [1]}))
        assert store.exists(f"{folder}/extra.parquet")
    finally:
        crashed.unlink()
        store.remove(f"{folder}/extra.parquet")


def test_bytes_round_trip_and_idempotent_remove(tmp_path):
    store = Store(f"file://{tmp_path}")
    store.write_bytes("job.json", b'{"a": 1}')
    assert store.read_bytes("job.json") == b'{"a": 1}' and store.exists("job.json")
    assert store.list("", suffix=".json") == ["job.json"]
    store.remove("job.json")
    store.remove("job.json")
    assert not store.exists("job.json")


def test_write_sequence_round_trip_sorted_and_split(tmp_path, catalogue):
    _, tables = catalogue
    tf = tables["tube_frames"]
    shuffled = tf.take(pa.array(list(reversed(range(tf.num_rows)))))
    store = Store(tmp_path)
    written = write_sequence(store, "tube_frames", DATASET, SEQUENCE, shuffled, rows_per_file=20, row_group_rows=8)
    assert written == [f"{catalog_dir('tube_frames', DATASET, SEQUENCE)}/part-{k}.parquet"
                       for k in range(-(-tf.num_rows // 20))]
    back = pa.concat_tables([store.read_table(p) for p in written])
    assert back.schema.equals(file_schema("tube_frames"))
    expect = tf.sort_by([("tube_id", "ascending"), ("frame", "ascending")])  # dataset / sequence in the file (v3)
    assert back.equals(expect.cast(file_schema("tube_frames")))
    meta = pq.ParquetFile(tmp_path / written[0]).metadata
    assert meta.num_row_groups == 3 and meta.row_group(0).column(0).compression == "ZSTD"

    # A later compaction with fewer rows: new files first, stale ones removed.
    fewer = write_sequence(store, "tube_frames", DATASET, SEQUENCE, tf.slice(0, 10), rows_per_file=20)
    assert store.list("catalog") == fewer and len(fewer) == 1
    assert store.read_table(fewer[0]).num_rows == 10


def test_write_sequence_rejects_schema_mismatch(tmp_path, catalogue):
    _, tables = catalogue
    tubes = tables["tubes"]
    store = Store(tmp_path)
    with pytest.raises(ValueError, match=r"missing columns \['score'\]"):
        write_sequence(store, "tubes", DATASET, SEQUENCE, tubes.drop_columns(["score"]))
    with pytest.raises(ValueError, match="column n_frames has type int64"):
        i = tubes.schema.get_field_index("n_frames")
        write_sequence(store, "tubes", DATASET, SEQUENCE, tubes.set_column(i, "n_frames", tubes["n_frames"].cast(pa.int64())))
    with pytest.raises(ValueError, match="column run_id has 1 nulls"):
        i = tubes.schema.get_field_index("run_id")
        ids = pa.array([None] + tubes["run_id"].to_pylist()[1:], pa.string())
        write_sequence(store, "tubes", DATASET, SEQUENCE, tubes.set_column(i, pa.field("run_id", pa.string()), ids))
    with pytest.raises(ValueError, match="expected only 'other'"):
        write_sequence(store, "tubes", DATASET, "other", tubes)
    with pytest.raises(ValueError, match=r"unexpected columns \['window'\]"):
        write_sequence(store, "tubes", DATASET, SEQUENCE, tubes.append_column("window", pa.array(["w"] * len(tubes))))
    assert store.list("") == [], "nothing written on a mismatch"
    assert conform("tubes", tubes, DATASET, SEQUENCE).schema.equals(file_schema("tubes"))


def test_schema_json_is_generated_from_schema_py():
    """schemas/v<SCHEMA_VERSION>/ cannot drift from the package: the JSON from mining/catalog/schema.py, views.sql
    a copy of mining/catalog/views.sql."""
    r = subprocess.run([sys.executable, str(REPO / "schemas" / "generate.py"), "--check"], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    sys.path.insert(0, str(REPO / "schemas"))
    try:
        import generate
    finally:
        sys.path.pop(0)
    files = generate.generate()
    assert sorted(files) == sorted([f"{t}.json" for t in SCHEMAS] + ["views.sql"])
    assert files["views.sql"] == generate.STANDALONE + (REPO / "mining" / "catalog" / "views.sql").read_text()
    doc = __import__("json").loads(files["tubes.json"])
    assert [f["name"] for f in doc["fields"]] == SCHEMAS["tubes"].names
    assert next(f for f in doc["fields"] if f["name"] == "score")["comment"].startswith("the unary score_model names")


def test_the_published_views_run_on_their_own_inside_a_catalogue(base_catalogue, tmp_path, monkeypatch):
    """schemas/v<SCHEMA_VERSION>/views.sql in a bare DuckDB, from inside the catalogue folder: every view
    answers as `mine query`'s do, labels included once loaded."""
    import duckdb

    from _jobs import copy_of
    from mining.catalog import labels
    from mining.catalog.views import connect

    out = copy_of(base_catalogue, tmp_path / "c")
    store = Store(out)
    first = connect(out).execute("SELECT dataset, sequence, tube_id FROM tubes ORDER BY tube_id LIMIT 1").fetchone()
    labels.append(store, labels.events([first], "tag", "post"))
    views = ("selected_tubes", "unknown_tubes", "tube_scores", "tube_tracks", "provisional_tubes",
             "provisional_tube_frames", "tube_labels", "labelled_tubes")
    ours = connect(out)
    want = {v: ours.execute(f"SELECT count(*) FROM {v}").fetchone()[0] for v in views}
    monkeypatch.chdir(out)
    con = duckdb.connect()
    con.execute((REPO / "schemas" / f"v{SCHEMA_VERSION}" / "views.sql").read_text())
    con.execute("INSERT INTO labels SELECT * FROM read_parquet('labels/*.parquet')")
    assert {v: con.execute(f"SELECT count(*) FROM {v}").fetchone()[0] for v in views} == want
    assert want["tube_labels"] == 1 and want["selected_tubes"] > 0


def test_job_record_round_trips(tmp_path):
    store = Store(tmp_path)
    assert JobRecord.load(store) is None
    w = Window("synthetic", "0000", (10, 20), (5, 25))
    JobRecord("r1", "p1", {"window": {"core": 10}}, [w]).save(store)
    assert JobRecord.load(store) == JobRecord("r1", "p1", {"window": {"core": 10}}, [w])
    assert json.loads((tmp_path / "job.json").read_text())["windows"] == [
        {"dataset": "synthetic", "sequence": "0000", "window": "0000-0000010-0000020", "core": [10, 20],
         "context": [5, 25]}]


def test_job_record_refuses_other_params(tmp_path):
    record = JobRecord("r1", "p1", {}, [])
    record.check("p1", "cat")
    with pytest.raises(ConfigError, match=r"cat holds a catalogue made with params p1; this job has p2\. "
                                          r"Use another --out, or the same config to resume\."):
        record.check("p2", "cat")


def test_a_file_that_is_no_job_record_is_an_input_error(tmp_path):
    Store(tmp_path).write_bytes("job.json", b'{"run_id": "r1"}')
    with pytest.raises(InputError, match="job.json is not a job record"):
        JobRecord.load(Store(tmp_path))
