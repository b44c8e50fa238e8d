"""`mine inspect geometry` end to end through the real CLI, on real KITTI frames."""

from __future__ import annotations

import json
import shutil

import numpy as np

from mining.cli import main
from mining.eval.odometry import odometry_errors
from mining.formats.disparity import read_disparity_png
from mining.formats.poses import read_poses


def test_inspect_geometry_writes_kitti_formats(kitti_tracking_root, tmp_path):
    out = tmp_path / "out"
    rc = main(["inspect", "geometry", "--dataset", "kitti", "--root", str(kitti_tracking_root),
               "--sequence", "0005", "--frames", "0:6", "--out", str(out)])
    assert rc == 0
    pngs = sorted((out / "disparity").glob("*.png"))
    assert [p.name for p in pngs] == [f"{i:06d}.png" for i in range(6)]
    d = read_disparity_png(pngs[0])
    assert d.shape == (375, 1242) and np.isfinite(d).mean() > 0.7
    poses = read_poses(out / "poses.txt")
    assert poses.shape == (6, 4, 4)
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-12)
    # The car drives forward in 0005: compare with the ORB-SLAM3 estimate.
    slam = read_poses(kitti_tracking_root / "training" / "egoposes_orbslam3" / "0005.txt")[:6]
    assert odometry_errors(poses, slam, min_frames=5).translation_pct < 3.0
    q = json.loads((out / "quality.json").read_text())
    assert [f["frame"] for f in q["frames"]] == list(range(6))
    assert q["frames"][0]["egomotion"] is None and all(f["egomotion"]["ok"] for f in q["frames"][1:])
    assert q["error"] is None and q["egomotion_failures"] == 0
    assert not list(out.rglob(".*.tmp*")), "temporary files left behind"


def test_inspect_geometry_bad_frame_keeps_earlier_output(kitti_tracking_root, tmp_path, capsys):
    src = kitti_tracking_root / "training"
    root = tmp_path / "kitti" / "training"
    for cam in ("image_02", "image_03"):
        (root / cam / "0005").mkdir(parents=True)
        for i in range(4):
            shutil.copy(src / cam / "0005" / f"{i:06d}.png", root / cam / "0005")
    (root / "calib").mkdir()
    shutil.copy(src / "calib" / "0005.txt", root / "calib")
    bad = root / "image_02" / "0005" / "000002.png"
    bad.write_bytes(bad.read_bytes()[:5000])  # truncated mid-file

    out = tmp_path / "out"
    rc = main(["inspect", "geometry", "--dataset", "kitti", "--root", str(tmp_path / "kitti"),
               "--sequence", "0005", "--out", str(out)])
    assert rc == 2
    err = capsys.readouterr().err
    assert "000002.png" in err and "frame 2" in err
    # Frames before the bad one stay written, and the quality file records the error.
    assert sorted(p.name for p in (out / "disparity").glob("*.png")) == ["000000.png", "000001.png"]
    q = json.loads((out / "quality.json").read_text())
    assert len(q["frames"]) == 2 and "000002.png" in q["error"]
    assert read_poses(out / "poses.txt").shape == (2, 4, 4)
