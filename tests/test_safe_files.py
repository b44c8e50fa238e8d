"""Every write goes through one door (``mining/catalog/safe_files.py``, issue 19): it follows no
link, and a full disk is one clear line.

No write follows a link (scope item 1): what the tool writes under ``--out``, an
export's DEST or beside a rendered video stays there, whatever links are planted.

The failures of the adversarial run, each a test here that failed on the old code:

* ``OUT/.mine.lock`` a link to a file outside: ``mine submit`` "took over a stale lock of
  pid None" and emptied the file. Now refused, naming the link; the file keeps its bytes.
* ``mine export --overwrite`` with a planted ``index.json`` link overwrote the file outside;
  a planted ``JPEGImages`` link put the JPEGs outside DEST; an unrecorded link among the
  files was refused only after the previous export was deleted. Now any link in DEST is
  refused before anything is removed or written, and the exporters write into a private
  folder, so even a link planted while they run is never written through.
* ``mine render`` wrote its temporary video at the fixed name ``.NAME.partial.mp4``: a link
  planted there had a file outside overwritten with MP4 data. Now the video is written in a
  private folder under an unpredictable name. And an existing DEST video is replaced only
  with ``--overwrite``, as ``mine export`` does.

Then one test per writer: every way the store writes (``job.json``, a Parquet part, a
compacted sequence, a removal, ``--new-run``'s move), the lock's ``O_EXCL`` fallback, every
export format and the export record, each against a link at its file or folder.
Real commands (``mine export``, ``mine render``, ``mine submit``), real files.

A full disk is one clear line, and nothing already written is lost (the disk-full case).

The adversarial run left 8 KB free on the disk of ``--out``: ``mine submit`` died with a raw
traceback (``OSError: [Errno 28]`` writing ``job.json``), exit status 1. Now every write
under ``--out`` that fails raises ``safe_files.WriteError``: ``mine: error: file
OUT/job.json: cannot be written: no space left on device (free some space and run the
command again)``, exit status 2; the temporary file is removed and the file it would have
replaced (an earlier job.json, a part, a compacted file) is untouched.

The disk is a real small tmpfs mounted for the test (root only; elsewhere those tests skip,
saying so). The same path is exercised without root by a file-size limit
(``RLIMIT_FSIZE``), under which a write fails with EFBIG ("file too large") instead.
"""

from __future__ import annotations

import importlib
import json
import os
import resource
import shutil
import subprocess
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from _catalog_data import SEQUENCE
from mining.catalog import safe_files
from mining.catalog.layout import part_path
from mining.catalog.lock import OutputLock
from mining.catalog import query as query_mod
from mining.catalog.safe_files import LinkError, WriteError
from mining.catalog.schema import SCHEMAS
from mining.catalog.store import Store, write_sequence
from mining.cli import main
from mining.errors import InputError
from mining.export import render as render_mod
from mining.export.dest import RECORD, STAGING_PREFIX
from mining.export import registry
from mining.names import tube_folder
from _jobs import CLI_SMALL, SYNTHETIC, catalogue_files, copy_of, mine, tables
from _run import cli, clean_error, command_parsers, env, mine_cmd, valued_options
from conftest import REPO

SECRET = "line one\nline two\n"  # the outside file a planted link points at: it must keep these bytes
TINY = [*SYNTHETIC, "--workers", "1", "--no-progress"]


def _outside(tmp_path: Path) -> Path:
    """A file outside every folder the tool is pointed at (two lines, as in the adversarial run)."""
    f = tmp_path / "elsewhere" / "precious.txt"
    f.parent.mkdir(parents=True, exist_ok=True)
    f.write_text(SECRET)
    return f


def _outside_dir(tmp_path: Path) -> Path:
    d = tmp_path / "elsewhere-dir"
    d.mkdir()
    return d


def _tree(folder: Path) -> dict[str, bytes | str]:
    """Every entry under ``folder``: a file's bytes, a link's target (never followed)."""
    out: dict[str, bytes | str] = {}
    for p in sorted(folder.rglob("*")):
        rel = str(p.relative_to(folder))
        if p.is_symlink():
            out[rel] = "-> " + os.readlink(p)
        elif p.is_file():
            out[rel] = p.read_bytes()
    return out


# -- the lock ---------------------------------------------------------------------------


