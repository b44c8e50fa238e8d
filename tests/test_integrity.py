"""Damage is found and repaired (issue 11, item 5), and never served (issue 19, scope item 3).

The manifest records every output file's size and sha256. ``mine status`` names a
damaged or missing file and exits non-zero (sizes always; checksums with ``--verify``);
``mine query`` refuses the damaged table, naming the file, and answers the others; a
resubmission recomputes exactly what owns the file: a compacted catalogue file is stitched
again from its sequence's parts (no window runs), or, with the parts gone too, their
windows run again; a damaged part runs its window again. Every repair ends with the
catalogue of the undamaged job.

Integrity on the read path: every reader (``mine query``, ``export``, ``render``, ``view``:
all through ``views.connect``) reads only the compacted files a sequence's finished marker
vouches for, each checked by size and sha256 against the marker once per process. Each
failure below was reproduced on the code before: a flipped bit in a compacted file was
served as a changed value with exit 0; a crash during a sequence's first stitch served its
tubes without their frames; a sequence folder no marker records was served (every tube twice).

Real files, real DuckDB, ``LocalExecutor``: the small synthetic job of ``tests/_jobs.py``
(``base_catalogue``: mined once, copied).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from mining.catalog import integrity
from mining.catalog.views import connect
from _jobs import SEQ, copy_of, mine, tables
from _run import cli, cli_status

D = f"dataset=synthetic/sequence={SEQ}"  # the working folders (manifest, parts, markers)
C = f"synthetic/{SEQ}"  # the compacted tables' folders (schema v3)
TUBES = f"catalog/tubes/{C}/part-0.parquet"
TUBE_FRAMES = f"catalog/tube_frames/{C}/part-0.parquet"
FRAMES = f"catalog/frames/{C}/part-0.parquet"
W0, W1 = f"{SEQ}-0000000-0000008", f"{SEQ}-0000008-0000016"
MARKER = f"catalog/_sequences/{D}.json"


def _query(capsys, out: Path, sql: str) -> tuple[int, str, str]:
    return cli(capsys, "query", sql, "--out", str(out), "--format", "csv")


def _count(capsys, out: Path, table: str) -> tuple[int, str, str]:
    return _query(capsys, out, f"SELECT count(*) AS n FROM {table}")


def _flip_a_value(path: Path) -> None:
    """Flip one bit of ``path`` where the file still reads as Parquet but a value changes
    (the silent kind of damage: no decoder notices it)."""
    data = path.read_bytes()
    before = pq.read_table(path)
    for i in range(len(data) // 8, len(data) - 8):  # past the header, before the footer's magic
        flipped = bytearray(data)
        flipped[i] ^= 0x10
        path.write_bytes(bytes(flipped))
        try:
            after = pq.read_table(path)
        except Exception:  # noqa: BLE001 - a flip a decoder sees: not the case under test
            continue
        if not after.equals(before):
            return
    raise AssertionError(f"no single flipped bit of {path} changes a value and still reads")


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def test_a_deleted_compacted_file_is_named_and_re_stitched_from_its_parts(base_catalogue, tmp_path, capsys):
    out = copy_of(base_catalogue, tmp_path / "out")
    n_frames = len(base_catalogue[1]["frames"])
    (out / TUBES).unlink()

    rc, text = cli_status(capsys, out)
    assert rc != 0 and f"damaged  {TUBES}: missing (a resubmission stitches sequence {SEQ} again)" in text, text
    rc, o, e = _count(capsys, out, "tubes")
    assert rc == 2 and str(out / TUBES) in e and "missing" in e, o + e  # not "0 rows"
    rc, o, e = _count(capsys, out, "frames")
    assert rc == 0 and o.split()[1:] == [str(n_frames)], o + e

    s = mine(out)
    assert (s.ok, s.skipped, s.sequences_written) == (0, 2, 1), s.lines()  # no window ran: stitched again
    assert tables(out) == base_catalogue[1]
    assert cli_status(capsys, out)[0] == 0


def test_a_truncated_compacted_file_breaks_only_its_table(base_catalogue, tmp_path, capsys):
    out = copy_of(base_catalogue, tmp_path / "out")
    _truncate(out / TUBE_FRAMES)

    rc, text = cli_status(capsys, out)
    assert rc != 0 and f"damaged  {TUBE_FRAMES}: " in text and "bytes," in text and "recorded" in text, text
    rc, o, e = _count(capsys, out, "tube_frames")
    assert rc == 2 and str(out / TUBE_FRAMES) in e, o + e
    rc, o, e = cli(capsys, "query", "SELECT count(*) FROM tube_tracks", "--out", str(out))  # a view over it
    assert rc == 2 and str(out / TUBE_FRAMES) in e, o + e
    for table, n in (("tubes", len(base_catalogue[1]["tubes"])), ("frames", len(base_catalogue[1]["frames"])),
                     ("windows", 2), ("selected_tubes", None)):
        rc, o, e = _count(capsys, out, table)
        assert rc == 0, f"{table}: {o + e}"
        assert n is None or o.split()[1:] == [str(n)], o

    s = mine(out)
    assert (s.ok, s.skipped, s.sequences_written) == (0, 2, 1), s.lines()
    assert tables(out) == base_catalogue[1]


def test_status_verify_finds_a_file_damaged_in_place(base_catalogue, tmp_path, capsys):
    out = copy_of(base_catalogue, tmp_path / "out")
    path = out / FRAMES
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte: the size is as recorded
    path.write_bytes(bytes(data))

    rc, text = cli_status(capsys, out)
    # the catalogue's files (what queries read) are always checked by checksum (issue 19)
    assert rc != 0 and f"damaged  {FRAMES}: sha256 " in text and "integrity: 1 damaged" in text, text
    assert "(a resubmission with --verify stitches sequence" in text, text
    rc, text = cli_status(capsys, out, "--verify")
    assert rc != 0 and f"damaged  {FRAMES}: sha256 " in text and "integrity: 1 damaged" in text, text

    s = mine(out)  # sizes only: nothing seen, nothing done
    assert (s.ok, s.sequences_written) == (0, 0)
    s = mine(out, verify=True)
    assert (s.ok, s.skipped, s.sequences_written) == (0, 2, 1), s.lines()
    assert path.read_bytes() != bytes(data)
    assert tables(out) == base_catalogue[1]
    assert cli_status(capsys, out, "--verify")[0] == 0


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_a_damaged_part_runs_its_window_again(base_catalogue, tmp_path, capsys):
    out = copy_of(base_catalogue, tmp_path / "out")
    part = f"_parts/tube_frames/{D}/{W1}.part"
    _truncate(out / part)

    rc, text = cli_status(capsys, out)
    assert rc != 0 and f"damaged  {part}: " in text and f"runs window {W1} again" in text, text
    s = mine(out)
    assert (s.ok, s.skipped, s.sequences_written) == (1, 1, 1), s.lines()  # that window, then the stitch
    assert tables(out) == base_catalogue[1]
    assert cli_status(capsys, out, "--verify")[0] == 0


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_a_damaged_compacted_file_without_its_parts_runs_their_windows_again(base_catalogue, tmp_path, capsys):
    out = copy_of(base_catalogue, tmp_path / "out")
    _truncate(out / TUBES)
    for p in (out / "_parts").rglob("*.part"):
        p.unlink()

    rc, text = cli_status(capsys, out)
    assert rc != 0 and TUBES in text and f"runs window {W0} again" in text and f"runs window {W1} again" in text
    s = mine(out)
    assert (s.ok, s.skipped, s.sequences_written) == (2, 0, 1), s.lines()
    assert tables(out) == base_catalogue[1]


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_an_unreadable_manifest_row_is_named_and_its_window_runs_again(base_catalogue, tmp_path, capsys):
    out = copy_of(base_catalogue, tmp_path / "out")
    row = f"manifest/{D}/{W0}.parquet"
    (out / row).write_bytes(b"not parquet")

    rc, text = cli_status(capsys, out)
    assert rc != 0 and f"damaged  {row}: unreadable" in text, text
    rc, o, e = _count(capsys, out, "tubes")
    assert rc == 0, o + e
    s = mine(out)
    assert (s.ok, s.skipped) == (1, 1), s.lines()
    assert tables(out) == base_catalogue[1]
    assert cli_status(capsys, out)[0] == 0


def test_an_export_over_a_damaged_table_names_the_file_not_the_predicate(base_catalogue, tmp_path, capsys):
    out = copy_of(base_catalogue, tmp_path / "out")
    _truncate(out / TUBE_FRAMES)
    dest = tmp_path / "crops"
    rc, o, e = cli(capsys, "export", "--out", str(out), "--where", "selected", "--format", "youtube-vis", str(dest))
    assert rc == 2 and str(out / TUBE_FRAMES) in e and "predicate" not in e, o + e
    assert not dest.exists() or not any(dest.iterdir())
    rc, o, e = cli(capsys, "export", "--out", str(out), "--where", "no_such_column > 1", "--format", "youtube-vis",
                   str(dest))
    assert rc == 2 and "--where" in e and "no_such_column" in e, o + e


# -- the read path -----------------------------------------------------------------------


def test_a_flipped_bit_is_an_error_naming_the_file_never_a_value(base_catalogue, tmp_path, capsys):
    out = copy_of(base_catalogue, tmp_path / "out")
    n_frames = len(base_catalogue[1]["frames"])
    _flip_a_value(out / TUBES)
    assert (out / TUBES).stat().st_size == json.loads((out / MARKER).read_text())["files"][TUBES]["size"]

    for sql in ("SELECT * FROM tubes", "SELECT count(*) FROM selected_tubes", "SELECT * FROM tube_tracks"):
        rc, o, e = _query(capsys, out, sql)
        assert rc == 2 and str(out / TUBES) in e and "sha256" in e, f"{sql}: {o + e}"  # was rc 0, changed values
        assert len(e.strip().splitlines()) == 1 and o == "", e
    rc, o, e = _query(capsys, out, "SELECT count(*) AS n FROM frames")  # the other tables answer
    assert rc == 0 and o.split()[1:] == [str(n_frames)], o + e

    dest = tmp_path / "export"
    rc, o, e = cli(capsys, "export", "--out", str(out), "--where", "selected", "--format", "youtube-vis", str(dest))
    assert rc == 2 and str(out / TUBES) in e, o + e
    assert not dest.exists() or not any(dest.iterdir())



def test_plain_status_finds_a_flipped_bit_in_the_catalogues_files(base_catalogue, tmp_path, capsys):
    """Plain ``mine status`` said "0 damaged" over a flipped bit that changed a query's values
    (only --verify found it): the compacted files, what queries read, are checked by checksum."""
    out = copy_of(base_catalogue, tmp_path / "out")
    _flip_a_value(out / TUBES)
    rc, o, e = cli(capsys, "status", "--out", str(out))
    assert rc == 1, o + e
    assert f"damaged  {TUBES}: sha256" in o and "integrity: 1 damaged" in o, o

def test_a_half_published_first_stitch_is_not_served(base_catalogue, tmp_path, capsys):
    """A crash during a sequence's first stitch: its tubes file published, the rest and its
    marker not. The final views show nothing of it (they showed its tubes without frames);
    the provisional views show its finished windows."""
    out = copy_of(base_catalogue, tmp_path / "out")
    (out / MARKER).unlink()
    for table in ("tube_frames", "frames", "windows"):
        shutil.rmtree(out / "catalog" / table / C)
    assert (out / TUBES).is_file()

    for table in ("tubes", "selected_tubes", "tube_frames", "frames", "tube_tracks"):
        rc, o, e = _query(capsys, out, f"SELECT count(*) AS n FROM {table}")
        assert rc == 0 and o.split()[1:] == ["0"], f"{table}: {o + e}"
    rc, o, e = _query(capsys, out, "SELECT count(*) AS n FROM provisional_tubes WHERE provisional")
    assert rc == 0 and int(o.split()[1]) > 0, o + e


def test_a_sequence_folder_no_marker_records_is_not_served(base_catalogue, tmp_path, capsys):
    out = copy_of(base_catalogue, tmp_path / "out")
    n = {t: len(base_catalogue[1][t]) for t in ("tubes", "tube_frames", "frames")}
    for table in ("tubes", "tube_frames", "frames", "windows"):
        src = out / "catalog" / table / C
        shutil.copytree(src, src.with_name("0001"))  # a stray copy: no marker records it

    for table in n:
        rc, o, e = _query(capsys, out, f"SELECT count(*) AS n, count(DISTINCT sequence) AS s FROM {table}")
        assert rc == 0 and o.split()[1:] == [f"{n[table]},1"], f"{table}: {o + e}"  # was every row twice


def test_each_file_is_hashed_once_per_process_until_it_changes(base_catalogue, tmp_path, monkeypatch):
    out = copy_of(base_catalogue, tmp_path / "out")
    hashed = []
    real = integrity.digest
    monkeypatch.setattr(integrity, "digest", lambda store, rel: hashed.append(rel) or real(store, rel))
    recorded = json.loads((out / MARKER).read_text())["files"]

    connect(out).close()
    assert sorted(hashed) == sorted(recorded)  # every vouched file, once
    hashed.clear()
    con = connect(out)
    assert hashed == [] and con.sql("SELECT count(*) FROM tubes").fetchone()[0] == len(base_catalogue[1]["tubes"])
    con.close()

    _flip_a_value(out / TUBES)  # a new mtime: checked again, and found
    con = connect(out)
    assert hashed == [TUBES]
    with pytest.raises(Exception, match="sha256"):
        con.sql("SELECT count(*) FROM tubes").fetchall()
    con.close()


def test_the_viewer_refuses_a_damaged_table(base_catalogue, tmp_path):
    from mining.view.catalogue import CatalogueBrowser

    out = copy_of(base_catalogue, tmp_path / "out")
    _flip_a_value(out / TUBES)
    cat = CatalogueBrowser(out)
    with pytest.raises(Exception, match="sha256"):
        cat.con.sql("SELECT max(size[1]) FROM tubes").fetchall()


def test_temporary_files_a_kill_left_are_reported_by_status_and_swept_by_the_next_submit(base_catalogue, tmp_path,
                                                                                         capsys):
    """A whole-session kill during the first stitch leaves ``.part-0.parquet.tmp-<hex>`` (the name
    the safe write path stages under); before, nothing removed it and ``mine status`` did not
    mention it. Now status counts and names it without removing it, and the next submit removes
    exactly such files in the job's own folders, saying so in one line: not a name of another
    pattern, not a link (nor what it points to), nothing outside the job's folders."""
    out = copy_of(base_catalogue, tmp_path / "out")
    stray = out / f"catalog/tube_frames/{C}/.part-0.parquet.tmp-0123456789ab"
    stray.write_bytes((out / TUBE_FRAMES).read_bytes()[:100])
    cache_stray = out / "_cache" / ".x.npz.zst.tmp-abcdefabcdef"
    cache_stray.parent.mkdir(exist_ok=True)
    cache_stray.write_bytes(b"half")
    root_stray = out / ".job.json.tmp-00aa00aa00aa"
    root_stray.write_bytes(b"{")
    elsewhere = tmp_path / "elsewhere.txt"
    elsewhere.write_text("not the catalogue's\n")
    keep = [out / f"catalog/tube_frames/{C}/.part-0.parquet.tmp-notahexname",  # not the pattern
            out / f"catalog/tubes/{C}/notes.tmp-0123456789ab",  # no leading dot: not a staged name
            out / "_replaced" / ".part-0.parquet.tmp-0123456789ab"]  # not a folder the job writes
    for p in keep:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(b"keep")
    link = out / f"catalog/frames/{C}/.part-0.parquet.tmp-ffffffffffff"
    link.symlink_to(elsewhere)

    rc, text = cli_status(capsys, out)
    assert rc == 0, text  # readers skip them: not damage
    said = [ln for ln in text.splitlines() if ln.startswith("temporary files:")]
    assert len(said) == 1 and said[0].startswith("temporary files: 3 left by unfinished writes"), text
    assert str(root_stray) in said[0] or str(cache_stray) in said[0] or str(stray) in said[0], said
    assert stray.exists() and cache_stray.exists() and root_stray.exists(), "status removes nothing"

    s = mine(out)
    swept = [ln for ln in s.lines() if ln.startswith("swept")]
    assert len(swept) == 1 and swept[0].startswith("swept 3 temporary file(s) an interrupted run left: "), s.lines()
    assert sorted(s.swept) == sorted(str(p) for p in (stray, cache_stray, root_stray)), s.swept
    assert not stray.exists() and not cache_stray.exists() and not root_stray.exists()
    assert all(p.read_bytes() == b"keep" for p in keep)
    assert link.is_symlink() and elsewhere.read_text() == "not the catalogue's\n"
    assert tables(out) == base_catalogue[1]

    link.unlink()
    rc, text = cli_status(capsys, out)
    assert rc == 0 and "temporary files:" not in text, text
    assert not [ln for ln in mine(out).lines() if ln.startswith("swept")], "nothing left to sweep"


