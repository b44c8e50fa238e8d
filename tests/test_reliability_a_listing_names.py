"""A source's own listing is checked like a user's names (issue 11, item 2): a RobotCar
root holding a traversal folder whose name is not a safe name (a copy named
``… (copy)``, a hidden ``.…`` folder) fails that sequence at planning, named with where
the name came from, and the other traversals are mined; nothing of the bad ones is
written. Before, their names went into paths under ``--out`` as they were.

The recordings are RobotCar-layout traversals of real KITTI 0005 frames."""

from __future__ import annotations

from pathlib import Path

import pytest

from conftest import kitti_0005_stereo
from mining.catalog.views import connect
from mining.config import load_config
from mining.pipeline.executors import LocalExecutor
from mining.pipeline.submit import mine_job
from mining.testing.fixtures import write_robotcar_fixture

N_FRAMES = 6
GOOD = "2014-12-09-13-21-02"
BAD = ("2014-12-09-13-21-02 (copy)", ".2014-12-10-18-10-13")


@pytest.fixture(scope="module")
def robotcar(kitti_tracking_root, tmp_path_factory) -> Path:
    left, right, calib = kitti_0005_stereo(kitti_tracking_root, N_FRAMES)
    root = tmp_path_factory.mktemp("robotcar")
    for name in (GOOD, *BAD):
        write_robotcar_fixture(root, left, right, calib, traversal=name)
    return root


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
