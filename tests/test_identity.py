"""A job's identity is complete (issue 11, item 4): config, source root, recording, sequences, frames.

A resubmission to an ``--out`` that holds another job's catalogue is refused naming every
key that differs (old → new), before any work; ``--extend`` widens the frame range and
gives exactly the catalogue of a clean run of the wide range; ``--new-run`` moves the
old catalogue aside and starts again. Real files, real DuckDB, a small synthetic job and
real KITTI frames, mined in this process (``LocalExecutor``).

A catalogue without a readable job.json is not an empty folder (issue 19, scope item 2). The
adversarial run deleted ``OUT/job.json`` (or moved it away, as its own error message
suggested) and submitted a different job to the same ``--out``: the old catalogue (78 tubes)
was silently replaced (77 tubes), nothing kept under ``_replaced/``. Now such a folder is
refused, naming job.json and offering ``--new-run``, which keeps the old catalogue under
``OUT/_replaced/`` like any other; an unreadable job.json's message no longer says to move
it away, and ``--new-run`` over it works too. ``--new-run`` never moves a catalogue
through a link planted at ``OUT/_replaced`` (the ``mine submit`` case in a process of its own).
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from mining.catalog.records import UnreadableRecord
from mining.catalog.safe_files import LinkError
from mining.catalog.views import connect
from mining.config import load_config
from mining.errors import ConfigError, InputError
from mining.pipeline.executors import LocalExecutor
from mining.pipeline.status import job_status
from mining.pipeline.submit import mine_job
from _jobs import CLI_SMALL, SEQ, catalogue_files, copy_of, files, mine, small_cfg, tables
from _run import env, mine_cmd
from conftest import REPO

KITTI_CORE = ["window.core=4", "window.context_before=2", "window.context_after=2", 'proposals.proposer="stereo"']


def _kitti_recording(src: Path, dst: Path, frames: range) -> Path:
    """Real KITTI 0005 frames ``frames``, renumbered from 0, in the tracking layout."""
    for cam in ("image_02", "image_03"):
        d = dst / "training" / cam / "0005"
        d.mkdir(parents=True)
        for i, f in enumerate(frames):
            shutil.copyfile(src / "training" / cam / "0005" / f"{f:06d}.png", d / f"{i:06d}.png")
    (dst / "training" / "calib").mkdir()
    shutil.copyfile(src / "training" / "calib" / "0005.txt", dst / "training" / "calib" / "0005.txt")
    return dst


def _kitti_cfg(root: Path):
    return load_config(None, ['source.dataset="kitti"', f'source.root="{root.as_posix()}"', *KITTI_CORE])


def test_another_recording_on_the_same_out_is_refused_naming_every_differing_key(kitti_tracking_root, tmp_path):
    a = _kitti_recording(kitti_tracking_root, tmp_path / "a", range(0, 4))
    b = _kitti_recording(kitti_tracking_root, tmp_path / "b", range(8, 14))  # another recording: 6 frames
    out = tmp_path / "out"
    s = mine_job(_kitti_cfg(a), str(out), ["0005"], (0, None), executor=LocalExecutor)
    assert s.ok == 1 and not s.failed, s.lines()
    before = files(out)

    with pytest.raises(ConfigError) as e:
        mine_job(_kitti_cfg(b), str(out), ["0005"], (0, None), executor=LocalExecutor)
    msg = str(e.value)
    named = dict(re.findall(r"^  (\S+): (.+)$", msg, re.M))
    assert named.keys() == {"source.root", "frames.0005", "recording.0005.frames", "recording.0005.stamps"}, msg
    assert named["source.root"] == f"{a.resolve()} → {b.resolve()}"
    assert named["frames.0005"] == "0:4 → 0:6" and named["recording.0005.frames"] == "4 → 6"
    assert "--new-run" in msg and "--extend" in msg
    assert files(out) == before, "the refused job wrote into the catalogue"
    # The catalogue still holds the first recording only, and job.json names it.
    assert json.loads((out / "job.json").read_text())["identity"]["source.root"] == str(a.resolve())


def test_a_config_change_is_refused_naming_the_key(base_catalogue, tmp_path):
    out = copy_of(base_catalogue, tmp_path / "out")

    with pytest.raises(ConfigError, match=r"(?m)^  config\.geometry\.stereo\.num_disparities: 128 → 96$"):
        mine(out, cfg=small_cfg("geometry.stereo.num_disparities=96"))


def test_widened_frames_are_refused_without_extend(base_catalogue, tmp_path):
    out = copy_of(base_catalogue, tmp_path / "out")
    before = files(out)
    with pytest.raises(ConfigError, match=r"(?m)^  frames\.0000: 0:16 → 0:24$"):
        mine(out, (0, 24))
    assert files(out) == before


def test_narrowed_frames_are_refused_even_with_extend(base_catalogue, tmp_path):
    out = copy_of(base_catalogue, tmp_path / "out")
    before = files(out)
    with pytest.raises(ConfigError, match=r"(?m)^  frames\.0000: 0:16 → 0:8$"):
        mine(out, (0, 8))
    with pytest.raises(ConfigError, match=r"--extend only widens.*changes frames\.0000"):
        mine(out, (0, 8), mode="extend")
    assert files(out) == before
    assert [r.status for r in job_status(str(out))] == ["done", "done"]  # no frame or tube was dropped
    assert tables(out) == base_catalogue[1]


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_extend_gives_the_catalogue_of_a_clean_run_of_the_wide_range(base_catalogue, tmp_path):
    wide = (0, 24)
    extended = copy_of(base_catalogue, tmp_path / "extended")
    s = mine(extended, wide, mode="extend")
    # [0, 8) keeps its context and is resumed; [8, 16) has a wider context now and runs
    # again; [16, 24) is new.
    assert (s.skipped, s.ok, s.failed) == (1, 2, {}), s.lines()
    clean = tmp_path / "clean"
    assert mine(clean, wide).ok == 3
    got, want = tables(extended), tables(clean)
    for k in want:
        assert got[k] == want[k], f"{k}: extended {len(got[k])} rows, clean {len(want[k])}"

    def windows(out):
        con = connect(out)
        try:
            return con.sql('SELECT "window", core_start, core_end, context_start, context_end, status '
                           'FROM windows ORDER BY "window"').fetchall()
        finally:
            con.close()
    assert windows(extended) == windows(clean)
    assert len(windows(clean)) == 3
    con = connect(clean)
    try:  # the comparison covers tubes stitched across the re-cut border
        assert con.sql("SELECT count(*) FROM tubes WHERE n_windows > 1 AND frame_end >= 16").fetchone()[0] > 0
    finally:
        con.close()
    # And the extended job is now the wide one: resubmitting it does nothing.
    again = mine(extended, wide)
    assert (again.skipped, again.ok) == (3, 0)


def test_new_run_moves_the_old_catalogue_aside(base_catalogue, tmp_path, capsys):
    out = copy_of(base_catalogue, tmp_path / "out")
    old = files(out)
    old_run = json.loads((out / "job.json").read_text())["run_id"]
    s = mine(out, (0, 8), mode="new")
    assert s.ok == 1 and s.skipped == 0, s.lines()
    moved = list((out / "_replaced").iterdir())
    assert len(moved) == 1 and moved[0].name.startswith(old_run + "-")
    assert str(moved[0]) in capsys.readouterr().err
    # Everything the old job wrote is there, byte for byte.
    kept = {k.split("/", 2)[2]: v for k, v in files(out).items() if k.startswith("_replaced/")}
    assert kept == {k: v for k, v in old.items() if k != ".mine.lock"}
    # The new catalogue holds frames 0:8 only, and a new run id.
    record = json.loads((out / "job.json").read_text())
    assert record["run_id"] != old_run and record["identity"][f"frames.{SEQ}"] == "0:8"
    assert len(tables(out)["frames"]) == 8
    assert [r.window for r in job_status(str(out))] == [f"{SEQ}-0000000-0000008"]


def _before_the_filters_moved(out: Path) -> None:
    """Rewrite ``out``'s job.json as a version before issue 27 wrote it: the geometric proposal
    filter under ``proposals.filters`` (config and identity), not ``localise.filters``."""
    job = json.loads((out / "job.json").read_text())
    job["config"]["proposals"]["filters"] = job["config"]["localise"].pop("filters")
    job["identity"] = {k.replace("config.localise.filters.", "config.proposals.filters."): v
                       for k, v in job["identity"].items()}
    assert any(k.startswith("config.proposals.filters.") for k in job["identity"])
    (out / "job.json").write_text(json.dumps(job, indent=1))


def test_a_catalogue_made_before_the_filters_moved_is_refused_saying_why(base_catalogue, tmp_path):
    from mining.catalog.records import JobRecord
    from mining.catalog.store import Store

    out = copy_of(base_catalogue, tmp_path / "out")
    _before_the_filters_moved(out)
    before = catalogue_files(out)
    # Its record still reads, with the keys at today's places; status still reads it.
    assert JobRecord.load(Store(str(out))).job_config() == small_cfg()
    assert [r.status for r in job_status(str(out))] == ["done", "done"]
    # The same job: refused (its rows carry the old layout's params hash), naming the move and the ways out.
    for mode in ("resume", "extend"):
        with pytest.raises(ConfigError, match=r"made before proposals\.filters moved to localise\.filters") as e:
            mine(out, mode=mode)
        assert "--new-run" in str(e.value) and "also differs" not in str(e.value), str(e.value)
    # Another difference besides the move is named too, as today's keys.
    with pytest.raises(ConfigError, match=r"(?m)also differs in 1 key\(s\):\n  config\.localise\.filters\.noise_sigmas: 2\.0 → 0\.0$"):
        mine(out, cfg=small_cfg("localise.filters.noise_sigmas=0.0"))
    assert catalogue_files(out) == before, "the refused job wrote into the catalogue"


def test_a_catalogue_made_before_the_mode_twins_became_tables_is_refused_saying_why():
    """Issue 38: select.epsilon1 … score.known_log_margin_calibrated became tables keyed by their mode; an
    identity recorded before is refused naming the moves, and nothing else differs once they are undone
    (tubes.min_association_normalised fills both association_floor.normalised and .innovation)."""
    from mining.catalog.identity import check_resubmit, job_identity

    new = job_identity(load_config(), {}, (0, None))
    old_names = {"select.price.reference": "select.epsilon1", "select.price.calibrated": "select.epsilon1_calibrated",
                 "select.overlap_weight.reference": "select.epsilon2",
                 "select.overlap_weight.calibrated": "select.epsilon2_calibrated",
                 "tubes.association_floor.reference": "tubes.min_association",
                 "tubes.association_floor.normalised": "tubes.min_association_normalised",
                 "score.known_margin.reference": "score.known_log_margin",
                 "score.known_margin.calibrated": "score.known_log_margin_calibrated"}
    old = {f"config.{old_names.get(k[len('config.'):], k[len('config.'):])}" if k.startswith("config.") else k: v
           for k, v in new.items() if k != "config.tubes.association_floor.innovation"}
    assert "config.select.epsilon1" in old and not any(".price." in k for k in old)
    for mode in ("resume", "extend"):
        with pytest.raises(ConfigError, match=r"made before select\.epsilon1 moved to select\.price\.reference; ") as e:
            check_resubmit(old, new, "out", mode)
        assert ("tubes.min_association_normalised moved to tubes.association_floor.normalised and "
                "tubes.association_floor.innovation") in str(e.value)
        assert "also differs" not in str(e.value) and "--new-run" in str(e.value), str(e.value)
    check_resubmit(new, new, "out")  # today's identity is not mistaken for an old one


# -- a catalogue without a readable job.json ---------------------------------------------


@pytest.mark.parametrize("mode", ["resume", "extend"])
def test_a_catalogue_whose_job_json_is_gone_is_not_mined_over(base_catalogue, tmp_path, mode):
    out = copy_of(base_catalogue, tmp_path / "out")
    (out / "job.json").rename(tmp_path / "job.json.moved-away")
    before = catalogue_files(out)
    with pytest.raises(InputError) as e:
        mine(out, (0, 8), mode=mode)  # another job: the old code replaced the catalogue with it
    msg = str(e.value)
    assert f"{out / 'job.json'}: missing" in msg and "catalog/" in msg and "--new-run" in msg, msg
    assert "move it away" not in msg
    assert catalogue_files(out) == before and not (out / "_replaced").exists()


def test_an_unreadable_job_json_says_new_run_not_move_it_away(base_catalogue, tmp_path):
    out = copy_of(base_catalogue, tmp_path / "out")
    (out / "job.json").write_text("{ truncated")
    before = catalogue_files(out)
    with pytest.raises(UnreadableRecord) as e:
        mine(out)
    assert "--new-run" in str(e.value) and "_replaced" in str(e.value) and "move it away" not in str(e.value)
    assert catalogue_files(out) == before


@pytest.mark.slow  # mines a window
@pytest.mark.parametrize("damage", ["missing", "unreadable"])
def test_new_run_keeps_a_catalogue_without_a_readable_job_json_under_replaced(base_catalogue, tmp_path, capsys,
                                                                              damage):
    out = copy_of(base_catalogue, tmp_path / "out")
    if damage == "missing":
        (out / "job.json").unlink()
    else:
        (out / "job.json").write_text("{ truncated")
    old = catalogue_files(out)
    s = mine(out, (0, 8), mode="new")
    assert s.ok == 1 and not s.failed, s.lines()
    moved, = (out / "_replaced").iterdir()
    assert moved.name.startswith("unknown-run-")
    assert str(moved) in capsys.readouterr().err
    kept = {k.split("/", 2)[2]: v for k, v in files(out).items() if k.startswith("_replaced/")}
    assert kept == old, "every file of the old catalogue is kept, byte for byte"
    assert len(tables(out)["frames"]) == 8
    assert json.loads((out / "job.json").read_text())["identity"]["frames.0000"] == "0:8"


def test_new_run_never_moves_the_catalogue_through_a_link(base_catalogue, tmp_path):
    """``OUT/_replaced`` planted as a link elsewhere: the old code made the run's folder
    there and moved the whole catalogue out of --out."""
    out = copy_of(base_catalogue, tmp_path / "out")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (out / "_replaced").symlink_to(elsewhere, target_is_directory=True)
    before = catalogue_files(out)
    with pytest.raises(LinkError, match="_replaced: is a link"):
        mine(out, (0, 8), mode="new")
    assert list(elsewhere.iterdir()) == []
    assert catalogue_files(out) == before


@pytest.mark.slow  # a `mine submit` process (refused before Ray starts)
def test_mine_submit_over_a_catalogue_without_job_json_is_refused_in_one_line(base_catalogue, tmp_path):
    out = copy_of(base_catalogue, tmp_path / "out")
    (out / "job.json").unlink()
    base_tables = tables(out)
    done = subprocess.run(mine_cmd("submit", *CLI_SMALL, "--frames", "0:8", "--out", str(out), "--workers", "1",
                                   "--no-progress"),
                          cwd=REPO, capture_output=True, text=True, timeout=300, env=env())
    assert done.returncode == 2, done.stdout + done.stderr
    err = done.stderr.strip().splitlines()
    assert len(err) == 1 and "job.json: missing" in err[0] and "--new-run" in err[0], done.stderr
    assert tables(out) == base_tables and not (out / "job.json").exists()