def test_a_lock_file_that_is_a_link_is_refused_and_what_it_points_to_is_kept(tmp_path, capsys):
    out, secret = tmp_path / "out", _outside(tmp_path)
    out.mkdir()
    (out / ".mine.lock").symlink_to(secret)
    with pytest.raises(LinkError, match=r"\.mine\.lock: is a link \(to .*precious\.txt\)"):
        OutputLock(Store(out)).acquire()
    assert secret.read_text() == SECRET
    assert "taking over" not in capsys.readouterr().err


def test_a_lock_file_of_junk_is_taken_over_saying_what_it_held_not_pid_none(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / ".mine.lock").write_text("line one\n")
    lock = OutputLock(Store(out)).acquire()
    lock.release()
    err = capsys.readouterr().err
    assert "taking over a stale lock of an unknown holder (the lock file held 'line one\\n')" in err, err
    assert "pid None" not in err


def test_a_lock_file_with_a_second_name_elsewhere_is_refused(tmp_path):
    """A hard link makes the lock file another file too: writing the holder would change it."""
    out, secret = tmp_path / "out", _outside(tmp_path)
    out.mkdir()
    os.link(secret, out / ".mine.lock")
    with pytest.raises(Exception, match="2 names"):
        OutputLock(Store(out)).acquire()
    assert secret.read_text() == SECRET


def test_the_exclusive_file_fallback_never_writes_through_a_link(tmp_path):
    import time

    out, secret = tmp_path / "out", _outside(tmp_path)
    out.mkdir()
    (out / ".mine.lock.excl").symlink_to(secret)
    with pytest.raises(LinkError, match="excl: is a link"):
        OutputLock(Store(out))._acquire_excl(time.monotonic())
    assert secret.read_text() == SECRET


@pytest.mark.slow  # a `mine submit` process (refused before Ray starts)
def test_mine_submit_refuses_a_lock_link_and_keeps_its_target(tmp_path):
    out, secret = tmp_path / "out", _outside(tmp_path)
    out.mkdir()
    (out / ".mine.lock").symlink_to(secret)
    done = subprocess.run(mine_cmd("submit", *TINY, "--out", str(out)), cwd=REPO, capture_output=True, text=True,
                          timeout=300, env=env())
    assert done.returncode == 2, done.stdout + done.stderr
    assert "is a link" in done.stderr and "Traceback" not in done.stderr and "taking over" not in done.stderr
    assert secret.read_text() == SECRET
    assert not (out / "job.json").exists()


# -- the store: one test per writer ------------------------------------------------------


def _table() -> pa.Table:
    return pa.table({"x": [1, 2, 3]})


def test_store_writes_replace_a_link_at_the_file_name_never_its_target(tmp_path):
    """job.json (write_bytes), a window's part (write_table): a link at the name is replaced
    by the file; the file it pointed to keeps its bytes."""
    out, secret = tmp_path / "out", _outside(tmp_path)
    store = Store(out)
    part = part_path("tubes", "synthetic", "0000", "0000-0000000-0000008")
    for rel in ("job.json", part):
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).symlink_to(secret)
    store.write_bytes("job.json", b'{"a": 1}')
    store.write_table(part, _table())
    assert secret.read_text() == SECRET
    assert not (out / "job.json").is_symlink() and (out / "job.json").read_bytes() == b'{"a": 1}'
    assert not (out / part).is_symlink() and store.read_table(part).equals(_table())


@pytest.mark.parametrize("folder", ["catalog", "manifest", "_parts", "_cache", "_running", "catalog/tubes"])
def test_store_refuses_to_write_through_a_folder_link(tmp_path, folder):
    """A link in place of a folder under --out (planted, or an old habit of linking _cache
    elsewhere) is refused, naming it; nothing lands where it points."""
    out, elsewhere = tmp_path / "out", _outside_dir(tmp_path)
    (out / folder).parent.mkdir(parents=True, exist_ok=True)
    (out / folder).symlink_to(elsewhere, target_is_directory=True)
    store = Store(out)
    with pytest.raises(LinkError, match=f"{folder}: is a link"):
        store.write_bytes(f"{folder}/dataset=d/x.json", b"{}")
    with pytest.raises(LinkError, match=f"{folder}: is a link"):
        store.write_table(f"{folder}/dataset=d/x.parquet", _table())
    assert list(elsewhere.iterdir()) == []


