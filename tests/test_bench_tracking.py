"""``mine bench tracking`` on one real KITTI sequence: detections-only tubes against the
2D-IoU baseline, both scored by the KITTI MOT protocol on the real labels."""

from __future__ import annotations

import pytest

from mining.bench.iou_tracker import iou_track
from mining.bench.tracking import run_tracking_bench
from mining.config import load_config
from mining.formats.poses import read_poses
from mining.proposals.precomputed import KittiDetections
from mining.sources.kitti import KittiTrackingSource

from conftest import REPO


def test_iou_baseline_links_real_detections(kitti_tracking_root):
    train = kitti_tracking_root / "training"
    source = KittiTrackingSource(str(kitti_tracking_root))
    calib = source.calib("0005")
    dets = KittiDetections(train / "det_pointrcnn", "0005", source.kitti_calib("0005"), (calib.width, calib.height),
                           load_config().proposals.kitti_detections)
    n = len(read_poses(train / "egoposes_orbslam3" / "0005.txt"))
    rows = iou_track(dets, n)
    ids, frames = rows.track_id, rows.frame
    assert len(ids) > 100 and frames.max() < n
    for tid in set(ids.tolist()):  # a track holds one box per frame
        f = frames[ids == tid]
        assert len(set(f.tolist())) == len(f)
    assert len(set(ids.tolist())) < 0.5 * len(ids), "boxes are linked into tracks"


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_tracking_bench_reports_what_an_independent_evaluation_gives(shared_data, tmp_path, capsys):
    """The bench's rows for 0005 equal our tracker's and the baseline's results written here
    and scored by the KITTI MOT evaluation on the real labels."""
    from mining.bench.iou_tracker import write_iou_tracks
    from mining.eval.kitti_mot import evaluate_kitti_mot
    from mining.pipeline.detections import track_detections

    train = shared_data / "kitti_tracking" / "training"
    cfg = load_config(REPO / "jobs" / "kitti-detections.toml", [f'source.root="{shared_data / "kitti_tracking"}"'])
    code = run_tracking_bench(shared_data, cfg, ["0005"])
    shown = {tuple(line.split()[:-6]): [float(x) for x in line.split()[-6:]]
             for line in capsys.readouterr().out.splitlines() if line.startswith("  tubes") or line.startswith("  2D")}
    track_detections(shared_data / "kitti_tracking", "0005", train / "det_pointrcnn",
                     train / "egoposes_orbslam3" / "0005.txt", cfg, tmp_path / "ours" / "0005.txt")
    source = KittiTrackingSource(str(shared_data / "kitti_tracking"))
    calib = source.calib("0005")
    dets = KittiDetections(train / "det_pointrcnn", "0005", source.kitti_calib("0005"), (calib.width, calib.height),
                           cfg.proposals.kitti_detections)
    write_iou_tracks(tmp_path / "iou" / "0005.txt", iou_track(dets, len(read_poses(train / "egoposes_orbslam3" / "0005.txt"))))
    seqmap = train / "seqmaps" / "train.seqmap"
    for name, folder in ((("tubes", "(ours)"), "ours"), (("2D-IoU", "Hungarian"), "iou")):
        car = evaluate_kitti_mot(train / "label_02", tmp_path / folder, ["0005"], seqmap=seqmap)["Car"]
        assert shown[(*name, "Car")][:2] == [round(100 * car["HOTA"], 1), round(100 * car["MOTA"], 1)]
        assert shown[(*name, "Car")][3] == car["IDSW"]
    ours, base = shown[("tubes", "(ours)", "Car")][0], shown[("2D-IoU", "Hungarian", "Car")][0]
    assert ours > base  # on 0005 (our reference sequence) the tubes beat the baseline on cars ...
    assert code == 1  # ... but 0005 has no pedestrians, so "better on both classes" does not hold
