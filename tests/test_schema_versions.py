"""Catalogue schema versions are checked on read (``mining/catalog/versions.py``).

A catalogue written by a newer tube-miner (its rows, its sequence marker or its job.json say
``schema_version`` 99, or the next version with a column this code does not know) is refused by every reader
(``mine query``, ``export``, ``render``, ``view``, ``status``) and by a resubmission, in one
line naming the version found, the file and the version this code reads; nothing is written.
Before: each read it as version 2, exit 0, the unknown column dropped without a word. Rows
older than this code reads (v1) are refused by the readers with the command that replaces them.

Real files: the small synthetic job of ``tests/_jobs.py`` (``base_catalogue``, copied), its
files rewritten as a newer writer would write them (checksums in the marker updated: the
integrity checks pass, only the version differs).
"""

from __future__ import annotations

import json
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from _jobs import CLI_SMALL, SEQ, catalogue_files, copy_of
from _run import cli, clean_error
from mining.catalog import integrity
from mining.catalog.schema import SCHEMA_VERSION
from mining.catalog.store import Store

D = f"dataset=synthetic/sequence={SEQ}"
TUBES = f"catalog/tubes/synthetic/{SEQ}/part-0.parquet"  # the compacted tables' folders (schema v3)
FRAMES = f"catalog/frames/synthetic/{SEQ}/part-0.parquet"
MARKER = f"catalog/_sequences/{D}.json"
ROW = f"manifest/{D}/{SEQ}-0000000-0000008.parquet"


def _rewrite(out: Path, rel: str, table: pa.Table) -> None:
    """Write ``table`` at ``rel`` and record its size and sha256 in the marker, as its writer would."""
    pq.write_table(table, out / rel)
    marker = json.loads((out / MARKER).read_text())
    if rel in marker.get("files", {}):
        marker["files"][rel] = integrity.digest(Store(out), rel)
        (out / MARKER).write_text(json.dumps(marker))


def _set_rows(out: Path, version: int, extra: str | None = None, rel: str = TUBES) -> None:
    t = pq.read_table(out / rel)
    if "schema_version" in t.column_names:
        i = t.schema.get_field_index("schema_version")
        t = t.set_column(i, t.schema.field(i), pa.array([version] * t.num_rows, pa.int16()))
    if extra:
        t = t.append_column(extra, pa.array([1.5] * t.num_rows, pa.float32()))
    _rewrite(out, rel, t)


def _set_record(out: Path, rel: str, version: int) -> None:
    d = json.loads((out / rel).read_text())
    d["schema_version"] = version
    (out / rel).write_text(json.dumps(d))


def _readers(out: Path, tmp_path: Path) -> dict[str, list[str]]:
    return {
        "query": ["query", "SELECT count(*) FROM tubes", "--out", str(out)],
        "query windows": ["query", "SELECT count(*) FROM windows", "--out", str(out)],
        "export": ["export", "--out", str(out), "--where", "selected", "--format", "youtube-vis",
                   str(tmp_path / "export")],
        "render": ["render", str(tmp_path / "render.mp4"), "--out", str(out), "--sequence", SEQ],
        "view": ["view", "--out", str(out), "--port", "0"],
        "status": ["status", "--out", str(out)],
        "submit": ["submit", *CLI_SMALL, "--frames", "0:16", "--out", str(out)],
    }


def _refused_by_every_reader(capsys, monkeypatch, out: Path, tmp_path: Path, *named: str) -> None:
    """Each reader exits 2 with one line naming everything in ``named``; nothing is written."""
    from mining.view.httpd import ViewServer

    def serve_forever(self, *a, **k):  # the old code served a newer catalogue: stop at once, rc 0
        raise KeyboardInterrupt
    monkeypatch.setattr(ViewServer, "serve_forever", serve_forever)
    before = catalogue_files(out)
    for reader, args in _readers(out, tmp_path).items():
        rc, o, e = cli(capsys, *args)
        assert rc == 2, f"{reader}: rc {rc}: {o + e}"
        line = clean_error(e)
        assert len(e.strip().splitlines()) == 1, f"{reader}: {e}"
        for text in named:
            assert text in line, f"{reader}: {text!r} not in {line!r}"
        assert catalogue_files(out) == before, f"{reader} wrote into the catalogue"
    assert not (tmp_path / "export").exists() and not (tmp_path / "render.mp4").exists()


NEWER = {
    # where a newer writer's version is: what the refusal names (the file and the version found)
    "rows, marker and job.json at 99": (
        lambda out: (_set_rows(out, 99), _set_record(out, MARKER, 99), _set_record(out, "job.json", 99)),
        ("v99",)),
    "rows at the next version with a new column": (lambda out: _set_rows(out, SCHEMA_VERSION + 1, extra="speed_3d"),
                                                   (TUBES, f"v{SCHEMA_VERSION + 1}")),
    "job.json at 99": (lambda out: _set_record(out, "job.json", 99), ("job.json", "v99")),
    "the marker at 99": (lambda out: _set_record(out, MARKER, 99), (MARKER, "v99")),
    "a frames file with a new column": (lambda out: _set_rows(out, 0, extra="lux", rel=FRAMES), (FRAMES, "'lux'")),
    "a manifest row with a new column": (lambda out: _set_rows(out, 0, extra="gpu_seconds", rel=ROW),
                                         (ROW, "'gpu_seconds'")),
}


@pytest.mark.parametrize("case", list(NEWER))
def test_a_newer_catalogue_is_refused_by_every_reader_and_by_a_resubmission(base_catalogue, tmp_path, capsys,
                                                                           monkeypatch, case):
    out = copy_of(base_catalogue, tmp_path / "out")
    write, named = NEWER[case]
    write(out)
    _refused_by_every_reader(capsys, monkeypatch, out, tmp_path, *named, f"tube-miner reads v{SCHEMA_VERSION}")


def test_older_rows_are_refused_with_the_command_that_replaces_them(base_catalogue, tmp_path, capsys):
    """v1 rows (before unclassified tubes) cannot be migrated: the readers say how to mine them again;
    ``--new-run`` does it (a submission reads them as before)."""
    out = copy_of(base_catalogue, tmp_path / "out")
    _set_rows(out, 1)
    before = catalogue_files(out)
    for reader in ("query", "export", "render", "status"):
        rc, o, e = cli(capsys, *_readers(out, tmp_path)[reader])
        line = clean_error(e)
        assert rc == 2 and "v1" in line and TUBES in line and f"--out {out} --new-run" in line, f"{reader}: {o + e}"
    assert catalogue_files(out) == before


def test_records_of_this_version_carry_it(base_catalogue):
    """Every JSON record is written with the version, so a later reader can tell it from a newer one."""
    out = base_catalogue[0]
    for rel in ("job.json", MARKER, f"manifest/{D}/{SEQ}-0000000-0000008.files.json"):
        assert json.loads((out / rel).read_text())["schema_version"] == SCHEMA_VERSION, rel
    assert set(pq.read_table(out / TUBES)["schema_version"].to_pylist()) == {SCHEMA_VERSION}


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_the_command_the_refusal_of_older_rows_names_mines_them_again(base_catalogue, tmp_path):
    from _jobs import mine, tables

    out = copy_of(base_catalogue, tmp_path / "out")
    _set_rows(out, 1)
    s = mine(out, mode="new")  # `mine submit … --new-run`
    assert s.ok == 2 and not s.failed, s.lines()
    assert tables(out) == base_catalogue[1]
    assert list((out / "_replaced").iterdir()), "the old catalogue is kept"