def test_compaction_and_removal_never_follow_a_link(tmp_path):
    """write_sequence over a folder link is refused; remove() unlinks a link, not its target."""
    out, secret, elsewhere = tmp_path / "out", _outside(tmp_path), _outside_dir(tmp_path)
    store = Store(out)
    folder = out / "catalog" / "frames" / "d" / "s"
    folder.parent.mkdir(parents=True)
    folder.symlink_to(elsewhere, target_is_directory=True)
    with pytest.raises(LinkError, match="d/s: is a link"):
        write_sequence(store, "frames", "d", "s", SCHEMAS["frames"].empty_table())
    assert list(elsewhere.iterdir()) == []
    (out / "job.json").symlink_to(secret)
    store.remove("job.json")
    assert not os.path.lexists(out / "job.json") and secret.read_text() == SECRET


def test_a_temporary_name_taken_by_a_link_is_never_opened(tmp_path, monkeypatch):
    """Temporary names are created with O_EXCL | O_NOFOLLOW: a link planted at the very name
    drawn (here forced) is skipped for another name."""
    out, secret = tmp_path / "out", _outside(tmp_path)
    out.mkdir()
    draws = iter(["aaaaaaaaaaaa", "bbbbbbbbbbbb"])
    monkeypatch.setattr(safe_files.secrets, "token_hex", lambda n: next(draws))
    (out / ".job.json.tmp-aaaaaaaaaaaa").symlink_to(secret)
    Store(out).write_bytes("job.json", b"{}")
    assert secret.read_text() == SECRET and (out / "job.json").read_bytes() == b"{}"


def test_a_store_on_another_filesystem_still_writes_through_pyarrow(tmp_path):
    """Object stores (``s3://``…) have no links and no rename: there the store keeps writing
    through pyarrow. Simulated on a ``file://`` store marked non-local."""
    store = Store(f"file://{tmp_path / 'out'}")
    store.local = False
    store.write_bytes("job.json", b"{}")
    store.write_table("manifest/x.parquet", _table())
    store.make_dir("_replaced/run")
    store.move("manifest", "_replaced/run/manifest")
    assert store.read_bytes("job.json") == b"{}" and store.read_table("_replaced/run/manifest/x.parquet").equals(_table())
    store.remove("job.json")
    assert not store.exists("job.json")
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["_replaced"], "no temporary file left"


# -- mine export -------------------------------------------------------------------------


def _export(out: Path, fmt: str, dest: Path, *extra: str) -> int:
    return main(["export", "--out", str(out), "--format", fmt, *extra, str(dest)])


def _replace_writer(monkeypatch, fmt: str, writer) -> None:
    """Make ``writer`` the function the registry loads for ``fmt`` (for this test only)."""
    f = registry.FORMATS[fmt]
    monkeypatch.setattr(importlib.import_module(f"mining.export.{f.module}"), f.writer, writer)


def test_export_overwrite_refuses_a_planted_index_json_link_before_removing_anything(catalogue, tmp_path, capsys):
    out, _ = catalogue
    dest, secret = tmp_path / "dest", _outside(tmp_path)
    assert _export(out, "kitti", dest) == 0
    before = _tree(dest)
    (dest / "index.json").symlink_to(secret)
    assert _export(out, "crops", dest, "--overwrite") == 2
    err = capsys.readouterr().err
    assert "index.json → " in err and "link" in err and "nothing was removed" in err
    assert secret.read_text() == SECRET
    assert _tree(dest) == before | {"index.json": "-> " + str(secret)}, "the previous export is kept as it was"


def test_export_images_never_follow_a_planted_jpegimages_link(catalogue, tmp_path, capsys):
    out, _ = catalogue
    dest, elsewhere = tmp_path / "dest", _outside_dir(tmp_path)
    assert _export(out, "youtube-vis", dest) == 0
    before = _tree(dest)
    (dest / "JPEGImages").symlink_to(elsewhere, target_is_directory=True)
    assert _export(out, "youtube-vis", dest, "--images", "--overwrite") == 2
    assert "JPEGImages → " in capsys.readouterr().err
    assert list(elsewhere.iterdir()) == [], "no JPEG outside DEST"
    assert _tree(dest) == before | {"JPEGImages": "-> " + str(elsewhere)}


