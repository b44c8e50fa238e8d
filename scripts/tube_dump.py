"""Dump every tube of fixed real and synthetic runs, to show that a change keeps behaviour.

    python scripts/tube_dump.py OUT_DIR [--cases NAME ...] [--data ../shared/data]
    python scripts/tube_dump.py --compare DIR_A DIR_B

Each case writes ``OUT_DIR/<case>.jsonl``: one line per tube (id, segment, score terms,
category, selection, and every frame with its mask, box, state and likelihood terms,
floats written exactly), and ``OUT_DIR/SHA256SUMS``. Two dumps are identical when their
sums are; ``--compare`` names the first differing tube of each case that differs.

Cases (real data from ../shared/data; the ONNX model from ../shared/models):

* ``kitti0005-json20``, ``kitti0005-json500``: KITTI tracking 0005 frames 0-15, the image
  pipeline on the shared 4D-GVT mask proposals (top 20; top 500 with the cap at 500);
* ``kitti0005-onnx``: the same frames with the shared YOLO-seg ONNX model;
* ``detections``: detections-only mode on the twelve KITTI training sequences
  (``jobs/kitti-detections.toml``: PointRCNN + ORB-SLAM3 egoposes);
* ``synthetic0000``: synthetic sequence 0000, 200 frames, the default (stereo) proposer;
* ``sharded0000``: the same 200 frames mined as a job in 100-frame windows (in-process
  executor), the stitched catalogue's tubes and tube frames.

The script runs against the layout before the refactor of issue 8 too (it imports what it
finds), so a dump made at an older commit compares with one made now.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

CASES = ("kitti0005-json20", "kitti0005-json500", "kitti0005-onnx", "detections", "synthetic0000", "sharded0000")


def _api():
    """(frames(source, plan, start, stop, cfg) → TrackingFrames, mine_tubes, detection_frames,
    run_job(cfg, out) → Summary, in this process)."""
    from mining.pipeline.detections import detection_frames
    try:
        from mining.pipeline.executors import LocalExecutor
        from mining.pipeline.submit import mine_job  # after issue 8

        def run_job(cfg, out):
            return mine_job(cfg, out, executor=LocalExecutor)
    except ImportError:
        from mining.pipeline.submit import run_job as _run_job  # before

        def run_job(cfg, out):
            return _run_job(cfg, out, executor="local")
    try:
        from mining.pipeline.frames import frame_records  # after issue 8

        def frames(source, plan, start, stop, cfg):
            return (r.tracking for r in frame_records(source, plan, start, stop, cfg))
    except ImportError:
        from mining.pipeline.frames import tracking_frames  # before

        def frames(source, plan, start, stop, cfg):
            return (r.tracking for r in tracking_frames(source, plan, start, stop, cfg))
    from mining.pipeline.mine import mine_tubes
    return frames, mine_tubes, detection_frames, run_job


def _num(x):
    if x is None:
        return None
    if isinstance(x, dict):  # an RLE
        counts = x["counts"]
        return {"size": list(x["size"]), "counts": counts.decode() if isinstance(counts, bytes) else counts}
    a = np.asarray(x)
    if a.dtype.kind in "fc" and a.ndim == 0:
        v = float(a)
        return "nan" if v != v else v
    if a.ndim == 0:
        return a.item()
    return [_num(v) for v in a.tolist()] if a.dtype.kind == "f" else a.tolist()


def tube_line(mt) -> str:
    t = mt.tube
    frames = [{k: _num(getattr(f, k)) for k in ("frame", "t_ns", "observed", "obs_index", "rle", "box",
                                               "footpoint_world", "velocity_world", "size", "position_cam",
                                               "objectness", "mask_iou", "motion_density", "posterior")}
              for f in t.frames]
    s, c = mt.score, mt.category
    return json.dumps({"tube_id": t.tube_id, "segment": t.segment, "end_reason": t.end_reason,
                       "score": [_num(s.motion), _num(s.mask), _num(s.objectness), _num(s.total)],
                       "category": [c.category, _num(c.probability), c.known, c.best_known, _num(c.posterior)],
                       "selected": bool(mt.selected), "frames": frames}, sort_keys=True)


def _filters_key() -> str:
    """Where the proposal filter's settings live: ``localise.filters`` since issue 27, ``proposals.filters`` before."""
    from mining.config import JobConfig

    return "localise.filters" if hasattr(JobConfig().localise, "filters") else "proposals.filters"


def _kitti(data: Path, overrides: list[str]):
    from mining.config import load_config
    from mining.sources import open_source

    cfg = load_config(str(REPO / "jobs" / "kitti.toml"), [f'source.root="{data / "kitti_tracking"}"', *overrides])
    return cfg, open_source("kitti", cfg.source.root)