def test_file_functions_in_a_query_read_only_the_files_the_markers_vouch_for(base_catalogue, tmp_path, capsys):
    """``read_parquet('<out>/catalog/tubes/…/part-0.parquet')`` inside ``mine query`` read a bit-flipped
    file and returned a changed value (exit 0) where the named tables refused it. DuckDB's file
    functions may read a compacted file only as the tables do: when its sha256 checked out."""
    out = copy_of(base_catalogue, tmp_path / "out")
    n_tubes = len(base_catalogue[1]["tubes"])
    rc, o, e = _query(capsys, out, f"SELECT count(*) AS n FROM read_parquet('{out / TUBES}')")
    assert rc == 0 and o.split()[1:] == [str(n_tubes)], o + e  # vouched for (its sha256 checked): read

    _flip_a_value(out / TUBES)
    for sql in (f"SELECT max(score) FROM read_parquet('{out / TUBES}')", f"SELECT * FROM parquet_scan('{out / TUBES}')",
                f"SELECT * FROM '{out / TUBES}'", f"SELECT length(content) FROM read_blob('{out / TUBES}')",
                f"SELECT * FROM parquet_metadata('{out / TUBES}')"):
        rc, o, e = _query(capsys, out, sql)
        assert rc == 2 and o == "" and len(e.strip().splitlines()) == 1, f"{sql}: {o + e}"  # was rc 0, a changed value
        assert str(out / TUBES) in e and "damaged" in e and "sha256" in e, f"{sql}: {e}"
    rc, o, e = _query(capsys, out, "SELECT max(score) FROM tubes")  # the named table, as before
    assert rc == 2 and str(out / TUBES) in e and "sha256" in e, o + e

    # No other way in: a pattern, a folder no marker records, the job record, a file outside --out.
    stray = out / "catalog" / "tubes" / "synthetic" / "0001" / "part-0.parquet"
    stray.parent.mkdir(parents=True)
    shutil.copy(out / TUBES, stray)
    for path in (out / "catalog/tubes/*/*/*.parquet", stray, out / "job.json"):
        rc, o, e = _query(capsys, out, f"SELECT * FROM read_text('{path}')")
        assert rc == 2 and str(path) in e and "not a file this catalogue vouches for" in e, f"{path}: {o + e}"
    rc, o, e = _query(capsys, out, "SELECT * FROM read_text('/etc/hostname')")
    assert rc == 2 and "outside the catalogue" in e, o + e
    # The windows table and the provisional views read the manifest and the parts as listed: so may SQL.
    rc, o, e = _query(capsys, out, f"SELECT count(*) AS n FROM read_parquet('{out}/manifest/*/*/*.parquet')")
    assert rc == 0 and o.split()[1:] == ["2"], o + e