@pytest.mark.parametrize("where", ["at a name the new export writes", "inside a recorded folder"])
def test_an_unrecorded_link_among_the_files_is_refused_before_the_previous_export_is_removed(catalogue, tmp_path,
                                                                                             capsys, where):
    """The old code refused the first (the crop folder resolved outside DEST) only after it
    had deleted the previous export; the second it did not notice."""
    out, tables = catalogue
    dest, elsewhere = tmp_path / "dest", _outside_dir(tmp_path)
    first, second = [t["tube_id"] for t in tables["tubes"].to_pylist() if t["selected"]][:2]
    assert _export(out, "crops", dest, "--where", f"tube_id = '{first}'") == 0
    if where == "inside a recorded folder":
        link = dest / tube_folder(first) / "more"
    else:
        link = dest / tube_folder(second)
    link.symlink_to(elsewhere, target_is_directory=True)
    before = _tree(dest)
    assert _export(out, "crops", dest, "--overwrite") == 2
    assert f"{link.relative_to(dest)} → " in capsys.readouterr().err
    assert _tree(dest) == before and list(elsewhere.iterdir()) == []


FORMATS = [("kitti", ()), ("kitti-mots", ()), ("crops", ()), ("youtube-vis", ("--images",)), ("tao", ("--images",)),
           ("burst", ("--images",)),
           ("fiftyone", ("--images",)), ("rerun", ())]


@pytest.mark.parametrize("fmt,extra", FORMATS, ids=[f for f, _ in FORMATS])
def test_every_export_writer_ignores_links_planted_while_it_runs(catalogue, tmp_path, monkeypatch, capsys, fmt, extra):
    """Links planted in DEST at every name the exporter writes, after DEST was checked (a
    race): the exporter wrote into its private folder, so nothing reaches the links'
    targets; the new entries would land on names DEST holds unrecorded, so the export is
    refused and the earlier export (KITTI txt, a different name) stays."""
    out, _ = catalogue
    dest, secret, elsewhere = tmp_path / "dest", _outside(tmp_path), _outside_dir(tmp_path)
    earlier = "crops" if fmt in ("kitti", "kitti-mots") else "kitti"  # an earlier export of other names
    assert _export(out, earlier, dest) == 0
    before = _tree(dest)
    real = registry.FORMATS[fmt].load()
    planted: list[str] = []

    def racing(tubes, frames, job, folder, **kw):
        n = real(tubes, frames, job, folder, **kw)
        for name in os.listdir(folder):
            if not os.path.lexists(dest / name):
                target = elsewhere if (folder / name).is_dir() else secret
                (dest / name).symlink_to(target, target_is_directory=target.is_dir())
                planted.append(name)
        return n

    _replace_writer(monkeypatch, fmt, racing)
    assert _export(out, fmt, dest, "--overwrite", *extra) == 2
    assert planted, "the exporter wrote nothing to plant links at"
    assert "which DEST holds and no earlier export recorded" in capsys.readouterr().err
    assert secret.read_text() == SECRET and list(elsewhere.iterdir()) == []
    assert _tree(dest) == before | {n: "-> " + str(elsewhere if (dest / n).is_dir() else secret) for n in planted}
    assert not [p for p in dest.iterdir() if p.name.startswith(STAGING_PREFIX)], "no partial folder left"


def test_the_export_record_replaces_a_link_planted_at_its_name(catalogue, tmp_path, monkeypatch):
    out, _ = catalogue
    dest, secret = tmp_path / "dest", _outside(tmp_path)
    real = registry.FORMATS["kitti"].load()

    def racing(tubes, frames, job, folder, **kw):
        (dest / RECORD).symlink_to(secret)
        return real(tubes, frames, job, folder, **kw)

    _replace_writer(monkeypatch, "kitti", racing)
    assert _export(out, "kitti", dest) == 0
    assert secret.read_text() == SECRET
    assert not (dest / RECORD).is_symlink()
    assert json.loads((dest / RECORD).read_text())["written"] == [f"{SEQUENCE}.ids.json", f"{SEQUENCE}.txt", "tube_labels.json"]


