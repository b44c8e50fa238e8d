"""Planning problems fail their sequence only, and only inside ``--frames`` (issue 11, item 7).

Before, any problem found while planning (a missing right image, a missing calibration
file, an empty folder) stopped the whole multi-sequence job before any window ran, even
when the bad frame lay outside ``--frames``. Jobs here mine real KITTI 0005 frames (two
sequences made of them, symlinked) through the real pipeline: in this process with the
LocalExecutor, and once through ``mine submit`` on a real local Ray (slow).
"""

from __future__ import annotations

import re

import pytest

from _jobs import SYNTHETIC
from _kitti_copy import kitti_copy
from _run import clean_error, cli_status, submit
from mining.catalog.views import connect
from mining.config import load_config
from mining.errors import InputError
from mining.pipeline.executors import LocalExecutor
from mining.pipeline.submit import mine_job


def _cfg(root):
    return load_config(overrides=['source.dataset="kitti"', f'source.root="{root}"'])


def _frames_in_catalogue(out) -> dict[str, int]:
    con = connect(out)
    try:
        return dict(con.sql("SELECT sequence, count(*) FROM frames GROUP BY sequence").fetchall())
    finally:
        con.close()


def _break(split, seq: str, how: str):
    """Damage sequence ``seq`` of a KITTI copy; returns (what the error must name, a repair)."""
    if how == "right-image":
        victim = split / "image_03" / seq / "000002.png"
        target = victim.resolve()
        victim.unlink()
        return f"{victim}, frame 2: right image is missing", lambda: victim.symlink_to(target)
    if how == "calib-file":
        victim = split / "calib" / f"{seq}.txt"
        text = victim.read_text()
        victim.unlink()
        return f"{victim}: calibration file is missing", lambda: victim.write_text(text)
    if how == "empty-folder":
        folder = split / "image_02" / seq
        links = {p: p.resolve() for p in folder.iterdir()}
        for p in links:
            p.unlink()
        return f"{folder}: no images found", lambda: [p.symlink_to(t) for p, t in links.items()]
    raise AssertionError(how)


@pytest.mark.parametrize("how", ["right-image", "calib-file", "empty-folder"])
def test_a_planning_problem_fails_its_sequence_and_the_other_runs(tmp_path, kitti_tracking_root, how, capsys):
    root = kitti_copy(tmp_path / "kitti", kitti_tracking_root, ("0005", "0006"), n_frames=4)
    named, repair = _break(root / "training", "0006", how)
    out = str(tmp_path / "out")
    summary = mine_job(_cfg(root), out, ["0005", "0006"], (0, 4), executor=LocalExecutor)
    assert summary.ok == 1 and not summary.failed, summary.lines()
    assert list(summary.unplanned) == ["kitti/0006"] and named in summary.unplanned["kitti/0006"]
    assert any(line.startswith("FAILED kitti/0006 (planning):") and named in line for line in summary.lines())
    assert _frames_in_catalogue(out) == {"0005": 4}
    # `mine status` keeps saying so after the submit has gone, and exits 1.
    rc, text = cli_status(capsys, out)
    assert rc == 1 and "sequences not planned: 1" in text, text
    line = next(x for x in text.splitlines() if x.startswith("failed   kitti/0006 planning"))
    assert named in line, text
    # Repaired, the same command runs only what is missing, and status is clean.
    repair()
    again = mine_job(_cfg(root), out, ["0005", "0006"], (0, 4), executor=LocalExecutor)
    assert (again.ok, again.skipped, again.unplanned) == (1, 1, {})
    assert _frames_in_catalogue(out) == {"0005": 4, "0006": 4}
    rc, text = cli_status(capsys, out)
    assert rc == 0 and "not planned" not in text and not any(x.startswith("failed") for x in text.splitlines()), text


