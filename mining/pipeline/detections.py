"""Detections-only mode: tubes → score → select on 3D detections and given egoposes.

No images: each detection is a box-shaped mask with a 3D box (e.g. PointRCNN on KITTI),
and the camera poses come from a file (e.g. ORB-SLAM3). Mask prediction warps the
box at the object's depth. Writes KITTI tracking txt.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from mining.catalog import safe_files
from mining.checks import input_folder, output_folder
from mining.config import JobConfig
from mining.errors import InputError
from mining.formats.poses import read_poses
from mining.localise.localise import geometric_filter, localise_detections
from mining.pipeline.arguments import add_job_options, add_overwrite_option, job_config
from mining.pipeline.kitti_export import write_tubes_kitti
from mining.pipeline.mine import mine_tubes
from mining.proposals.precomputed import KittiDetections
from mining.sources.kitti import KittiTrackingSource
from mining.types import GroundPlane, MinedTube, TrackingFrame

FRAME_INTERVAL_NS = 100_000_000  # KITTI tracking is recorded at 10 Hz
# The evidence's name for the unary (mining.pipeline.mine.unary): 3D detections are not the job's image
# proposer, and no calibrated weights exist for them, so score.model "auto" scores them by the REFERENCE.
DETECTIONS = "detections"


def detection_frames(kitti_root: str | Path, sequence: str, detections: str | Path, poses_path: str | Path,
                     cfg: JobConfig) -> Iterator[TrackingFrame]:
    source = KittiTrackingSource(str(kitti_root))
    kcalib = source.kitti_calib(sequence)
    calib = source.calib(sequence)
    dets = KittiDetections(detections, sequence, kcalib, (calib.width, calib.height), cfg.proposals.kitti_detections)
    poses0 = read_poses(poses_path)
    if not np.isfinite(poses0).all():
        raise InputError("egoposes contain non-finite values", poses_path)
    poses = kcalib.camera2_poses(poses0)
    no_ground = GroundPlane(None, 0.0, 0, False, "detections-only mode: no images")
    for index, pose in enumerate(poses):
        t_ns = index * FRAME_INTERVAL_NS
        props = dets(index)
        obs = localise_detections(props, calib, t_ns, cfg.localise)
        obs = obs.take(geometric_filter(obs, no_ground, cfg.localise.filters, stereo_noise=False))  # LiDAR boxes
        yield TrackingFrame(index=index, t_ns=t_ns, calib=calib, pose=pose, segment=0, observations=obs, depth=None)


def track_detections(kitti_root: str | Path, sequence: str, detections: str | Path, poses_path: str | Path,
                     cfg: JobConfig, out_txt: str | Path | None = None, overwrite: bool = False) -> list[MinedTube]:
    mined = mine_tubes(detection_frames(kitti_root, sequence, detections, poses_path, cfg), cfg, proposer=DETECTIONS)
    if out_txt is not None:
        write_detection_tubes(kitti_root, sequence, mined, cfg, out_txt, overwrite)
    return mined


def write_detection_tubes(kitti_root: str | Path, sequence: str, mined: list[MinedTube], cfg: JobConfig,
                          out_txt: str | Path, overwrite: bool = False) -> None:
    """A sequence's mined tubes as KITTI tracking txt (3D fields in rectified camera 0); an
    existing file is replaced only with ``overwrite``."""
    kcalib = KittiTrackingSource(str(kitti_root)).kitti_calib(sequence)
    write_tubes_kitti(out_txt, mined, rect0_from_cam2=kcalib.cam2_to_rect0, observed_only=cfg.export.observed_only,
                      overwrite=overwrite)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine track detections``' options."""
    add_job_options(p)
    p.add_argument("--sequences", nargs="+", required=True)
    p.add_argument("--detections", type=input_folder, help="PointRCNN folder (<Class>/<seq>.txt) or result-format "
                                                            "folder; default <root>/training/det_pointrcnn")
    p.add_argument("--poses", type=input_folder,
                   help="folder of <seq>.txt camera-to-world poses; default <root>/training/egoposes_orbslam3")
    p.add_argument("--out", type=output_folder, required=True, help="folder of the <sequence>.txt results")
    add_overwrite_option(p, "OUT/<sequence>.txt")


def run(args: argparse.Namespace) -> int:
    """``mine track detections``: writes OUT/<sequence>.txt per sequence, a line each."""
    cfg = job_config(args)
    root = Path(args.root or cfg.source.root)
    split = root / "training" if (root / "training").is_dir() else root
    detections = Path(args.detections) if args.detections else split / "det_pointrcnn"
    poses = Path(args.poses) if args.poses else split / "egoposes_orbslam3"
    out = Path(args.out)
    for seq in args.sequences:  # before any work: every result file may be written
        safe_files.check_output_file(out / f"{seq}.txt", args.overwrite, "--out")
    for seq in args.sequences:
        mined = track_detections(root, seq, detections, poses / f"{seq}.txt", cfg, out / f"{seq}.txt", args.overwrite)
        sel = [m for m in mined if m.selected]
        print(f"{seq}: {len(mined)} tubes, {len(sel)} selected → {out / f'{seq}.txt'}")
    return 0