def test_a_failed_export_keeps_the_previous_one(catalogue, tmp_path, monkeypatch, capsys):
    """The old export is removed only once the new one is complete: an exporter that fails
    half-way (here: a full disk) leaves DEST as it was, and says why in one line."""
    import errno

    out, _ = catalogue
    dest = tmp_path / "dest"
    assert _export(out, "crops", dest) == 0
    before = _tree(dest)

    def full(tubes, frames, job, folder, **kw):
        (folder / "index.json").write_text("half")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(folder / "index.parquet"))

    _replace_writer(monkeypatch, "crops", full)
    assert _export(out, "crops", dest, "--overwrite") == 2
    err = capsys.readouterr().err.strip()
    assert "index.parquet: cannot be written: no space left on device" in err and len(err.splitlines()) == 1
    assert _tree(dest) == before


# -- mine render -------------------------------------------------------------------------


def _render(out: Path, dest: Path, *extra: str) -> int:
    return main(["render", "--out", str(out), "--sequence", SEQUENCE, "--frames", "0:2", *extra, str(dest)])


def test_render_never_writes_through_a_link_at_the_old_temporary_name(catalogue, tmp_path):
    out, _ = catalogue
    dest, secret = tmp_path / "v.mp4", _outside(tmp_path)
    (tmp_path / ".v.partial.mp4").symlink_to(secret)
    assert _render(out, dest) == 0
    assert secret.read_text() == SECRET
    assert dest.stat().st_size > 0 and not dest.is_symlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == [".v.partial.mp4", "elsewhere", "v.mp4"], "no partial left"


def test_render_writes_its_video_only_in_a_private_folder(catalogue, tmp_path, monkeypatch):
    """The encoder opens its file by path: that path is inside a folder made for this render
    alone (mode 0700, an unpredictable name beside DEST), removed afterwards."""
    out, _ = catalogue
    dest = tmp_path / "v.webm"
    seen = []
    real = render_mod.open_video

    def spy(path, fps, size):
        seen.append((path, oct(path.parent.stat().st_mode & 0o777), sorted(os.listdir(path.parent))))
        return real(path, fps, size)

    monkeypatch.setattr(render_mod, "open_video", spy)
    assert _render(out, dest) == 0
    (path, mode, listing), = seen
    assert path.name == "v.webm" and path.parent.parent == tmp_path and path.parent.name.startswith(".v.webm.partial-")
    assert mode == "0o700" and listing == []
    assert not path.parent.exists()


def test_render_replaces_an_existing_video_only_with_overwrite(catalogue, tmp_path, capsys):
    out, _ = catalogue
    dest = tmp_path / "v.webm"
    dest.write_bytes(b"an earlier video")
    assert _render(out, dest) == 2
    assert "--overwrite" in capsys.readouterr().err and dest.read_bytes() == b"an earlier video"
    assert _render(out, dest, "--overwrite") == 0
    assert dest.read_bytes()[:4] == b"\x1a\x45\xdf\xa3"  # a WebM (EBML) file now


def test_render_refuses_a_link_at_dest_even_with_overwrite(catalogue, tmp_path, capsys):
    out, _ = catalogue
    dest, secret = tmp_path / "v.mp4", _outside(tmp_path)
    dest.symlink_to(secret)
    assert _render(out, dest, "--overwrite") == 2
    assert "is a link" in capsys.readouterr().err
    assert secret.read_text() == SECRET and dest.is_symlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["elsewhere", "v.mp4"]


# -- one file where the user named it: --output, every --json, a bench's pictures -----------------
#
# The adversarial run (issue 28, case 1): `mine query … --output F` and `mine eval recall …
# --json F` wrote through a link planted at F (the file it pointed to was overwritten with
# Parquet / JSON), and `--output` replaced an existing file without --overwrite, where export
# and render refuse. Now every single file a command writes keeps one rule
# (safe_files.write_file, checked up front by check_output_file): a temporary name in the
# same folder and a rename, a link at the name refused, an existing file replaced only with
# --overwrite and only when it is a plain file.


def _output_file_options() -> list[tuple[str, str]]:
    """(command, option) of every option naming a file a command writes (walked from the parser)."""
    from mining.checks import PathType

    return [(command, a.option_strings[-1] if a.option_strings else "DEST")
            for command, parser in command_parsers() for a in valued_options(parser)
            if isinstance(a.type, PathType) and a.type.role == "output-file"]


OUTPUT_FILE_OPTIONS = _output_file_options()


def _with_output(command: str, option: str, path: Path) -> list[str]:
    """A command line of ``command`` writing its ``option`` file at ``path`` (required options filled)."""
    required = {"query": ["SELECT 1 AS x"], "render": ["--sequence", SEQUENCE]}.get(command, [])
    return [*command.split(), *required, *([option] if option != "DEST" else []), str(path)]


