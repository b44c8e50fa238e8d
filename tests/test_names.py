"""Names (issue 11, item 2): one rule for every name that becomes a path, wherever the name comes from.

* The rule (``mining/names.py``): every real sequence name of the shared datasets passes it,
  everything that could act as a path (or a hive key, a hidden file, a command-line flag)
  does not, and ``inside`` follows symbolic links.
* A sequence name is never a path: ``--sequences ../../../…/<a real traversal>`` with the
  oxford source used to plan that traversal, write Parquet and pickle files outside
  ``--out`` (into the dataset folder) and crash with IndexError in ``write_manifest``
  because every table resolved to one file. Now the job is refused before anything is
  written, naming the bad name and where it came from.
* A source's own listing is checked like a user's names: a RobotCar root holding a
  traversal folder whose name is not a safe name (a copy named ``… (copy)``, a hidden
  ``.…`` folder, a ``_…`` one readers would skip) fails that sequence at planning, named with where the name came from, and
  the other traversals are mined; nothing of the bad ones is written. Before, their names
  went into paths under ``--out`` as they were.
* ``mine export`` never writes outside DEST: a catalogue whose tube id is ``..`` made
  ``--format crops`` write into DEST's parent (``tube_folder`` replaced only ``/``). Now an
  unsafe tube id (``..``, ``a/../../x``) or sequence name read from the catalogue is an
  error naming it, and nothing is written outside DEST.

The recordings are RobotCar-layout traversals of real KITTI 0005 frames; the catalogue is the
real KITTI 0005 one of ``tests/_catalog_data.py``, one tube renamed."""

from __future__ import annotations

import json
import os
import re
import shutil
import string
from pathlib import Path

import pyarrow as pa
import pytest

from _catalog_data import DATASET, SEQUENCE
from _jobs import SYNTHETIC
from _run import cli, clean_error
from conftest import kitti_0005_stereo
from mining.export.dest import RECORD
from mining.export.run import run_export
from mining.catalog.schema import SCHEMAS
from mining.catalog.store import Store, write_sequence
from mining.catalog.views import connect
from mining.cli import main
from mining.config import load_config
from mining.errors import InputError, MiningError
from mining.names import (MAX_NAME_LENGTH, check_name, check_tube_id, inside, name_problem, path_problem, shown,
                          tube_folder)
from mining.pipeline.executors import LocalExecutor
from mining.pipeline.submit import mine_job
from mining.sources import open_source
from mining.testing.fixtures import write_robotcar_fixture

N_FRAMES = 6
# From <tmp>/r1/r2/r3/root, four levels up is <tmp>: this name reaches <tmp>/elsewhere/victim.
ESCAPE = "../../../../elsewhere/victim"
GOOD = "2014-12-09-13-21-02"
BAD = ("2014-12-09-13-21-02 (copy)", ".2014-12-10-18-10-13", "_2014-12-10-18-10-13")


# -- paths a user names ---------------------------------------------------------------------
#
# The adversarial run (issue 28, case 8): a 300-character --out component ended `mine submit`
# with a traceback, ``OSError: [Errno 36] File name too long``. Now any path option with a
# name the system cannot hold (over NAME_MAX bytes), a path over PATH_MAX, or one that does
# not print as one line is refused before any work: one line naming the option, exit 2.

LONG = "x" * 300


@pytest.mark.parametrize("args", [
    ["submit", *SYNTHETIC, "--workers", "1", "--out", "{tmp}/" + LONG + "/catalog"],
    ["submit", *SYNTHETIC, "--workers", "1", "--out", "{tmp}/" + "d/" * 2100],
    ["status", "--out", "{tmp}/" + LONG],
    ["query", "SELECT 1", "--out", "{tmp}", "--format", "csv", "--output", "{tmp}/" + LONG + ".csv"],
    ["export", "--format", "crops", "--out", "{tmp}", "{tmp}/" + LONG],
    ["render", "--sequence", "0000", "--out", "{tmp}", "{tmp}/" + LONG + ".mp4"],
    ["inspect", "geometry", *SYNTHETIC[:2], "--sequence", "0000", "--out", "{tmp}/" + LONG],
    ["eval", "synthetic", "--n-frames", "2", "--json", "{tmp}/" + LONG + ".json"],
], ids=["submit --out name", "submit --out path", "status --out", "query --output", "export DEST", "render DEST",
        "inspect --out", "eval synthetic --json"])
