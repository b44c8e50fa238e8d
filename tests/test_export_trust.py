"""`mine export` trusts only what the source has, and a failed export leaves nothing of its own
(issue 40): a tube frame the source's plan lacks is refused before DEST is touched; label times
are written as UTC text by every format; a failed export removes the folder it made."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from _catalog_data import SEQUENCE
from _jobs import SEQ, copy_of
from mining.catalog.integrity import digest
from mining.catalog.labels import read_labels
from mining.catalog.store import Store
from mining.cli import main
from mining.errors import InputError
from mining.export.registry import FORMATS

MOVED = 999_999  # the frame the tampered row is moved to: no source has it


def _selected(out: Path) -> str:
    """The first selected tube of a catalogue, by id."""
    files = sorted((out / "catalog" / "tubes").rglob("*.parquet"))
    tubes = pa.concat_tables([pq.read_table(f, columns=["tube_id", "selected"]) for f in files]).to_pylist()
    return sorted(t["tube_id"] for t in tubes if t["selected"])[0]


def _tamper(out: Path, tube: str, reseal: bool = True) -> Path:
    """Move the first ``tube_frames`` row of ``tube`` to frame MOVED, as the audit did; with
    ``reseal`` the sequence marker records the edited file's new size and sha256, so the
    catalogue's integrity checks pass (a catalogue consistent with itself, not with its source).
    The edited file."""
    (path,) = [f for f in sorted((out / "catalog" / "tube_frames").rglob("*.parquet"))
               if tube in pq.read_table(f, columns=["tube_id"]).column("tube_id").to_pylist()]
    table = pq.read_table(path)
    rows = table.to_pylist()
    k = next(i for i, r in enumerate(rows) if r["tube_id"] == tube)
    rows[k]["frame"] = MOVED
    pq.write_table(pa.Table.from_pylist(rows, schema=table.schema), path, compression="zstd")
    if reseal:
        store = Store(out)
        rel = str(path.relative_to(out))
        for marker in (out / "catalog" / "_sequences").rglob("*.json"):
            rec = json.loads(marker.read_text())
            if rel in rec.get("files", {}):
                rec["files"][rel] = digest(store, rel)
                marker.write_text(json.dumps(rec, indent=1))
                break
        else:
            pytest.fail(f"no marker records {rel}")
    return path


def _export(out: Path, fmt: str, dest: Path, where: str, *extra: str) -> int:
    return main(["export", str(dest), "--out", str(out), "--where", where, "--format", fmt, *extra])


def _files(dest: Path) -> dict[str, bytes]:
    return {str(p.relative_to(dest)): p.read_bytes() for p in sorted(dest.rglob("*")) if p.is_file()}


# ── case 4: a vouched frame the source lacks ──────────────────────────────────────────────


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_every_format_refuses_a_vouched_frame_the_source_lacks(base_catalogue, tmp_path, capsys, fmt):
    """The old code wrote kitti-mots, youtube-vis, tao, burst and fiftyone with exit 0 (youtube-vis
    and tao inventing a frame 999999.jpg); crops refused naming an empty file."""
    out = copy_of(base_catalogue, tmp_path / "c")
    tube = _selected(out)
    edited = _tamper(out, tube)
    dest = tmp_path / "dest"
    capsys.readouterr()
    assert _export(out, fmt, dest, f"tube_id = '{tube}'") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("mine export: "), err
    line = err[0]
    assert f"file {edited}" in line and f"frame {MOVED}" in line and tube in line and SEQ in line, line
    assert "Traceback" not in line
    assert not dest.exists(), "DEST was made though the export was refused"


def test_a_refused_export_leaves_an_earlier_one_as_it_was(base_catalogue, tmp_path, capsys):
    out = copy_of(base_catalogue, tmp_path / "c")
    tube = _selected(out)
    dest = tmp_path / "dest"
    assert _export(out, "youtube-vis", dest, "selected") == 0
    before = _files(dest)
    assert "instances.json" in before and ".mine-export.json" in before
    _tamper(out, tube)
    capsys.readouterr()
    assert _export(out, "youtube-vis", dest, "selected", "--overwrite") == 2
    err = capsys.readouterr().err
    assert f"frame {MOVED}" in err and tube in err, err
    assert _files(dest) == before, "the earlier export was changed by a refused one"


def _away(catalogue, cat: Path, moved_root: Path) -> None:
    """A copy of the KITTI catalogue at ``cat`` whose job.json names a source root that is not
    there (the catalogue copied to another machine)."""
    shutil.copytree(catalogue[0], cat)
    job = json.loads((cat / "job.json").read_text())
    job["config"]["source"]["root"] = str(moved_root)
    (cat / "job.json").write_text(json.dumps(job))


def test_a_catalogue_away_from_its_source_is_checked_against_its_frames_table(catalogue, tmp_path, capsys):
    """Where the recorded source root is not there, the catalogue's own frames table is the plan:
    an export that needs no image still writes, and a tube frame that table lacks is refused."""
    cat = tmp_path / "cat"
    _away(catalogue, cat, tmp_path / "not-here")
    tube = _selected(cat)
    assert _export(cat, "youtube-vis", tmp_path / "ok", "selected") == 0
    edited = _tamper(cat, tube, reseal=False)  # no job marker: the catalogue is served as listed
    capsys.readouterr()
    dest = tmp_path / "dest"
    assert _export(cat, "youtube-vis", dest, "selected") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"file {edited}" in err[0] and f"frame {MOVED}" in err[0], err
    assert tube in err[0] and SEQUENCE in err[0] and "frames table" in err[0], err
    assert not dest.exists()


# ── case 6: labelled tubes, and a failed export's folder ──────────────────────────────────


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_every_format_exports_a_labelled_tube_with_its_label_and_time(base_catalogue, tmp_path, capsys, fmt):
    """The README's workflow, label then export: crops crashed on the label's time (a datetime
    json cannot write) and left an empty folder."""
    out = copy_of(base_catalogue, tmp_path / "c")
    tube = _selected(out)
    one = f"tube_id = '{tube}'"
    assert main(["label", "--out", str(out), "--where", one, "--verdict", "object"]) == 0
    assert main(["label", "--out", str(out), "--where", one, "--tag", "traffic cone"]) == 0
    last = max(read_labels(Store(out)).column("at").to_pylist())  # naive UTC, as LABEL_SCHEMA keeps it
    when = last.strftime("%Y-%m-%dT%H:%M:%S.%fZ")
    dest = tmp_path / "dest"
    capsys.readouterr()
    assert _export(out, fmt, dest, one) == 0, capsys.readouterr().err
    sidecar = json.loads((dest / "tube_labels.json").read_text())
    assert [(t["tube_id"], t["verdict"], t["tags"], t["labelled_at"]) for t in sidecar["tubes"]] == [
        (tube, "object", ["traffic cone"], when)]
    if fmt == "crops":  # the index carries every tubes column, the labels among them
        (row,) = json.loads((dest / "index.json").read_text())
        assert (row["tube_id"], row["verdict"], row["tags"], row["labelled_at"]) == (
            tube, "object", ["traffic cone"], when)
        assert pq.read_table(dest / "index.parquet").column("labelled_at").to_pylist() == [last]


@pytest.mark.parametrize("fmt", ["crops", "youtube-vis"])
def test_a_failed_export_leaves_no_folder(catalogue, tmp_path, capsys, fmt):
    """A writer that fails (here: the source's frames are not reachable) removes the DEST folder it
    made; a folder that was there before stays, empty, as it was."""
    cat = tmp_path / "cat"
    _away(catalogue, cat, tmp_path / "not-here")
    extra = ("--images",) if fmt == "youtube-vis" else ()
    dest = tmp_path / "a" / "dest"
    capsys.readouterr()
    assert _export(cat, fmt, dest, "selected", *extra) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not-here" in err[0], err
    assert not dest.exists() and not dest.parent.exists(), "the failed export left the folders it made"
    there = tmp_path / "there"
    there.mkdir()
    assert _export(cat, fmt, there, "selected", *extra) == 2
    assert there.is_dir() and not list(there.iterdir())


def test_an_empty_path_names_no_file():
    """A source without a root (the synthetic one) gave ``file , frame 999999: …``."""
    assert str(InputError("not in the source", "", 7)) == "frame 7: not in the source"
    assert str(InputError("not in the source", Path("a.parquet"), 7)) == "file a.parquet, frame 7: not in the source"