def test_a_problem_outside_frames_does_not_matter(tmp_path, kitti_tracking_root):
    root = kitti_copy(tmp_path / "kitti", kitti_tracking_root, n_frames=16)
    victim = root / "training" / "image_03" / "0005" / "000012.png"
    victim.unlink()
    out = str(tmp_path / "out")
    summary = mine_job(_cfg(root), out, ["0005"], (0, 4), executor=LocalExecutor)
    assert (summary.ok, summary.failed, summary.unplanned) == (1, {}, {})
    assert _frames_in_catalogue(out) == {"0005": 4}
    # Inside the range it does, naming the file and the frame; positions did not shift.
    with pytest.raises(InputError, match=re.escape(f"{victim}, frame 12: right image is missing")):
        mine_job(_cfg(root), str(tmp_path / "out2"), ["0005"], (10, 14), executor=LocalExecutor)


def test_oxford_missing_image_outside_the_range_does_not_matter(tmp_path, kitti_tracking_root):
    from conftest import kitti_0005_stereo
    from mining.sources.oxford import OxfordSource
    from mining.testing.fixtures import write_robotcar_fixture

    left, right, calib = kitti_0005_stereo(kitti_tracking_root, 6)
    write_robotcar_fixture(tmp_path, left, right, calib, traversal="t")
    plan = OxfordSource(tmp_path).plan("t")
    victim = tmp_path / "t" / "stereo" / "right" / f"{plan.t_ns[4] // 1000}.png"
    victim.unlink()
    src = OxfordSource(tmp_path)
    assert src.plan("t", 0, 4).frames == plan.frames  # the frame keeps its place
    assert src.read_frame(src.plan("t", 0, 4), 3).index == plan.frames[3]
    with pytest.raises(InputError, match="frame 4") as e:
        src.plan("t", 2, 6)
    assert str(victim) in str(e.value)


@pytest.mark.slow  # two `mine submit` runs on a local Ray
def test_submit_on_ray_mines_the_good_sequence_and_names_the_bad_one(tmp_path, kitti_tracking_root):
    root = kitti_copy(tmp_path / "kitti", kitti_tracking_root, ("0005", "0006"), n_frames=4)
    named, _ = _break(root / "training", "0006", "right-image")
    out = tmp_path / "out"
    rc, stdout, stderr = submit(out, "--dataset", "kitti", "--root", str(root), "--sequences", "0005", "0006",
                                "--frames", "0:4", workers=1)
    assert rc == 1, (rc, stdout, stderr)
    assert "Traceback" not in stderr
    assert "windows: 1 ok, 0 failed, 0 already done (of 1)" in stdout
    assert any(line.startswith("FAILED kitti/0006 (planning):") and named in line for line in stdout.splitlines())
    assert _frames_in_catalogue(out) == {"0005": 4}


@pytest.mark.slow  # `mine submit` on a local Ray
def test_after_a_preflight_failure_the_fixed_command_runs_on_the_same_out(tmp_path):
    # Before, a bad proposer name failed every window after Ray started and left a job.json
    # by which the fixed command was then refused on the same --out.
    out = tmp_path / "out"
    rc, stdout, stderr = submit(out, *SYNTHETIC, "--set", 'proposals.proposer="stero"', workers=1)
    assert rc == 2 and "unknown proposer 'stero'" in clean_error(stderr), (rc, stdout, stderr)
    assert not (out / "job.json").exists()
    rc, stdout, stderr = submit(out, *SYNTHETIC, "--set", 'proposals.proposer="stereo"', workers=1)
    assert rc == 0, (rc, stdout, stderr)
    assert "windows: 1 ok, 0 failed, 0 already done (of 1)" in stdout


def test_a_sequence_the_source_does_not_have_says_the_nearest_it_has(tmp_path, kitti_tracking_root):
    from mining.pipeline.preflight import plan_sequences

    root = kitti_copy(tmp_path / "kitti", kitti_tracking_root, n_frames=4)
    with pytest.raises(InputError, match=re.escape("no sequence '5'; did you mean '0005'? (have: 0005)")):
        plan_sequences(_cfg(root), ["5"])
    with pytest.raises(InputError, match=re.escape("no sequence 'zzz' (have: 0005)")):
        plan_sequences(_cfg(root), ["zzz"])
    assert list(plan_sequences(_cfg(root), ["0005"]).plans) == ["0005"]
