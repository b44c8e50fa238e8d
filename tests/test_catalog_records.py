"""The records under ``--out`` as types (``mining/catalog/records.py``): each loads tolerantly
(a damaged record is an ``Unreadable`` naming the file and why, never an exception; job.json's
is raised, as an ``UnreadableRecord``), saves as
the pipeline always wrote it, and ``mine status`` names a record that does not read; a
resubmission then recomputes what it vouched for. The catalogue cases use the small synthetic
job of ``conftest.base_catalogue`` (mined once, copied).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from _jobs import SEQ, copy_of, mine, tables
from mining.catalog.layout import done_path, files_path, stitch_path
from mining.catalog.records import (FRESH_START, JobRecord, ManifestRow, SequenceMarker, Unreadable,
                                    UnreadableRecord, WindowFiles)
from mining.catalog.store import Store
from mining.cli import main
from mining.types import Window


D = f"dataset=synthetic/sequence={SEQ}"
MARKER = f"catalog/_sequences/{D}.json"
STITCH = f"manifest/{D}/stitch.parquet"
W = Window("d", "s", (0, 8), (0, 12))
DIGEST = {"size": 3, "sha256": "ab" * 32}


def _status(capsys, out: Path) -> tuple[int, str]:
    capsys.readouterr()
    rc = main(["status", "--out", str(out)])
    got = capsys.readouterr()
    return rc, got.out + got.err


# -- the records alone ------------------------------------------------------------------------

def test_a_marker_saves_as_the_stitch_wrote_it_and_loads_back(tmp_path):
    store = Store(tmp_path)
    m = SequenceMarker("d", "s", ("s-0000000-0000008",), files={"catalog/tubes/x.parquet": DIGEST},
                       params_hash="p", run_id="r", contexts={"s-0000000-0000008": (0, 12)}, planned=2,
                       finished="2026-01-01T00:00:00+00:00")
    m.save(store)
    written = json.loads((tmp_path / done_path("d", "s")).read_text())
    assert list(written) == ["params_hash", "run_id", "dataset", "sequence", "windows", "contexts", "planned",
                             "finished", "files", "schema_version"]
    assert SequenceMarker.load(store, "d", "s") == m
    assert SequenceMarker.load(store, "d", "other") is None
    assert m.of_job("p", {"s-0000000-0000008": (0, 12)}) and not m.of_job("q")
    assert not m.of_job("p", {"s-0000000-0000008": (0, 16)})  # the window's context was widened since


@pytest.mark.parametrize("content, reason", [
    (b'{"windows": ["a", "b"], "fil', "not valid JSON"),
    (b"[]", "expected a JSON object, got an array"),
    (b'{"x": 1}', "key 'windows' is missing"),
    (b'{"windows": "a"}', "key 'windows' holds a string"),
    (b'{"windows": [], "files": {"f": {"size": "3"}}}', "key 'files' holds an object"),
    (b'{"windows": [], "dataset": "d", "sequence": "t"}', "another sequence's marker"),
    (b"\xff\xfe", "not valid JSON"),
    (b"[" * 100_000 + b"]" * 100_000, "not valid JSON"),  # a RecursionError inside json.loads (issue 40)
])
def test_a_damaged_or_foreign_marker_is_unreadable_with_why(tmp_path, content, reason):
    store = Store(tmp_path)
    (tmp_path / done_path("d", "s")).parent.mkdir(parents=True)
    (tmp_path / done_path("d", "s")).write_bytes(content)
    got = SequenceMarker.load(store, "d", "s")
    assert isinstance(got, Unreadable) and got.path == done_path("d", "s") and reason in got.reason, got
    assert SequenceMarker.load_all(store) == [got]


def test_every_marker_file_is_listed_a_stray_one_as_unreadable(tmp_path):
    store = Store(tmp_path)
    SequenceMarker("d", "s", ()).save(store)
    (tmp_path / "catalog" / "_sequences" / "stray.json").write_text("{}")
    marker, stray = SequenceMarker.load_all(store)  # sorted by path
    assert marker == SequenceMarker("d", "s", ())
    assert isinstance(stray, Unreadable) and stray.path == "catalog/_sequences/stray.json"


def test_a_windows_files_record_names_what_it_lacks_and_refuses_another_windows(tmp_path):
    store = Store(tmp_path)
    parts = {f"_parts/{t}/dataset=d/sequence=s/{W.name}.part": DIGEST for t in ("tubes", "frames")}
    WindowFiles(W, parts).save(store)
    got = WindowFiles.load(store, W)
    assert got == WindowFiles(W, parts)
    assert got.missing() == [f"_parts/tube_frames/dataset=d/sequence=s/{W.name}.part"]
    other = Window("d", "s", (8, 16), (4, 20))
    (tmp_path / files_path("d", "s", other.name)).write_text(json.dumps({"window": W.name, "files": parts}))
    got = WindowFiles.load(store, other)
    assert isinstance(got, Unreadable) and f"records window {W.name!r}" in got.reason
    (tmp_path / files_path("d", "s", other.name)).write_text('{"window": "x"')
    assert isinstance(WindowFiles.load(store, other), Unreadable)
    assert WindowFiles.load(store, Window("d", "s", (16, 24), (12, 24))) is None


def test_a_manifest_row_round_trips_and_a_damaged_one_is_unreadable(tmp_path):
    store = Store(tmp_path)
    row = ManifestRow("r", W.name, W.core, W.context, "done", 2, "p", n_pieces=3, context_complete=True)
    row.save(store, "d", "s")
    assert ManifestRow.load(store, "d", "s", W.name) == row
    assert row.says_done("p", W) and row.says_done("p") and not row.says_done("q", W)
    assert not row.says_done("p", Window("d", "s", (0, 8), (0, 16)))  # planned with another context now
    assert ManifestRow.load(store, "d", "s", "stitch") is None
    (tmp_path / stitch_path("d", "s")).write_bytes(b"not parquet")
    got = ManifestRow.load(store, "d", "s", "stitch")
    assert isinstance(got, Unreadable) and got.path == stitch_path("d", "s") and "Parquet" in got.reason


JOB_OK = {"run_id": "r", "params_hash": "p", "config": {}, "windows": []}
WIN = {"dataset": "d", "sequence": "s", "core": [0, 8], "context": [0, 12]}


@pytest.mark.parametrize("content, reason", [
    (b'{"run_id": "r", "par', "not valid JSON"),
    (b'{"run_id": ' + b"[" * 100_000 + b"]" * 100_000 + b"}", "not valid JSON"),  # RecursionError (issue 40)
    (b"[]", "expected a JSON object, got an array"),
    (b'{"run_id": "r"}', "key 'params_hash' is missing"),
    (json.dumps({**JOB_OK, "run_id": 1}).encode(), "key 'run_id' holds a number, expected a run id"),
    (json.dumps({**JOB_OK, "windows": {}}).encode(), "key 'windows' holds an object, expected a list of windows"),
    (json.dumps({**JOB_OK, "windows": [WIN, {**WIN, "core": [8, 0]}]}).encode(),
     "windows[1]: key 'core' holds an array, expected [start, end] frame positions"),
    (json.dumps({**JOB_OK, "windows": [{**WIN, "sequence": None}]}).encode(),
     "windows[0]: key 'sequence' holds null, expected a name"),
    (json.dumps({**JOB_OK, "unplanned": {"s": 1}}).encode(), "key 'unplanned' holds an object, expected {sequence: reason}"),
    (json.dumps({**JOB_OK, "identity": []}).encode(), "key 'identity' holds an array, expected {key: value}"),
])
def test_a_job_record_that_does_not_read_is_raised_naming_why_and_the_fresh_start(tmp_path, content, reason):
    (tmp_path / "job.json").write_bytes(content)
    with pytest.raises(UnreadableRecord) as e:
        JobRecord.load(Store(tmp_path))
    assert str(e.value).startswith(f"file {tmp_path / 'job.json'}: job.json is not a job record: {reason}"), e.value
    assert str(e.value).endswith(f"; {FRESH_START}"), e.value


def test_a_job_record_with_a_window_name_that_is_a_path_is_unreadable(tmp_path):
    (tmp_path / "job.json").write_text(json.dumps({**JOB_OK, "windows": [{**WIN, "dataset": "../x"}]}))
    with pytest.raises(UnreadableRecord, match=r"dataset name '\.\./x' from job\.json is not a safe name"):
        JobRecord.load(Store(tmp_path))


def test_a_job_record_without_identity_or_unplanned_reads_as_older_versions_wrote_it(tmp_path):
    (tmp_path / "job.json").write_text(json.dumps({**JOB_OK, "windows": [WIN]}))
    got = JobRecord.load(Store(tmp_path))
    assert got.windows == [Window("d", "s", (0, 8), (0, 12))] and got.unplanned == {} and isinstance(got.identity, dict)


# -- mine status and resume over a damaged record ---------------------------------------------

@pytest.mark.slow  # a resubmission mines again
def test_status_names_a_truncated_marker_and_a_resubmission_stitches_again(base_catalogue, tmp_path, capsys):
    out = copy_of(base_catalogue, tmp_path / "out")
    data = (out / MARKER).read_bytes()
    (out / MARKER).write_bytes(data[: len(data) // 2])

    rc, text = _status(capsys, out)
    assert rc == 1, text
    assert f"damaged  {MARKER}: unreadable: not valid JSON (" in text, text
    assert f"(a resubmission stitches sequence {SEQ} again)" in text, text
    assert "sequences: 0 stitched" in text and "Traceback" not in text, text
    s = mine(out)
    assert (s.ok, s.skipped, s.sequences_written) == (0, 2, 1), s.lines()  # no window ran: stitched again
    assert tables(out) == base_catalogue[1]
    assert _status(capsys, out)[0] == 0


@pytest.mark.parametrize("content, reason", [
    ("[]", "not a sequence marker: expected a JSON object, got an array"),
    ('{"x": 1}', "not a sequence marker: key 'windows' is missing"),
])
def test_status_names_a_foreign_marker(base_catalogue, tmp_path, capsys, content, reason):
    out = copy_of(base_catalogue, tmp_path / "out")
    (out / MARKER).write_text(content)
    rc, text = _status(capsys, out)
    assert rc == 1 and f"damaged  {MARKER}: unreadable: {reason} (a resubmission stitches sequence {SEQ} again)" \
        in text, text
    assert "integrity: 1 damaged" in text, text


def test_status_names_an_unreadable_stitch_row_and_a_resubmission_repairs_it(base_catalogue, tmp_path, capsys):
    out = copy_of(base_catalogue, tmp_path / "out")
    (out / STITCH).write_bytes(b"not parquet")
    rc, text = _status(capsys, out)
    assert rc == 1 and f"damaged  {STITCH}: unreadable: cannot read Parquet file" in text, text
    s = mine(out)
    assert (s.ok, s.skipped, s.sequences_written) == (0, 2, 1), s.lines()
    assert not (out / STITCH).exists()
    assert _status(capsys, out)[0] == 0


def test_status_reports_a_job_whose_config_does_not_read(base_catalogue, tmp_path, capsys):
    out = copy_of(base_catalogue, tmp_path / "out")
    record = json.loads((out / "job.json").read_text())
    record["config"]["no_such_section"] = {}
    (out / "job.json").write_text(json.dumps(record))
    rc, text = _status(capsys, out)
    assert rc == 0, text
    assert "config unreadable: " in text and "no_such_section" in text, text
    assert "2 windows: 2 done" in text and "integrity: 0 damaged" in text, text