def _flip_a_column_name(path: Path) -> str:
    """Flip one bit of a column name in ``path``'s footer (a letter's case), so the file still
    reads but with a column its table does not have; the name it now has."""
    data = path.read_bytes()
    before = pq.ParquetFile(path).schema_arrow.names
    for name in before:
        start = 0
        while (i := data.find(name.encode(), start)) >= 0:
            start = i + 1
            flipped = bytearray(data)
            flipped[i] ^= 0x20
            path.write_bytes(bytes(flipped))
            try:
                after = pq.ParquetFile(path).schema_arrow.names
            except Exception:  # noqa: BLE001 - a flip the reader sees: not the case under test
                continue
            if after != before:
                return next(n for n in after if n not in before)
    raise AssertionError(f"no single flipped bit of {path} renames a column")


@pytest.mark.slow  # mines the catalogue again (over ~2.5 s)
@pytest.mark.parametrize("repair", ["verify", "new-run"])
def test_a_flipped_bit_in_a_column_name_is_damage_not_a_newer_version(base_catalogue, tmp_path, capsys, repair):
    """One flipped bit in a compacted file's column name was refused as "written by a newer
    version" by every command, `submit --verify` and `--new-run` included (its sha256 no longer
    matched its marker, which was never said): it is damage, named so, and repaired."""
    out = copy_of(base_catalogue, tmp_path / "out")
    renamed = _flip_a_column_name(out / TUBES)
    assert renamed

    rc, o, e = _count(capsys, out, "tubes")
    assert rc == 2 and str(out / TUBES) in e and "damaged" in e and "newer" not in e, o + e
    assert "does not match its marker" in e and "mine submit --verify" in e and len(e.strip().splitlines()) == 1, e
    rc, o, e = _count(capsys, out, "frames")  # the other tables answer
    assert rc == 0 and o.split()[1:] == [str(len(base_catalogue[1]["frames"]))], o + e
    rc, o, e = cli(capsys, "status", "--out", str(out))
    assert rc == 1 and f"damaged  {TUBES}: sha256" in o and "newer" not in o + e, o + e

    s = mine(out, verify=True) if repair == "verify" else mine(out, mode="new")
    assert not s.failed, s.lines()
    assert tables(out) == base_catalogue[1]
    rc, o, e = _count(capsys, out, "tubes")
    assert rc == 0 and o.split()[1:] == [str(len(base_catalogue[1]["tubes"]))], o + e
    assert cli_status(capsys, out, "--verify")[0] == 0