def test_a_path_the_system_cannot_hold_is_one_line_before_any_work(args, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc, out, err = cli(capsys, *[a.replace("{tmp}", str(tmp_path)) for a in args])
    line = clean_error(err)
    assert rc == 2 and not out and len(err.strip().splitlines()) == 1, (rc, out, err)
    assert re.search(r"a name of 30[0-9] bytes; a name holds at most 255|bytes long; a path holds at most", line), line
    assert os.listdir(tmp_path) == [], "nothing written"


@pytest.mark.parametrize("path, problem", [
    ("x" * 255, None), ("ü" * 127, None), ("a/" + "x" * 256, "a name of 256 bytes"), ("ü" * 128, "a name of 256 bytes"),
    ("/" + "d/" * 2048, "bytes long"), ("", "empty"), ("a\nb", "control"), ("a\x1b[31m", "control"),
    ("x\u202etxt.exe", "text-direction"), ("caf\udce9", "not UTF-8"), ("s3://bucket/key", None),
])
def test_the_path_rule(path, problem):
    found = path_problem(path)
    assert (found is None) if problem is None else (problem in found), (path, found)
    assert "\n" not in shown(path) and shown("plain/ünï") == "plain/ünï"


# -- the rule ----------------------------------------------------------------------------


def test_the_real_sequence_names_are_names(kitti_tracking_root, kitti_raw_root):
    names = open_source("kitti", str(kitti_tracking_root)).sequences() + \
            open_source("kitti-raw", str(kitti_raw_root)).sequences()
    assert "0005" in names and "2011_09_26_drive_0001_sync" in names
    names += ["2014-12-09-13-21-02", "training_0005", "0000", "rosbag2_2024_01_31-12_00_00_0", "a" * MAX_NAME_LENGTH]
    for name in names:
        assert check_name(name, "sequence", "test") == name


@pytest.mark.parametrize("name", ["", ".", "..", "../x", "a/b", "a\\b", "/abs", ".hidden", "-rf", "a..b", "a b",
                                  "sequence=x", "x\n", "caf\u00e9", "a*", "a" * (MAX_NAME_LENGTH + 1), 5, None])
def test_anything_else_is_refused_naming_it_and_its_origin(name):
    with pytest.raises(InputError) as e:
        check_name(name, "sequence", "--sequences")
    assert repr(name) in str(e.value) and "--sequences" in str(e.value)


def test_tube_ids_and_their_folders():
    assert tube_folder("kitti/0005/0000012.003-1") == "kitti_0005_0000012.003-1"
    assert check_tube_id("kitti-raw/2011_09_26_drive_0005_sync/0000001.000", "t")
    for bad in ("..", "a/../../x", "/kitti/0005/1.0", "kitti//1.0", "kitti/0005/", "kitti/.x/1.0"):
        with pytest.raises(InputError, match="tube id"):
            tube_folder(bad)


def test_inside_follows_links(tmp_path):
    dest = tmp_path / "dest"
    (dest / "real").mkdir(parents=True)
    os.symlink(tmp_path, dest / "link")
    assert inside(dest, "real/a.png") == dest / "real" / "a.png"
    for escape in ("../x", "link/x", str(tmp_path / "x")):
        with pytest.raises(InputError, match="outside"):
            inside(dest, escape)


# -- a sequence name is never a path -----------------------------------------------------


@pytest.fixture(scope="module")
def recordings(kitti_tracking_root, tmp_path_factory) -> Path:
    left, right, calib = kitti_0005_stereo(kitti_tracking_root, N_FRAMES)
    base = tmp_path_factory.mktemp("escape")
    write_robotcar_fixture(base / "r1/r2/r3/root", left, right, calib, traversal="t1")
    write_robotcar_fixture(base / "elsewhere", left, right, calib, traversal="victim")
    return base


def _files(folder: Path) -> set[Path]:
    return {p for p in folder.rglob("*")}


def _cfg(base: Path, shared_data: Path, *extra: str):
    folder = shared_data / "proposals_4dgvt_format" / "kitti_tracking_0005" / "top20"
    return load_config(None, ['source.dataset="oxford"', f'source.root="{base / "r1/r2/r3/root"}"',
                              'proposals.proposer="json"', f'proposals.json.folder="{folder}"', "window.core=3",
                              *extra])


def test_sequences_flag_cannot_leave_the_source_or_the_output(recordings, shared_data, tmp_path):
    out = tmp_path / "o1" / "o2" / "out"
    before = _files(recordings) | _files(tmp_path)
    with pytest.raises(InputError) as e:
        mine_job(_cfg(recordings, shared_data), str(out), [ESCAPE], executor=LocalExecutor)
    msg = str(e.value)
    assert repr(ESCAPE) in msg and "--sequences" in msg and "'/'" in msg and "'..'" in msg
    assert _files(recordings) | _files(tmp_path) == before, "nothing is written anywhere"


def test_config_sequences_are_checked_too(recordings, shared_data, tmp_path):
    cfg = _cfg(recordings, shared_data, f'source.sequences=["t1", "{ESCAPE}"]')
    before = _files(recordings)
    with pytest.raises(InputError, match=r"source\.sequences"):
        mine_job(cfg, str(tmp_path / "out"), executor=LocalExecutor)
    assert _files(recordings) == before and not (tmp_path / "out").exists()


def test_mine_submit_refuses_the_name_before_ray_starts(recordings, tmp_path, capsys):
    out = tmp_path / "out"
    rc = main(["submit", "--dataset", "oxford", "--root", str(recordings / "r1/r2/r3/root"), "--out", str(out),
               "--sequences", "t1", ESCAPE, "--no-progress"])
    assert rc == 2
    err = capsys.readouterr().err
    assert repr(ESCAPE) in err and "--sequences" in err and "Traceback" not in err
    assert not out.exists()


# -- a source's own listing --------------------------------------------------------------


@pytest.fixture(scope="module")
def robotcar(kitti_tracking_root, tmp_path_factory) -> Path:
    left, right, calib = kitti_0005_stereo(kitti_tracking_root, N_FRAMES)
    root = tmp_path_factory.mktemp("robotcar")
    for name in (GOOD, *BAD):
        write_robotcar_fixture(root, left, right, calib, traversal=name)
    return root


@pytest.mark.slow  # mines the RobotCar recordings that are well named
def test_a_badly_named_traversal_fails_alone_and_the_others_run(robotcar, shared_data, tmp_path, capsys):
    folder = shared_data / "proposals_4dgvt_format" / "kitti_tracking_0005" / "top20"
    cfg = load_config(None, ['source.dataset="oxford"', f'source.root="{robotcar}"', 'proposals.proposer="json"',
                             f'proposals.json.folder="{folder}"', "window.core=3"])
    out = tmp_path / "out"
    summary = mine_job(cfg, str(out), executor=LocalExecutor)  # no --sequences: the source's listing

    assert summary.ok == 2 and summary.windows == 2, "the good traversal's two windows ran"
    assert not summary.failed
    failed = dict(summary.unplanned)  # left out at planning, named in the summary
    assert sorted(failed) == sorted(f"oxford/{name}" for name in BAD)
    for name in BAD:
        reason = failed[f"oxford/{name}"]
        assert repr(name) in reason and "listing" in reason and str(robotcar) in reason
    assert any(f"FAILED oxford/{BAD[0]} (planning)" in line for line in summary.lines())

    written = [p.relative_to(out).as_posix() for p in out.rglob("*")]
    assert not [p for p in written if any(b in p for b in BAD)], "nothing of the bad traversals is written"
    # `mine status` names them too (job.json keeps why; no path is made from the names).
    from mining.pipeline.status import print_status

    capsys.readouterr()
    assert print_status(str(out)) == 1
    text = capsys.readouterr().out
    assert f"sequences not planned: {len(BAD)}" in text
    for name in BAD:
        assert any(x.startswith(f"failed   oxford/{name} planning") and "listing" in x for x in text.splitlines()), text
    con = connect(out)
    try:
        assert con.execute("SELECT DISTINCT sequence FROM frames").fetchall() == [(GOOD,)]
        assert con.execute("SELECT count(*) FROM frames").fetchone()[0] == N_FRAMES
    finally:
        con.close()


# -- names read from the catalogue by mine export ----------------------------------------


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
    with pytest.raises(MiningError) as e:
        run_export(str(cat), where, "crops", str(dest))
    assert repr(tube_id) in str(e.value) and "tube id" in str(e.value)
    assert {p for p in tmp_path.rglob("*")} - before <= {dest}, "nothing but DEST itself is made"


def test_the_other_tubes_still_export_and_a_safe_id_keeps_its_folder(catalogue, tmp_path):
    cat = _with_tube_id(catalogue, tmp_path, f"{DATASET}/{SEQUENCE}/renamed.000")
    dest = tmp_path / "dest"
    assert run_export(str(cat), "tube_id LIKE '%renamed%'", "crops", str(dest)) == 0
    assert sorted(p.name for p in dest.iterdir()) == [RECORD, "index.json", "index.parquet",
                                                      f"{DATASET}_{SEQUENCE}_renamed.000", "tube_labels.json"]


@pytest.mark.parametrize("layout", ["v3 file", "v2 hive folder"])
def test_kitti_export_of_an_unsafe_sequence_name(catalogue, tmp_path, capsys, layout):
    """The sequence ``../../escaped``, which the KITTI export made a file name of, read back from a
    v3 file's ``sequence`` column, or from a v2 hive folder ``sequence=..%2F..%2Fescaped`` (DuckDB
    and pyarrow decode it)."""
    import pyarrow.parquet as pq

    from _jobs import to_hive_layout

    out, _ = catalogue
    cat = tmp_path / "cat"
    shutil.copytree(out, cat)
    if layout == "v3 file":
        for table in ("tubes", "tube_frames"):
            (f,) = (cat / "catalog" / table).rglob("*.parquet")
            t = pq.read_table(f)
            i = t.schema.get_field_index("sequence")
            pq.write_table(t.set_column(i, t.schema.field(i), pa.array(["../../escaped"] * len(t), pa.string())), f)
    else:
        to_hive_layout(cat)
        for table in ("tubes", "tube_frames"):
            folder = cat / "catalog" / table / f"dataset={DATASET}"
            (folder / f"sequence={SEQUENCE}").rename(folder / "sequence=..%2F..%2Fescaped")
    dest = tmp_path / "work" / "dest"
    before = {p for p in tmp_path.rglob("*")}
    with pytest.raises(MiningError, match=re.escape("sequence name '../../escaped'")):
        run_export(str(cat), "selected", "kitti", str(dest))
    assert {p for p in tmp_path.rglob("*")} - before <= {tmp_path / "work", dest}, "nothing written"


# -- every name a folder a default read sees (issue 40, case 2) --------------------------
#
# The adversarial run: a sequence named ``_x`` (the rule allowed it) lay at
# ``catalog/<table>/<dataset>/_x/``, and pandas, ``pyarrow.dataset`` and ``pq.read_table`` skip
# ``_``- and ``.``-prefixed folders by default: they saw 10 tubes where ``mine query`` saw 20,
# silently. Now a name starts with a letter or digit; a catalogue an older rule let hold
# such a name is refused whole, in one line, when opened.

# One name the rule admits for each character a name may start with, the longest, and each
# character at the end: the names a reader must not skip.
ADMITTED = sorted({c + "x" for c in string.ascii_letters + string.digits + "._-" if name_problem(c + "x") is None}
                  | {"a" + c for c in "._-"} | {"7", "A.b-c_d", "z" * MAX_NAME_LENGTH})


def test_every_name_the_rule_admits_makes_folders_a_default_read_sees(catalogue, tmp_path):
    import pandas as pd
    import pyarrow.dataset as pads
    import pyarrow.parquet as pq

    from mining.catalog.layout import CATALOG, MANIFEST, manifest_path
    from mining.types import Window

    _, tables = catalogue
    tubes = tables["tubes"]
    store = Store(tmp_path / "cat")
    manifest = pa.table({"window": pa.array([], pa.string())})
    for name in ADMITTED:
        named = tubes
        for column in ("dataset", "sequence"):
            named = named.set_column(named.schema.get_field_index(column), column, pa.array([name] * len(tubes)))
        write_sequence(store, "tubes", name, name, named)
        window = Window(name, name, (0, 10), (0, 10)).name  # the window's own file: named by its sequence
        store.write_table(manifest_path(name, name, window), manifest)
    want = len(ADMITTED) * len(tubes)
    folder = tmp_path / "cat" / CATALOG / "tubes"
    assert len(pd.read_parquet(folder)) == want, "pandas"
    assert pads.dataset(folder, format="parquet").count_rows() == want, "pyarrow.dataset"
    assert pq.read_table(folder).num_rows == want, "pq.read_table"
    assert sorted(set(pq.read_table(folder).column("sequence").to_pylist())) == ADMITTED
    # The manifest's files are named by their window, so by their sequence: all seen too.
    assert len(pads.dataset(tmp_path / "cat" / MANIFEST, format="parquet").files) == len(ADMITTED)


@pytest.mark.parametrize("name", ["_x", "_", "__init__", "_" + "a" * 10])
def test_a_name_starting_with_an_underscore_is_refused(name):
    with pytest.raises(InputError) as e:
        check_name(name, "sequence", "--sequences")
    assert repr(name) in str(e.value) and "starts with '_'" in str(e.value)
    assert "starting with a letter or digit" in str(e.value)


def test_mine_submit_refuses_an_underscore_name_before_anything_is_written(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "out"
    rc, _, err = cli(capsys, "submit", *SYNTHETIC[:2], "--sequences", "0000", "_1", *SYNTHETIC[4:],
                     "--workers", "1", "--out", str(out))
    line = clean_error(err)
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert "'_1'" in line and "--sequences" in line and "starts with '_'" in line, line
    assert os.listdir(tmp_path) == [], "nothing written"


def test_config_sequences_starting_with_an_underscore_are_refused(tmp_path):
    cfg = load_config(None, ['source.dataset="synthetic"', 'source.sequences=["0000", "_1"]',
                             "source.options.n_frames=8"])
    with pytest.raises(InputError) as e:
        mine_job(cfg, str(tmp_path / "out"), executor=LocalExecutor)
    assert "'_1'" in str(e.value) and "source.sequences" in str(e.value) and "starts with '_'" in str(e.value)
    assert not (tmp_path / "out").exists()


def _as_older_rule_named(base: Path, dst: Path, name: str) -> Path:
    """A copy of the mined catalogue ``base`` whose sequence is called ``name`` (as an older name
    rule let it be): job.json's windows and the compacted tables' folders."""
    from _jobs import SEQ

    shutil.copytree(base, dst)
    job = json.loads((dst / "job.json").read_text())
    for w in job["windows"]:
        w["sequence"], w["window"] = name, w["window"].replace(SEQ, name, 1)
    (dst / "job.json").write_text(json.dumps(job))
    for folder in list((dst / "catalog").glob(f"*/*/{SEQ}")):
        folder.rename(folder.with_name(name))
    return dst


@pytest.mark.parametrize("command", [["query", "SELECT count(*) FROM tubes"], ["status"]], ids=["query", "status"])
def test_a_catalogue_holding_a_name_an_older_rule_allowed_is_one_line(base_catalogue, tmp_path, capsys, command):
    out = _as_older_rule_named(base_catalogue[0], tmp_path / "out", "_1")
    rc, _, err = cli(capsys, *command, "--out", str(out))
    line = clean_error(err)
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert "'_1'" in line and "--new-run" in line and "starting with a letter or digit" in line, line


@pytest.mark.slow  # mines the catalogue again
def test_new_run_mines_a_catalogue_an_older_rule_named_again(base_catalogue, tmp_path):
    from _jobs import mine

    out = _as_older_rule_named(base_catalogue[0], tmp_path / "out", "_1")
    summary = mine(out, mode="new")  # `mine submit --new-run`, as the refusal advises
    assert summary.ok == 2 and not summary.failed, summary.lines()
    con = connect(out)
    try:
        assert con.execute("SELECT DISTINCT sequence FROM frames").fetchall() == [("0000",)]
    finally:
        con.close()


def test_a_catalogue_no_job_wrote_holding_such_a_name_is_refused_too(catalogue, tmp_path):
    out, _ = catalogue
    cat = tmp_path / "cat"
    shutil.copytree(out, cat)
    for folder in list((cat / "catalog").glob(f"*/*/{SEQUENCE}")):
        folder.rename(folder.with_name("_" + SEQUENCE))
    with pytest.raises(InputError) as e:
        connect(cat)
    assert repr("_" + SEQUENCE) in str(e.value) and "--new-run" in str(e.value) and "\n" not in str(e.value)


# -- the longest names fit every path (issue 40, case 7) ----------------------------------
#
# The adversarial run: a sequence of 128 characters (the rule allowed it) aborted the whole
# job, good sequences included, blaming --out: its window name (the sequence's name and its
# frame range) was 144 characters, over the name rule, and job.json was already written. Now
# a name is at most 100 characters and a window's 120 (100 + 2 × (1 + 9)), and every path
# built from names of those lengths, its temporary name included, fits NAME_MAX.


def test_every_path_built_from_names_of_the_maximum_length_fits(tmp_path):
    from mining.catalog import layout, safe_files
    from mining.catalog.store import LEFTOVER, TMP_MARK
    from mining.export.fiftyone_video import VIDEO_SUFFIX
    from mining.export.rerun_rrd import RRD_SUFFIX
    from mining.export.selection import video_name
    from mining.names import FRAME_DIGITS, MAX_WINDOW_NAME_LENGTH, NAME_MAX
    from mining.types import Window

    d, s = "d" * MAX_NAME_LENGTH, "s" * MAX_NAME_LENGTH
    last = 10 ** FRAME_DIGITS - 1
    w = Window(d, s, (last - 1, last), (last - 1, last))
    assert len(w.name) == MAX_WINDOW_NAME_LENGTH == 120
    catalogue = [
        *(layout.part_path(t, d, s, w.name) for t in layout.PART_TABLES), layout.manifest_path(d, s, w.name),
        layout.files_path(d, s, w.name), layout.stitch_path(d, s), layout.observed_path(d, s, w.name),
        layout.running_path(d, s, w.name), layout.cache_path(w), layout.cache_path(w, layout.LEGACY_CACHE_SUFFIX),
        layout.done_path(d, s), *(layout.catalog_file(t, d, s, 999) for t in layout.TABLE_DIRS)]
    tube_id = f"{d}/{s}/{last:07d}.999-99"  # stitch.py: first frame and observation, -k for the k-th alike
    video = video_name(d, s)
    export = [video + VIDEO_SUFFIX, f"labels/{video}.json", video + RRD_SUFFIX, f"{tube_folder(tube_id)}/index.json",
              f"{s}.txt", f"{s}.ids.json"]  # fiftyone, rerun, crops, kitti (export/*.py)
    for rel in catalogue + export:
        for name in rel.split("/"):
            temporary = f".{name}{TMP_MARK}{'0' * 12}"  # what every write makes first (store, safe_files)
            assert LEFTOVER.fullmatch(temporary)
            assert len(temporary.encode()) <= NAME_MAX, (rel, len(temporary.encode()))
    # And written for real, through the catalogue's and the exports' own writers.
    store = Store(tmp_path / "out")
    for rel in catalogue:
        store.write_bytes(rel, b"x")
    for rel in export:
        safe_files.write_atomic(tmp_path / "dest", rel, b"x")
    assert all((tmp_path / "out" / rel).is_file() for rel in catalogue)
    assert all((tmp_path / "dest" / rel).is_file() for rel in export)


def test_a_sequence_over_the_maximum_length_is_refused_naming_the_limit(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert MAX_NAME_LENGTH == 100, "the limit docs/OPERATING.md states"
    long = "0" * 100 + "1"  # a synthetic sequence is named by an integer
    rc, _, err = cli(capsys, "submit", *SYNTHETIC[:2], "--sequences", "0000", long, *SYNTHETIC[4:],
                     "--workers", "1", "--out", str(tmp_path / "out"))
    line = clean_error(err)
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert repr(long) in line and f"{MAX_NAME_LENGTH + 1} characters, more than {MAX_NAME_LENGTH}" in line, line
    assert "--sequences" in line and "--out" not in line.split(repr(long))[1], line
    assert os.listdir(tmp_path) == [], "nothing written"


@pytest.mark.slow  # a real `mine submit` on a local Ray
def test_a_sequence_of_the_maximum_length_is_mined_beside_another(tmp_path):
    from _jobs import TINY
    from _run import SUMMARY, submit

    longest = "0" * (MAX_NAME_LENGTH - 1) + "1"  # a synthetic sequence is named by an integer
    args = list(TINY)
    at = args.index("--sequences")
    args[at + 1:at + 2] = ["0000", longest]
    rc, out, err = submit(tmp_path / "out", *args, workers=1)
    assert rc == 0, (out, err)
    assert SUMMARY.search(out + err).groups() == ("4", "0", "0", "4"), out + err
    con = connect(tmp_path / "out")
    try:
        got = con.execute("SELECT sequence, count(*) FROM frames GROUP BY sequence ORDER BY sequence").fetchall()
    finally:
        con.close()
    assert got == [("0000", 12), (longest, 12)]


def test_a_single_file_dest_of_the_longest_name_is_written(tmp_path):
    """``mine render``'s and a one-file export's DEST: its private folder beside it was named
    ``.<DEST name>.partial-<random>``, over NAME_MAX for a DEST name the path check admits."""
    from mining.export.dest import publish_file

    for name in ("v" * 251 + ".mp4", "ü" * 125 + ".mp4"):  # 255 bytes each: the longest name a path may hold
        dest = tmp_path / name
        assert path_problem(dest) is None
        publish_file(dest, False, lambda path: path.write_bytes(b"video"))
        assert dest.read_bytes() == b"video"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["v" * 251 + ".mp4", "ü" * 125 + ".mp4"])
    # A file a command writes in place (`mine query --output`, `--json`): its temporary name beside it too.
    from mining.catalog import safe_files

    safe_files.write_atomic(tmp_path, "q" * 251 + ".csv", b"a,b\n")
    assert (tmp_path / ("q" * 251 + ".csv")).read_bytes() == b"a,b\n"
