"""A sequence name is never a path (issue 11, item 2): ``--sequences ../../../…/<a real
traversal>`` with the oxford source used to plan that traversal, write Parquet and pickle
files outside ``--out`` (into the dataset folder) and crash with IndexError in
``write_manifest`` because every table resolved to one file. Now the job is refused before
anything is written, naming the bad name and where it came from.

The recordings are RobotCar-layout traversals of real KITTI 0005 frames."""

from __future__ import annotations

from pathlib import Path

import pytest

from conftest import kitti_0005_stereo
from mining.cli import main
from mining.config import load_config
from mining.errors import InputError
from mining.pipeline.executors import LocalExecutor
from mining.pipeline.submit import mine_job
from mining.testing.fixtures import write_robotcar_fixture

N_FRAMES = 6
# From <tmp>/r1/r2/r3/root, four levels up is <tmp>: this name reaches <tmp>/elsewhere/victim.
ESCAPE = "../../../../elsewhere/victim"


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
