"""One window's observe step on real KITTI frames: a bad frame fails its own window only."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from mining.config import load_config
from mining.errors import InputError
from mining.pipeline.window import observe_window, track_window
from mining.sources.kitti import KittiTrackingSource
from mining.types import plan_windows

from conftest import REPO

N = 8


def _copy(src: Path, dst: Path) -> Path:
    for cam in ("image_02", "image_03"):
        (dst / "training" / cam / "0005").mkdir(parents=True)
        for i in range(N):
            name = f"{i:06d}.png"
            shutil.copyfile(src / "training" / cam / "0005" / name, dst / "training" / cam / "0005" / name)
    (dst / "training" / "calib").mkdir()
    shutil.copyfile(src / "training" / "calib" / "0005.txt", dst / "training" / "calib" / "0005.txt")
    return dst


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_bad_warm_up_frame_fails_only_the_window_that_owns_it(kitti_tracking_root, tmp_path):
    root = _copy(kitti_tracking_root, tmp_path / "kitti")
    cfg = load_config(REPO / "jobs" / "kitti.toml", ['proposals.proposer="stereo"'])
    source = KittiTrackingSource(str(root))
    plan = source.plan("0005")
    first, second = plan_windows(plan, core=4)
    clean = observe_window(source, plan, second, cfg)
    assert clean[0].egomotion_ok is True  # the warm-up frames give the core's first egomotion

    bad = root / "training" / "image_03" / "0005" / "000003.png"
    bad.write_bytes(bad.read_bytes()[:2000])  # the last frame of the first window, cut off
    with pytest.raises(InputError) as e:
        observe_window(source, plan, first, cfg)
    assert e.value.frame == 3 and str(bad) in str(e.value)

    frames = observe_window(source, plan, second, cfg)
    assert [f.position for f in frames] == [4, 5, 6, 7]
    assert frames[0].egomotion_ok is None and frames[0].T_cur_prev is None  # no previous frame: not the identity
    assert frames[1].egomotion_ok is True
    for a, b in zip(frames[1:], clean[1:]):  # later frames are as in the clean run
        assert [r["counts"] for r in a.observations.proposals.rles] == [r["counts"] for r in b.observations.proposals.rles]
    _, poses = track_window(frames, cfg)  # the poses it tracked with, one segment
    assert [s for _, s in poses] == [0, 0, 0, 0]