def test_the_output_file_options_include_query_output_and_every_json():
    found = set(OUTPUT_FILE_OPTIONS)
    assert {("query", "--output"), ("eval recall", "--json"), ("eval synthetic", "--json"), ("render", "DEST"),
            ("bench calibrate", "--json"), ("bench pipeline", "--json")} <= found
    for command, parser in command_parsers():  # every command that writes a file offers --overwrite
        if any(c == command for c, _ in found):
            assert any("--overwrite" in a.option_strings for a in parser._actions), command


@pytest.mark.parametrize("command, option", OUTPUT_FILE_OPTIONS, ids=[f"{c} {o}" for c, o in OUTPUT_FILE_OPTIONS])
def test_every_output_file_refuses_a_link_at_its_name_before_any_work(command, option, tmp_path, capsys,
                                                                       monkeypatch):
    monkeypatch.chdir(tmp_path)
    secret = _outside(tmp_path)
    dest = tmp_path / "result.mp4"
    dest.symlink_to(secret)
    for extra in ([], ["--overwrite"]):  # a link is refused whatever the flag
        rc, out, err = cli(capsys, *_with_output(command, option, dest), *extra)
        assert rc == 2 and "is a link" in clean_error(err) and not out, (rc, out, err)
        assert secret.read_text() == SECRET and dest.is_symlink()


