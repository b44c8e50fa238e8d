"""``mine export`` never writes outside DEST (issue 11, item 2): a catalogue whose tube id is
``..`` made ``--format crops`` write into DEST's parent (``tube_folder`` replaced only
``/``). Now an unsafe tube id (``..``, ``a/../../x``) or sequence name read from the
catalogue is an error naming it, and nothing is written outside DEST.

The catalogue is the real KITTI 0005 one of ``tests/_catalog_data.py``, one tube renamed."""

from __future__ import annotations

import shutil
from pathlib import Path

import pyarrow as pa
import pytest

from _catalog_data import DATASET, SEQUENCE
from mining.catalog.schema import SCHEMAS
from mining.catalog.store import Store, write_sequence
from mining.export.dest import RECORD
from mining.export.run import run_export


def _with_tube_id(catalogue, tmp_path: Path, tube_id: str) -> Path:
    """A copy of the catalogue with its longest selected tube renamed ``tube_id``."""
    out, tables = catalogue
    tubes, tf = tables["tubes"].to_pylist(), tables["tube_frames"].to_pylist()
    victim = max((t for t in tubes if t["selected"]), key=lambda t: t["n_frames"])["tube_id"]
    cat = tmp_path / "cat"
    shutil.copytree(out, cat)
    store = Store(cat)
    rename = {victim: tube_id}
    write_sequence(store, "tubes", DATASET, SEQUENCE, pa.Table.from_pylist(
        [dict(t, tube_id=rename.get(t["tube_id"], t["tube_id"])) for t in tubes], schema=SCHEMAS["tubes"]))
    write_sequence(store, "tube_frames", DATASET, SEQUENCE, pa.Table.from_pylist(
        [dict(f, tube_id=rename.get(f["tube_id"], f["tube_id"])) for f in tf], schema=SCHEMAS["tube_frames"]))
    return cat


@pytest.mark.parametrize("tube_id", ["..", "a/../../x", f"{DATASET}/{SEQUENCE}/../../../escaped"])
def test_crops_of_an_unsafe_tube_id_stay_inside_dest(catalogue, tmp_path, capsys, tube_id):
    cat = _with_tube_id(catalogue, tmp_path, tube_id)
    work = tmp_path / "work"
    dest = work / "dest"
    work.mkdir()
    before = {p for p in tmp_path.rglob("*")}
    where = "tube_id = '" + tube_id.replace("'", "''") + "'"
    assert run_export(str(cat), where, "crops", str(dest)) == 2
    err = capsys.readouterr().err
    assert repr(tube_id) in err and "tube id" in err
    assert {p for p in tmp_path.rglob("*")} - before <= {dest}, "nothing but DEST itself is made"


def test_the_other_tubes_still_export_and_a_safe_id_keeps_its_folder(catalogue, tmp_path):
    cat = _with_tube_id(catalogue, tmp_path, f"{DATASET}/{SEQUENCE}/renamed.000")
    dest = tmp_path / "dest"
    assert run_export(str(cat), "tube_id LIKE '%renamed%'", "crops", str(dest)) == 0
    assert sorted(p.name for p in dest.iterdir()) == [RECORD, "index.json", "index.parquet",
                                                      f"{DATASET}_{SEQUENCE}_renamed.000"]


def test_kitti_export_of_an_unsafe_sequence_name(catalogue, tmp_path, capsys):
    """A hive folder ``sequence=..%2F..%2Fescaped`` reads back (DuckDB and pyarrow decode
    it) as the sequence ``../../escaped``, which the KITTI export made a file name of."""
    out, _ = catalogue
    cat = tmp_path / "cat"
    shutil.copytree(out, cat)
    for table in ("tubes", "tube_frames"):
        folder = cat / "catalog" / table / f"dataset={DATASET}"
        (folder / f"sequence={SEQUENCE}").rename(folder / "sequence=..%2F..%2Fescaped")
    dest = tmp_path / "work" / "dest"
    before = {p for p in tmp_path.rglob("*")}
    assert run_export(str(cat), "selected", "kitti", str(dest)) == 2
    assert "sequence name '../../escaped'" in capsys.readouterr().err
    assert {p for p in tmp_path.rglob("*")} - before <= {tmp_path / "work", dest}, "nothing written"