def run_case(name: str, data: Path, models: Path) -> list[str]:
    frames, mine_tubes, detection_frames, run_job = _api()
    from mining.config import load_config
    from mining.sources import open_source

    if name.startswith("kitti0005"):
        props = data / "proposals_4dgvt_format" / "kitti_tracking_0005"
        over = {"kitti0005-json20": [f'proposals.proposer="json"', f'proposals.json.folder="{props / "top20"}"'],
                "kitti0005-json500": [f'proposals.proposer="json"', f'proposals.json.folder="{props / "top500"}"',
                                      f"{_filters_key()}.max_proposals=500"],
                "kitti0005-onnx": [f'proposals.proposer="onnx"',
                                   f'proposals.onnx.model_path="{models / "yolov8n-seg_int8.onnx"}"']}[name]
        cfg, source = _kitti(data, over)
        plan = source.plan("0005")
        return [tube_line(m) for m in mine_tubes(frames(source, plan, 0, 16, cfg), cfg)]
    if name == "detections":
        try:
            from mining.formats.kitti_tracking import read_seqmap  # after issue 27
        except ImportError:
            from mining.eval.kitti_mot import read_seqmap  # before

        train = data / "kitti_tracking" / "training"
        cfg = load_config(str(REPO / "jobs" / "kitti-detections.toml"), [f'source.root="{data / "kitti_tracking"}"'])
        lines = []
        for seq in read_seqmap(train / "seqmaps" / "train.seqmap"):
            fr = detection_frames(data / "kitti_tracking", seq, train / "det_pointrcnn",
                                  train / "egoposes_orbslam3" / f"{seq}.txt", cfg)
            lines += [json.dumps({"sequence": seq}) + "\t" + tube_line(m) for m in mine_tubes(fr, cfg)]
        return lines
    if name == "synthetic0000":
        cfg = load_config(str(REPO / "jobs" / "synthetic.toml"), ["source.options.n_frames=200"])
        source = open_source("synthetic", None, **cfg.source.options)
        plan = source.plan("0000")
        return [tube_line(m) for m in mine_tubes(frames(source, plan, 0, 200, cfg), cfg)]
    if name == "sharded0000":
        import pyarrow.parquet as pq

        cfg = load_config(str(REPO / "jobs" / "synthetic.toml"), ["source.options.n_frames=200"])
        with tempfile.TemporaryDirectory() as tmp:
            summary = run_job(cfg, tmp)
            assert not summary.failed and not getattr(summary, "stitch_failed", None), summary.lines()
            lines = []
            for table in ("tubes", "tube_frames", "frames"):
                t = pq.read_table(Path(tmp) / "catalog" / table)
                drop = [c for c in ("run_id", "params_hash", "dataset", "sequence") if c in t.column_names]
                t = t.drop_columns(drop)
                keys = [k for k in ("tube_id", "frame") if k in t.column_names]
                t = t.sort_by([(k, "ascending") for k in keys])
                lines += [json.dumps({"table": table, **{k: _num(v) if isinstance(v, float) else v
                                                         for k, v in row.items()}}, sort_keys=True, default=str)
                          for row in t.to_pylist()]
        return lines
    raise SystemExit(f"unknown case {name!r}; known: {CASES}")


def compare(a: Path, b: Path) -> int:
    bad = 0
    for case in CASES:
        fa, fb = a / f"{case}.jsonl", b / f"{case}.jsonl"
        if not (fa.exists() and fb.exists()):
            print(f"{case}: missing in {'A' if not fa.exists() else 'B'}")
            continue
        la, lb = fa.read_text().splitlines(), fb.read_text().splitlines()
        if la == lb:
            print(f"{case}: identical ({len(la)} lines)")
            continue
        bad += 1
        i = next((i for i, (x, y) in enumerate(zip(la, lb)) if x != y), min(len(la), len(lb)))
        print(f"{case}: DIFFERENT ({len(la)} vs {len(lb)} lines; first difference at line {i + 1})")
        if i < min(len(la), len(lb)):
            print(f"  A: {la[i][:400]}\n  B: {lb[i][:400]}")
    return 1 if bad else 0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", nargs="?")
    p.add_argument("--cases", nargs="+", default=list(CASES))
    p.add_argument("--data", default=str(REPO.parent / "shared" / "data"))
    p.add_argument("--models", default=str(REPO.parent / "shared" / "models"))
    p.add_argument("--compare", nargs=2, metavar=("A", "B"))
    args = p.parse_args()
    if args.compare:
        return compare(Path(args.compare[0]), Path(args.compare[1]))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for case in args.cases:
        lines = run_case(case, Path(args.data), Path(args.models))
        text = "\n".join(lines) + "\n"
        (out / f"{case}.jsonl").write_text(text)
        print(f"{case}: {len(lines)} lines, sha256 {hashlib.sha256(text.encode()).hexdigest()[:16]}", flush=True)
    sums = [f"{hashlib.sha256((out / f'{c}.jsonl').read_bytes()).hexdigest()}  {c}.jsonl"
            for c in CASES if (out / f"{c}.jsonl").exists()]
    (out / "SHA256SUMS").write_text("\n".join(sums) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
