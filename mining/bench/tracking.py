"""``mine bench tracking``: detections-only tubes against a 2D-IoU baseline on KITTI.

Both trackers get the same PointRCNN detections; ours also the ORB-SLAM3 egoposes. Both
are scored by the KITTI MOT protocol (Car, Pedestrian) on the training sequences, whose
labels are the only ones in ../shared/data. The AB3DMOT row is the reference the issue
gives (TrackEval's KITTI 2D-box evaluation of AB3DMOT on these detections and poses).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from mining.bench.iou_tracker import iou_track, write_iou_tracks
from mining.config import JobConfig
from mining.eval.kitti_mot import evaluate_kitti_mot
from mining.formats.kitti_tracking import read_seqmap
from mining.formats.poses import read_poses
from mining.pipeline.arguments import add_data_option, add_job_options, job_config
from mining.pipeline.detections import track_detections
from mining.proposals.precomputed import KittiDetections
from mining.sources.kitti import KittiTrackingSource

AB3DMOT = {"Car": {"HOTA": 0.733, "MOTA": 0.813, "IDSW": 39},
           "Pedestrian": {"HOTA": 0.458, "MOTA": 0.606, "IDSW": 72}}  # the reference figures


def run_tracking_bench(data: Path, cfg: JobConfig, sequences: list[str] | None = None) -> int:
    train = data / "kitti_tracking" / "training"
    seqmap = train / "seqmaps" / "train.seqmap"
    sequences = sequences or list(read_seqmap(seqmap))
    source = KittiTrackingSource(str(data / "kitti_tracking"))
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        ours, base = Path(tmp) / "ours", Path(tmp) / "iou"
        t0 = time.perf_counter()
        for seq in sequences:
            track_detections(data / "kitti_tracking", seq, train / "det_pointrcnn",
                             train / "egoposes_orbslam3" / f"{seq}.txt", cfg, ours / f"{seq}.txt")
        t_ours = time.perf_counter() - t0
        for seq in sequences:
            calib = source.calib(seq)
            dets = KittiDetections(train / "det_pointrcnn", seq, source.kitti_calib(seq), (calib.width, calib.height),
                                   cfg.proposals.kitti_detections)
            n = len(read_poses(train / "egoposes_orbslam3" / f"{seq}.txt"))
            write_iou_tracks(base / f"{seq}.txt", iou_track(dets, n))
        rows["tubes (ours)"] = evaluate_kitti_mot(train / "label_02", ours, sequences, seqmap=seqmap)
        rows["2D-IoU Hungarian"] = evaluate_kitti_mot(train / "label_02", base, sequences, seqmap=seqmap)
    print(f"KITTI MOT on {len(sequences)} training sequences (PointRCNN detections; ours with ORB-SLAM3 poses)")
    print(f"  {'tracker':<18} {'class':<11} {'HOTA':>6} {'MOTA':>6} {'IDF1':>6} {'IDSW':>5} {'FP':>6} {'FN':>6}")
    for name, r in rows.items():
        for cls in ("Car", "Pedestrian"):
            m = r[cls]
            print(f"  {name:<18} {cls:<11} {100 * m['HOTA']:6.1f} {100 * m['MOTA']:6.1f} {100 * m['IDF1']:6.1f} "
                  f"{m['IDSW']:5.0f} {m['FP']:6.0f} {m['FN']:6.0f}")
    for cls, m in AB3DMOT.items():
        print(f"  {'AB3DMOT (ref.)':<18} {cls:<11} {100 * m['HOTA']:6.1f} {100 * m['MOTA']:6.1f} {'':>6} {m['IDSW']:5d}")
    print(f"  (ours: {t_ours:.0f} s for {len(sequences)} sequences)")
    ok = all(rows["tubes (ours)"][c]["HOTA"] > rows["2D-IoU Hungarian"][c]["HOTA"] for c in ("Car", "Pedestrian"))
    return 0 if ok else 1


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine bench tracking``'s options."""
    add_job_options(p)
    add_data_option(p)
    p.add_argument("--sequences", nargs="+", default=None, help="default: the twelve training sequences")


def run(args: argparse.Namespace) -> int:
    """``mine bench tracking``: 0 when the tubes beat the baseline's HOTA for cars and pedestrians."""
    return run_tracking_bench(Path(args.data), job_config(args), args.sequences)