@pytest.mark.parametrize("command, option", OUTPUT_FILE_OPTIONS, ids=[f"{c} {o}" for c, o in OUTPUT_FILE_OPTIONS])
def test_every_output_file_refuses_an_existing_file_without_overwrite_before_any_work(command, option, tmp_path,
                                                                                      capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    dest = tmp_path / "result.mp4"
    dest.write_text("an earlier result\n")
    rc, out, err = cli(capsys, *_with_output(command, option, dest))
    assert rc == 2 and "--overwrite" in clean_error(err) and not out, (rc, out, err)
    assert dest.read_text() == "an earlier result\n"


def _query(out: Path, dest: Path, fmt: str, *extra: str) -> int:
    return main(["query", "SELECT 1 AS x, 'a' AS y", "--out", str(out), "--format", fmt, "--output", str(dest), *extra])


@pytest.mark.parametrize("fmt", ["parquet", "csv", "json", "table"])
def test_query_output_never_writes_through_a_link_planted_while_it_runs(catalogue, tmp_path, monkeypatch, capsys,
                                                                        fmt):
    """A link that appears at --output after the check (while the query runs) is refused at the write too."""
    out, _ = catalogue
    secret, dest = _outside(tmp_path), tmp_path / "result"
    real = query_mod.query_table

    def plant(*args, **kwargs):
        t = real(*args, **kwargs)
        dest.symlink_to(secret)
        return t

    monkeypatch.setattr(query_mod, "query_table", plant)
    assert _query(out, dest, fmt, "--overwrite") == 2
    assert "is a link" in clean_error(capsys.readouterr().err)
    assert secret.read_text() == SECRET and dest.is_symlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["elsewhere", "result"], "no temporary file left"


def test_query_output_replaces_an_existing_file_only_with_overwrite(catalogue, tmp_path, capsys):
    out, _ = catalogue
    dest = tmp_path / "r.csv"
    dest.write_text("earlier\n")
    assert _query(out, dest, "csv") == 2
    assert "--overwrite" in clean_error(capsys.readouterr().err) and dest.read_text() == "earlier\n"
    assert _query(out, dest, "csv", "--overwrite") == 0
    assert dest.read_text() == "\"x\",\"y\"\n1,\"a\"\n"
    assert _query(out, tmp_path / "new.parquet", "parquet") == 0  # a new name needs no flag
    assert pq.read_table(tmp_path / "new.parquet").to_pylist() == [{"x": 1, "y": "a"}]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new.parquet", "r.csv"], "no temporary file left"


def test_query_output_refuses_a_folder_at_its_name_even_with_overwrite(catalogue, tmp_path, capsys):
    out, _ = catalogue
    (tmp_path / "r.json").mkdir()
    assert _query(out, tmp_path / "r.json", "json", "--overwrite") == 2
    assert "not a file" in clean_error(capsys.readouterr().err) and (tmp_path / "r.json").is_dir()


def test_a_failed_write_leaves_the_earlier_file_and_no_temporary_file(tmp_path):
    dest = tmp_path / "r.json"
    dest.write_text("earlier")

    def fail(f):
        f.write(b"half a fi")
        raise OSError(28, "No space left on device")

    with pytest.raises(WriteError, match="no space left on device"):
        safe_files.write_file(dest, fail, overwrite=True)
    assert dest.read_text() == "earlier" and sorted(os.listdir(tmp_path)) == ["r.json"]


def test_write_file_claims_a_new_name_atomically_and_replaces_only_a_plain_file(tmp_path):
    dest = tmp_path / "sub" / "r.json"
    safe_files.write_file(dest, b"one")  # its folder is made
    with pytest.raises(InputError, match="--overwrite"):
        safe_files.write_file(dest, b"two")
    safe_files.write_file(dest, b"three", overwrite=True)
    assert dest.read_bytes() == b"three" and sorted(os.listdir(dest.parent)) == ["r.json"]
    secret = _outside(tmp_path)
    link = tmp_path / "sub" / "l.json"
    link.symlink_to(secret)
    for overwrite in (False, True):
        with pytest.raises(LinkError):
            safe_files.write_file(link, b"x", overwrite)
    assert secret.read_text() == SECRET and sorted(os.listdir(dest.parent)) == ["l.json", "r.json"]


def test_no_bench_or_eval_module_writes_a_file_by_itself():
    """Every file a bench or an evaluation writes for the user goes through the destination rule
    (safe_files.write_file): no ``write_text``, ``write_bytes``, ``open(…, "w")``, ``imwrite``
    or ``savefig`` of their own, except into a private temporary folder (named here)."""
    import ast

    private = {("mining/eval/kitti_mot.py", "evaluate_first_frames"),  # a TemporaryDirectory for TrackEval
               ("mining/bench/pipeline.py", "measure_run"), ("mining/bench/pipeline.py", "_main"),  # its tmp folder
               ("mining/bench/stages.py", "measure"), ("mining/bench/stages.py", "_main"),  # likewise
               ("mining/bench/iou_tracker.py", "write_iou_tracks"),  # into the benches' TemporaryDirectory
               ("mining/bench/scale.py", "chart"),  # savefig into a BytesIO that write_file then writes
               ("mining/bench/memory.py", "reset_peaks")}  # "5" into /proc/<pid>/clear_refs: the kernel's peak reset, no file
    found = []
    for path in sorted([*(REPO / "mining" / "bench").rglob("*.py"), *(REPO / "mining" / "eval").rglob("*.py"),
                        REPO / "mining" / "catalog" / "query.py"]):
        rel = str(path.relative_to(REPO))
        tree = ast.parse(path.read_text())
        for fn in [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]:
            for node in ast.walk(fn):
                if not isinstance(node, ast.Call):
                    continue
                name = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
                mode = [a.value for a in node.args[1:2] if isinstance(a, ast.Constant)]
                writes = name in ("write_text", "write_bytes", "imwrite", "savefig", "write_kitti_tracking") or (
                    name == "open" and any("w" in str(m) or "a" in str(m) for m in mode))
                if writes and (rel, fn.name) not in private:
                    found.append(f"{rel}:{node.lineno} {fn.name}: {name}")
    assert not found, found


# -- a full disk -------------------------------------------------------------------------


@pytest.fixture
def small_disk(tmp_path):
    """A 4 MB tmpfs of this test's own."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    try:
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(mnt)], capture_output=True,
                              text=True, timeout=30)
        why = done.stderr.strip() if done.returncode else ""
    except FileNotFoundError:
        why = "no mount command"
    if why:
        pytest.skip(f"a small tmpfs cannot be mounted here ({why}; it needs root): the file-size-limit test covers "
                    "a failing write without it")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True, timeout=30)


def fill(disk: Path, free: int) -> Path:
    """Fill ``disk`` until the system says it is full, then free ``free`` bytes of it."""
    filler = disk / "filler"
    with open(filler, "wb", buffering=0) as f:
        try:
            while True:
                f.write(b"\0" * 65536)
        except OSError as e:
            assert e.errno == 28, e
    os.truncate(filler, filler.stat().st_size - free)
    return filler


@pytest.mark.slow  # a `mine submit` process (it fails before Ray starts)
def test_mine_submit_with_8_kb_free_says_no_space_left_in_one_line(small_disk):
    out = small_disk / "out"
    fill(small_disk, 8 * 1024)
    done = subprocess.run(mine_cmd("submit", *TINY, "--out", str(out)), cwd=REPO, env=env(), capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 2, done.stdout + done.stderr
    err = done.stderr.strip().splitlines()
    assert err == [f"mine: error: file {out}/job.json: cannot be written: no space left on device (free some space "
                   "and run the command again)"], done.stderr
    assert sorted(p.name for p in out.iterdir()) == [".mine.lock"], "no job.json, no temporary file left behind"


def test_a_full_disk_while_rewriting_job_json_keeps_the_old_one(base_catalogue, small_disk):
    """``--extend`` rewrites job.json: on a full disk it fails naming the file, and the
    catalogue (job.json included) is as it was, byte for byte."""
    out = copy_of(base_catalogue, small_disk / "out")
    before = catalogue_files(out)
    fill(small_disk, 8 * 1024)
    with pytest.raises(WriteError) as e:
        mine(out, (0, 24), mode="extend")
    assert str(e.value) == (f"file {out}/job.json: cannot be written: no space left on device (free some space and "
                            "run the command again)")
    assert catalogue_files(out) == before


@pytest.mark.slow  # mines (and fails) a window
def test_a_full_disk_while_writing_a_window_fails_naming_the_file_and_keeps_the_catalogue(base_catalogue, small_disk):
    """A window whose parts are gone is recomputed on resubmission; with 40 KB free its
    observation cache does not fit. The failure names the file and the reason, and the
    catalogue's tables and job.json are unchanged."""
    out = copy_of(base_catalogue, small_disk / "out")
    for table in ("tubes", "tube_frames", "frames"):
        (out / "_parts" / table / "dataset=synthetic" / "sequence=0000" / "0000-0000008-0000016.part").unlink()
    before_tables, job = tables(out), (out / "job.json").read_bytes()
    fill(small_disk, 40 * 1024)
    try:
        s = mine(out)
        said = "\n".join(s.lines())
        assert s.failed, said
    except WriteError as e:  # the driver's own write hit the full disk first
        said = str(e)
    assert "cannot be written: no space left on device" in said and f"file {out}/" in said, said
    assert "Traceback" not in said
    (small_disk / "filler").unlink()
    assert tables(out) == before_tables and (out / "job.json").read_bytes() == job


def _limit_file_size(limit: int):
    def preexec() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return preexec


@pytest.mark.slow  # a `mine submit` process (it fails before Ray starts)
def test_mine_submit_under_a_file_size_limit_says_file_too_large_in_one_line(tmp_path):
    """No root needed: RLIMIT_FSIZE of 8 KB, job.json (≈ 17 KB) does not fit (EFBIG; Python
    ignores SIGXFSZ, so the write returns the error)."""
    out = tmp_path / "out"
    done = subprocess.run(mine_cmd("submit", *TINY, "--out", str(out)), cwd=REPO, env=env(), capture_output=True,
                          text=True, timeout=300, preexec_fn=_limit_file_size(8192))
    assert done.returncode == 2, done.stdout + done.stderr
    err = done.stderr.strip().splitlines()
    assert err == [f"mine: error: file {out}/job.json: cannot be written: file too large (the file exceeds the size "
                   "limit of this process or filesystem)"], done.stderr
    assert sorted(p.name for p in out.iterdir()) == [".mine.lock"]


@pytest.mark.slow  # a `mine submit` process (it fails before Ray starts)
def test_an_existing_job_json_survives_a_failed_rewrite_under_a_file_size_limit(base_catalogue, tmp_path):
    out = copy_of(base_catalogue, tmp_path / "out")
    before = catalogue_files(out)
    done = subprocess.run(mine_cmd("submit", *CLI_SMALL, "--frames", "0:24", "--extend", "--out", str(out),
                                   "--workers", "1", "--no-progress"), cwd=REPO, env=env(),
                          capture_output=True, text=True, timeout=300, preexec_fn=_limit_file_size(8192))
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr.strip().splitlines() == [f"mine: error: file {out}/job.json: cannot be written: file too large "
                                                "(the file exceeds the size limit of this process or filesystem)"]
    assert catalogue_files(out) == before
    shutil.rmtree(out)
