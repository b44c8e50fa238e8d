"""The ``mine`` command line."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from mining.config import JobConfig, load_config, parse_override, validate
from mining.errors import ConfigError, MiningError, NothingMatched
from mining.names import check_name
from mining.proposals.make import classifiers_line
from mining.score.unary import unary_line


INTERRUPTED = 130  # the shell's exit status for a process ended by SIGINT (128 + 2)
NOTHING_MATCHED = 1  # a predicate matched nothing and nothing was written (grep's "no match")


def _frames(text: str) -> tuple[int, int | None]:
    """``a:b`` → (a, b); ``a:`` → (a, None); ``a`` → (a, a + 1). An empty range is an error."""
    try:
        if ":" not in text:
            a = int(text)
            frames = a, a + 1
        else:
            a, b = text.split(":", 1)
            frames = int(a or 0), (int(b) if b else None)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expects A:B, got {text!r}") from None
    from mining.pipeline.preflight import check_frames

    try:
        check_frames(frames)
    except ConfigError as e:
        raise argparse.ArgumentTypeError(str(e).removeprefix("--frames ")) from None
    return frames


def _add_job_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dataset", help="kitti, kitti-raw, oxford, mcap or synthetic (default: the config's)")
    p.add_argument("--root", help="dataset root folder")
    p.add_argument("--config", help="job config TOML (e.g. jobs/kitti.toml)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value, e.g. geometry.stereo.num_disparities=96")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="source option, e.g. pair=narrow (oxford) or n_frames=2000 (synthetic)")


def _job_config(args: argparse.Namespace) -> JobConfig:
    overrides = list(args.set)
    if args.dataset:
        overrides.append(f"source.dataset={args.dataset!r}".replace("'", '"'))
    if args.root:
        overrides.append(f'source.root="{Path(args.root).as_posix()}"')
    if getattr(args, "host", None):
        overrides.append(f"run.bind_host={args.host!r}".replace("'", '"'))
    cfg = load_config(args.config, overrides)
    for o in args.option:
        for k, v in parse_override(o).items():
            cfg.source.options[k] = v
    validate(cfg)  # the options too: an unknown key or a wrong type fails here, naming it
    return cfg


def cmd_inspect_geometry(args: argparse.Namespace) -> int:
    from mining.pipeline.inspect_geometry import inspect_geometry

    cfg = _job_config(args)
    source = cfg.source.open()
    start, stop = args.frames
    summary = inspect_geometry(source, args.sequence, start, stop, cfg.geometry, args.out)
    n = len(summary["frames"])
    fails = summary["egomotion_failures"]
    print(f"{n} frames of {summary['dataset']}/{summary['sequence']} → {args.out}: "
          f"disparity/*.png, poses.txt, quality.json; egomotion failures: {fails}")
    return 0


def cmd_bench_geometry(args: argparse.Namespace) -> int:
    from mining.bench.geometry import run_geometry_bench

    cfg = _job_config(args)
    return run_geometry_bench(Path(args.data), cfg.geometry, synthetic_frames=args.synthetic_frames,
                              json_out=args.json)


def cmd_track_detections(args: argparse.Namespace) -> int:
    from mining.pipeline.detections import track_detections

    cfg = _job_config(args)
    root = Path(args.root or cfg.source.root)
    split = root / "training" if (root / "training").is_dir() else root
    detections = Path(args.detections) if args.detections else split / "det_pointrcnn"
    poses = Path(args.poses) if args.poses else split / "egoposes_orbslam3"
    out = Path(args.out)
    for seq in args.sequences:
        mined = track_detections(root, seq, detections, poses / f"{seq}.txt", cfg, out / f"{seq}.txt")
        sel = [m for m in mined if m.selected]
        print(f"{seq}: {len(mined)} tubes, {len(sel)} selected → {out / f'{seq}.txt'}")
    return 0


def cmd_track_images(args: argparse.Namespace) -> int:
    from mining.pipeline.frames import frame_records
    from mining.pipeline.kitti_export import write_tubes_kitti
    from mining.pipeline.mine import mine_tubes
    from mining.pipeline.preflight import checked_plan

    cfg = _job_config(args)
    source = cfg.source.open()
    plan = checked_plan(source, cfg, args.sequence, args.frames)
    start, stop = args.frames
    stop = len(plan) if stop is None else min(stop, len(plan))
    mined = mine_tubes((r.tracking for r in frame_records(source, plan, start, stop, cfg)), cfg)
    out = Path(args.out) / f"{args.sequence}.txt"
    # KITTI's 3D fields are in rectified camera 0; elsewhere they are placeholders.
    to_rect0 = source.kitti_calib(args.sequence).cam2_to_rect0 if cfg.source.dataset == "kitti" else None
    n = write_tubes_kitti(out, mined, to_rect0, observed_only=cfg.export.observed_only,
                          unclassified_as=cfg.export.unclassified_as)
    sel = [m for m in mined if m.selected]
    known = sum(m.category.known is True for m in sel)
    unknown = sum(m.category.known is False for m in sel)
    print(f"{args.sequence} frames {start}:{stop}: {len(mined)} tubes, {len(sel)} selected "
          f"({known} known, {unknown} unknown, {len(sel) - known - unknown} unclassified), {n} rows → {out}")
    print(classifiers_line(cfg.proposals.proposer))
    print(unary_line(cfg.score, cfg.proposals.proposer))
    return 0


def cmd_eval_kitti_mot(args: argparse.Namespace) -> int:
    import tempfile

    from mining.eval.kitti_mot import evaluate_kitti_mot, format_table

    gt: Path | dict[str, Path] = Path(args.gt)
    with tempfile.TemporaryDirectory() as tmp:
        seqmap = args.seqmap
        if args.frames is not None:  # evaluate the first N frames only
            gt_files, lines = {}, []
            for seq in args.sequences:
                rows = [ln for ln in (Path(args.gt) / f"{seq}.txt").read_text().splitlines()
                        if ln.strip() and int(ln.split()[0]) < args.frames]
                gt_files[seq] = Path(tmp) / f"{seq}.txt"
                gt_files[seq].write_text("\n".join(rows) + "\n")
                lines.append(f"{seq} empty 000000 {args.frames:06d}")
            seqmap = Path(tmp) / "seqmap"
            seqmap.write_text("\n".join(lines) + "\n")
            gt = gt_files
        results = evaluate_kitti_mot(gt, args.results, args.sequences, tuple(args.classes), seqmap)
    print(format_table(results, per_sequence=args.per_sequence))
    return 0


def _format_recall(r: dict) -> str:
    ns = sorted(r["all"])
    lines = [f"  {'objects':<8} {'count':>6} " + " ".join(f"{'@' + str(n):>6}" for n in ns)]
    for name in ("known", "unknown", "all"):
        lines.append(f"  {name:<8} {r['n_' + name]:>6} " + " ".join(f"{r[name][n]:6.3f}" for n in ns))
    return "\n".join(lines)


def cmd_eval_recall(args: argparse.Namespace) -> int:
    from mining.eval.recall import kitti_ground_truth, recall_at_n

    if args.oxford_labels:
        from mining.formats.oxford_labels import read_oxford_labels
        from mining.proposals.precomputed import read_proposal_json

        labels = read_oxford_labels(args.oxford_labels)
        props, boxes, known = [], [], []
        for lf in labels:
            rel = lf.path.relative_to(lf.path.parents[1])
            props.append(read_proposal_json(Path(args.proposals_json) / rel, lf.frame))
            boxes.append(lf.boxes)
            known.append(lf.known)
        print(f"Proposal recall (box IoU > 0.5) on {len(labels)} labelled RobotCar frames")
        print(_format_recall(recall_at_n(props, boxes, known)))
        return 0
    from mining.formats.kitti_tracking import read_kitti_tracking
    from mining.pipeline.frames import frame_records
    from mining.pipeline.preflight import checked_plan

    cfg = _job_config(args)
    source = cfg.source.open()
    plan = checked_plan(source, cfg, args.sequence, args.frames)
    start, stop = args.frames
    stop = len(plan) if stop is None else min(stop, len(plan))
    labels = Path(args.labels) if args.labels else Path(cfg.source.root) / "training" / "label_02" / f"{args.sequence}.txt"
    rows = read_kitti_tracking(labels)
    funnel = None
    if args.funnel:
        from mining.bench.funnel import run_kitti_funnel
        from mining.eval.funnel import format_funnel

        props, frames, _, funnel = run_kitti_funnel(source, plan, start, stop, cfg, rows)
    else:
        props, frames = [], []
        for rec in frame_records(source, plan, start, stop, cfg):
            props.append(rec.proposals)
            frames.append(rec.frame.index)
    boxes, known = kitti_ground_truth(rows, frames)
    recall = recall_at_n(props, boxes, known)
    print(f"Proposal recall (box IoU > 0.5), {cfg.proposals.proposer} proposer, {args.sequence} frames {start}:{stop}")
    print(_format_recall(recall))
    if funnel is not None:
        print(format_funnel(funnel))
    if args.json:
        import json

        doc = {"sequence": args.sequence, "frames": [start, stop], "proposer": cfg.proposals.proposer,
               "recall_at_n": recall} | ({"funnel": funnel} if funnel is not None else {})
        Path(args.json).write_text(json.dumps(doc, indent=1))
    return 0


def cmd_eval_synthetic(args: argparse.Namespace) -> int:
    from mining.bench.synthetic import run_synthetic_eval

    protocol = {"max_depth_m": args.max_depth_m}
    if args.min_visible_px is not None:
        protocol["min_visible_px"] = args.min_visible_px
    return run_synthetic_eval(args.sequence, args.n_frames, load_config(args.config, args.set), json_out=args.json,
                              **protocol)


def cmd_bench_tubes(args: argparse.Namespace) -> int:
    from mining.bench.tubes import run_tubes_bench

    return run_tubes_bench(Path(args.data), _job_config(args), repeats=args.repeats)


def cmd_bench_range(args: argparse.Namespace) -> int:
    from mining.bench.range import run_range_bench

    return run_range_bench(Path(args.data), _job_config(args), args.sources, kitti_frames=args.kitti_frames,
                           synthetic_sequence=args.synthetic_sequence, synthetic_n_frames=args.synthetic_n_frames,
                           synthetic_frames=args.synthetic_frames, verbose=args.verbose)


def cmd_bench_tracking(args: argparse.Namespace) -> int:
    from mining.bench.tracking import run_tracking_bench

    return run_tracking_bench(Path(args.data), _job_config(args), args.sequences)


def cmd_bench_scenarios(args: argparse.Namespace) -> int:
    from mining.bench.scenarios import run_scenarios_bench

    return run_scenarios_bench(_job_config(args), args.scenarios, args.frames, args.sequence, args.half, args.json)


def cmd_bench_crossval(args: argparse.Namespace) -> int:
    from mining.bench.crossval import parse_grid, run_crossval_bench

    return run_crossval_bench(Path(args.data), args.config, args.set, k=args.folds,
                              grid=parse_grid(args.grid) if args.grid else None, sequences=args.sequences,
                              json_out=args.json)


def cmd_bench_crossval_scenarios(args: argparse.Namespace) -> int:
    from mining.bench.crossval import parse_grid
    from mining.bench.crossval_scenarios import run_crossval_scenarios

    return run_crossval_scenarios(args.config, args.set, grid=parse_grid(args.grid) if args.grid else None,
                                  seeds=args.seeds, names=args.scenarios, n_frames=args.frames, half=not args.full,
                                  json_out=args.json)


def cmd_bench_classify(args: argparse.Namespace) -> int:
    from mining.bench.classify import run_classify_bench

    return run_classify_bench(Path(args.data), _job_config(args), train_seeds=args.train_seeds, test_seed=args.test_seed,
                              n_frames=args.frames, train_frames=args.train_frames, json_out=args.json)


def cmd_bench_calibrate(args: argparse.Namespace) -> int:
    from mining.bench.calibrate import run_calibrate_bench

    return run_calibrate_bench(_job_config(args), args.seeds, args.frames, workers=args.workers, l2=args.l2,
                               epsilon1=args.epsilon1, epsilon2=args.epsilon2, balance=not args.no_balance,
                               json_out=args.json)


def cmd_bench_proposals(args: argparse.Namespace) -> int:
    from mining.bench.proposals import run_proposals_bench

    return run_proposals_bench(Path(args.data), _job_config(args), frames=args.frames,
                               random_weights=args.random_weights, json_path=args.json)


def cmd_bench_looks(args: argparse.Namespace) -> int:
    from mining.bench.looks import run_looks_bench

    return run_looks_bench(Path(args.data), _job_config(args), args.model, args.seeds, frames=args.frames,
                           step=args.step, n_frames=args.n_frames, png_dir=args.png, json_out=args.json,
                           kitti=not args.no_kitti)


def cmd_bench_pipeline(args: argparse.Namespace) -> int:
    from mining.bench.pipeline import run_pipeline_bench

    return run_pipeline_bench(_job_config(args), frames=args.frames, sequences=args.sequences, long=args.long,
                              long_frames=args.long_frames, catalog_rows=args.catalog_rows, workdir=args.dir,
                              json_out=args.json)


def cmd_submit(args: argparse.Namespace) -> int:
    cfg = _job_config(args)
    if args.new_run and args.extend:
        raise ConfigError("--new-run and --extend exclude each other")
    if args.address and args.address.startswith("http"):
        from mining.pipeline.rayjobs import submit_ray_job

        return submit_ray_job(args.address, args.argv, args.out, wait=not args.no_wait)
    if args.no_wait:
        raise ConfigError("--no-wait needs --address http://HEAD:8265 (a job handed to a cluster through Ray Jobs)")
    from mining.pipeline.submit import mine_on_ray

    mode = "new" if args.new_run else "extend" if args.extend else "resume"
    summary = mine_on_ray(cfg, args.out, args.sequences, args.frames, address=args.address, workers=args.workers,
                          progress=not args.no_progress, mode=mode, verify=args.verify, lock_wait=args.lock_wait)
    for line in summary.lines():
        print(line)
    return 1 if summary.failed or summary.unplanned else 0


def cmd_status(args: argparse.Namespace) -> int:
    if args.address:
        from mining.pipeline.rayjobs import ray_jobs_status

        return ray_jobs_status(args.address, args.job)
    if args.job:
        raise ConfigError("--job needs --address http://HEAD:8265")
    from mining.pipeline.status import print_status

    return print_status(args.out, verify=args.verify)


def cmd_query(args: argparse.Namespace) -> int:
    from mining.catalog.query import run_query

    limits = {k: v for k, v in (("memory_limit", args.memory_limit), ("threads", args.threads),
                                ("timeout_s", args.timeout), ("limit", args.limit)) if v is not None}  # unset: query.py's defaults
    return run_query(args.sql, args.out, args.format, args.output, **limits)


def cmd_export(args: argparse.Namespace) -> int:
    from mining.catalog.export import run_export

    return run_export(args.out, args.where, args.format, args.dest, args.margin, args.images, args.overwrite)


def cmd_render(args: argparse.Namespace) -> int:
    from mining.catalog.render import run_render

    return run_render(args.out, args.sequence, args.dest, args.where, args.depth, args.fps, args.frames,
                      overwrite=args.overwrite)


def _version_text() -> str:
    """The package version, and the catalogue schema it writes."""
    from mining import __version__
    from mining.catalog.schema import SCHEMA_VERSION

    return f"mine (tube-miner) {__version__}, catalogue schema v{SCHEMA_VERSION}"


def cmd_view(args: argparse.Namespace) -> int:
    from mining.view.server import run_view

    return run_view(args.out, args.host, args.port, args.cache, args.log)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mine", description="Tube Miner: mine generic object tubes from stereo video.")
    parser.add_argument("--version", action="version", version=_version_text())
    sub = parser.add_subparsers(dest="command", required=True)

    smt = sub.add_parser("submit", help="plan windows and mine them on Ray (local, or a cluster with --address)")
    _add_job_options(smt)
    smt.add_argument("--sequences", nargs="+", help="default: the config's, else every sequence the source finds")
    smt.add_argument("--frames", type=_frames, default=(0, None), metavar="A:B",
                     help="plan positions [A, B) of every sequence (default: all)")
    smt.add_argument("--out", default="out/catalog", help="catalogue folder or pyarrow filesystem URI")
    smt.add_argument("--address", help="http://HEAD:8265: hand the job to that cluster through Ray Jobs (--config, "
                                       "--root and --out are made absolute here and read on the cluster); "
                                       "HOST:PORT or auto: run the scheduler here, the work on that cluster; "
                                       "default: start a local Ray on this machine")
    smt.add_argument("--no-wait", action="store_true", help="with --address http://…: print the submission id and "
                                                            "return instead of following the job's logs")
    smt.add_argument("--workers", type=int, help="local Ray only: CPUs to use (default: all)")
    smt.add_argument("--host", metavar="IP", help="local Ray only: the interface every Ray port listens on (default: "
                                                  "the config's run.bind_host, 127.0.0.1). Ray's ports run code "
                                                  "unauthenticated: another interface only on a network you trust")
    smt.add_argument("--no-progress", action="store_true", help="no progress bar (logs and CI)")
    smt.add_argument("--extend", action="store_true",
                     help="--out holds this job with a narrower --frames or fewer --sequences: widen it (what differs "
                          "from a clean run of the new range is recomputed); anything else that differs is refused")
    smt.add_argument("--new-run", action="store_true",
                     help="--out holds another job, or catalogue data without a readable job.json: move it aside "
                          "(to OUT/_replaced/<run id>-<time>/, local folders only) and start a new one")
    smt.add_argument("--verify", action="store_true",
                     help="check every recorded checksum before resuming (default: sizes only); damaged files are "
                          "recomputed")
    smt.add_argument("--lock-wait", type=float, default=0.0, metavar="SECONDS",
                     help="another submit is writing --out: wait up to this long for it (default: refuse at once)")
    smt.set_defaults(func=cmd_submit)

    sts = sub.add_parser("status", help="windows done, failed (with the error) and pending")
    sts.add_argument("--out", default="out/catalog", help="catalogue folder or URI")
    sts.add_argument("--verify", action="store_true",
                     help="also check every file's sha256 against the manifest (reads the whole catalogue)")
    sts.add_argument("--address", help="http://HEAD:8265: the cluster's Tube Miner jobs through Ray Jobs instead")
    sts.add_argument("--job", help="with --address: one job's status and the end of its logs")
    sts.set_defaults(func=cmd_status)

    qry = sub.add_parser("query", help="read-only SQL (DuckDB) over the catalogue's tables and views")
    qry.add_argument("sql")
    qry.add_argument("--out", default="out/catalog", help="catalogue folder or URI")
    qry.add_argument("--format", choices=["table", "csv", "json", "parquet"], default="table")
    qry.add_argument("--output", help="write here instead of standard output (required for parquet)")
    qry.add_argument("--memory-limit", help="most memory the query may use, e.g. 4GB; beyond it DuckDB spills to "
                                            "a private temporary folder (default: query.MEMORY_LIMIT, 2GB)")
    qry.add_argument("--threads", type=int, help="threads the query may use (default: query.THREADS, 2)")
    qry.add_argument("--timeout", type=float, metavar="SECONDS",
                     help="stop the query after this many seconds (default: query.TIMEOUT_S, 60)")
    qry.add_argument("--limit", type=int, metavar="N",
                     help="table output shows at most N rows and the total count (default: query.LIMIT, 50; 0 = all)")
    qry.set_defaults(func=cmd_query)

    exp = sub.add_parser("export", help="tubes matching a SQL predicate, for other tools")
    exp.add_argument("dest", help="output folder")
    exp.add_argument("--where", default="selected", help="SQL predicate over the tubes table (default: selected)")
    exp.add_argument("--format", choices=["kitti", "kitti-mots", "crops", "youtube-vis", "tao"], required=True)
    exp.add_argument("--out", default="out/catalog", help="catalogue folder or URI")
    exp.add_argument("--overwrite", action="store_true",
                     help="DEST holds an earlier export: remove what that export recorded (DEST/.mine-export.json) "
                          "and write this one; other files in DEST are kept")
    exp.add_argument("--margin", type=float, default=None,
                     help="crops: context on each side, as a fraction of the box (default 0.15, at least 8 px)")
    exp.add_argument("--images", action="store_true",
                     help="youtube-vis, tao: also write the video frames (rectified left images, JPEG) the JSON names")
    exp.set_defaults(func=cmd_export)

    rnd = sub.add_parser("render", help="a sequence with its selected tubes drawn (mask, id, category), as a video")
    rnd.add_argument("dest", help="DEST.mp4 (H.264 with PyAV, the `video` extra; without it MPEG-4 Part 2, which "
                                  "browsers do not play) or DEST.webm (VP8); H.264 and VP8 play in browsers")
    rnd.add_argument("--out", default="out/catalog", help="catalogue folder")
    rnd.add_argument("--sequence", required=True)
    rnd.add_argument("--where", help="SQL predicate over the tubes table: draw only the selected tubes it matches")
    rnd.add_argument("--depth", action="store_true", help="add a stereo depth panel beside each frame")
    rnd.add_argument("--fps", type=float, help="frame rate (default: the sequence's, from its timestamps)")
    rnd.add_argument("--frames", type=_frames, default=None, metavar="A:B",
                     help="plan positions [A, B) (default: the frames the catalogue mined)")
    rnd.add_argument("--overwrite", action="store_true",
                     help="DEST exists: replace it (a plain file only; without this flag an existing DEST is refused)")
    rnd.set_defaults(func=cmd_render)

    viw = sub.add_parser("view", help="browse the catalogue in a web browser: a gallery of tubes, a page per tube")
    viw.add_argument("--out", default="out/catalog", help="catalogue folder")
    viw.add_argument("--port", type=int, default=8765, help="port to listen on (default 8765; 0 picks a free one)")
    viw.add_argument("--host", default="127.0.0.1",
                     help="address to listen on (default 127.0.0.1: this machine only; there is no login)")
    viw.add_argument("--cache", help="folder for rendered pictures (default: tube-miner/view in $XDG_CACHE_HOME or "
                                     "~/.cache, made 0700; refused when not yours alone; not inside the catalogue)")
    viw.add_argument("--log", action="store_true", help="log one line per request on standard error")
    viw.set_defaults(func=cmd_view)

    inspect = sub.add_parser("inspect", help="run one stage on a frame range and write its raw outputs")
    isub = inspect.add_subparsers(dest="stage", required=True)
    geo = isub.add_parser("geometry", help="disparity PNGs, KITTI poses and per-frame quality JSON")
    _add_job_options(geo)
    geo.add_argument("--sequence", required=True)
    geo.add_argument("--frames", type=_frames, default=(0, None), metavar="A:B", help="plan positions [A, B)")
    geo.add_argument("--out", required=True, help="output folder")
    geo.set_defaults(func=cmd_inspect_geometry)

    bench = sub.add_parser("bench", help="accuracy and speed on real ground truth")
    bsub = bench.add_subparsers(dest="stage", required=True)
    bgeo = bsub.add_parser("geometry", help="depth, stereo and egomotion accuracy; ms per step on one core")
    _add_job_options(bgeo)
    default_data = os.environ.get("TUBE_MINER_DATA", str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    bgeo.add_argument("--data", default=default_data, help="the shared real-data folder (default: ../shared/data)")
    bgeo.add_argument("--synthetic-frames", type=int, default=200, help="length of the synthetic egomotion runs")
    bgeo.add_argument("--json", help="also write the results as JSON here")
    bgeo.set_defaults(func=cmd_bench_geometry)

    btub = bsub.add_parser("tubes", help="ms per frame of localise + tubes + score + select at 20/100/500 proposals")
    _add_job_options(btub)
    btub.add_argument("--data", default=default_data, help="the shared real-data folder (default: ../shared/data)")
    btub.add_argument("--repeats", type=int, default=3)
    btub.set_defaults(func=cmd_bench_tubes)

    brng = bsub.add_parser("range", help="proposal survival and localisation error against distance "
                                         "(KITTI 0005 labels, synthetic truth)")
    _add_job_options(brng)
    brng.add_argument("--data", default=default_data, help="the shared real-data folder (default: ../shared/data)")
    brng.add_argument("--sources", nargs="+", choices=["kitti", "synthetic", "kitti-raw"],
                      default=["kitti", "synthetic", "kitti-raw"])
    brng.add_argument("--kitti-frames", type=_frames, default=(0, 16), metavar="A:B", help="KITTI 0005 frames [A, B)")
    brng.add_argument("--synthetic-sequence", default="0000")
    brng.add_argument("--synthetic-n-frames", type=int, default=200, help="length of the synthetic world")
    brng.add_argument("--synthetic-frames", type=_frames, default=(0, 100), metavar="A:B", help="synthetic frames [A, B)")
    brng.add_argument("--verbose", action="store_true", help="also list every dropped object")
    brng.set_defaults(func=cmd_bench_range)

    btrk = bsub.add_parser("tracking", help="detections-only tubes vs a 2D-IoU Hungarian baseline, KITTI MOT metrics")
    _add_job_options(btrk)
    btrk.add_argument("--data", default=default_data, help="the shared real-data folder (default: ../shared/data)")
    btrk.add_argument("--sequences", nargs="+", default=None, help="default: the twelve training sequences")
    btrk.set_defaults(func=cmd_bench_tracking)

    bcv = bsub.add_parser("crossval", help="choose the detections-only settings by leave-sequences-out "
                                           "cross-validation over the KITTI training sequences; report every fold")
    bcv.add_argument("--config", default="jobs/kitti-detections.toml", help="job config TOML the grid overrides")
    bcv.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config value")
    bcv.add_argument("--data", default=default_data, help="the shared real-data folder (default: ../shared/data)")
    bcv.add_argument("--folds", type=int, default=4, help="number of folds (default 4)")
    bcv.add_argument("--grid", action="append", default=[], metavar="KEY=V1,V2,...",
                     help="a grid axis, REFERENCE value first; repeat for more (default: mining/bench/crossval.py "
                          "DEFAULT_GRID)")
    bcv.add_argument("--sequences", nargs="+", default=None, help="default: the twelve training sequences")
    bcv.add_argument("--json", help="also write the results as JSON here")
    bcv.set_defaults(func=cmd_bench_crossval)

    bcvs = bsub.add_parser("crossval-scenarios", help="choose the image pipeline's added settings by leave-one-seed-out "
                                                      "cross-validation over the synthetic scenarios; report every fold")
    bcvs.add_argument("--config", default=None, help="job config TOML the grid overrides (default: jobs/synthetic.toml)")
    bcvs.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config value")
    bcvs.add_argument("--grid", action="append", default=[], metavar="KEY=V1,V2,...",
                      help="a grid axis, REFERENCE value first (default: mining/bench/crossval_scenarios.py DEFAULT_GRID)")
    bcvs.add_argument("--seeds", nargs="+", default=["0000", "0001", "0002", "0003"], help="synthetic seeds, one fold each")
    bcvs.add_argument("--scenarios", nargs="+", default=None, help="default: all")
    bcvs.add_argument("--frames", type=int, default=60, help="frames per scenario (default 60)")
    bcvs.add_argument("--full", action="store_true", help="render at 1242x375 instead of half size")
    bcvs.add_argument("--json", help="also write the results as JSON here")
    bcvs.set_defaults(func=cmd_bench_crossval_scenarios)
    if (Path(__file__).resolve().parents[1] / "jobs" / "synthetic.toml").is_file():
        bcvs.set_defaults(config=str(Path(__file__).resolve().parents[1] / "jobs" / "synthetic.toml"))

    bcls = bsub.add_parser("classify", help="known/unknown: fit detectability, calibrate the known margin on training "
                                            "seeds, measure on a held-out seed and KITTI 0005 (needs the ONNX model)")
    _add_job_options(bcls)
    bcls.add_argument("--data", default=default_data, help="the shared real-data folder (default: ../shared/data)")
    bcls.add_argument("--train-seeds", nargs="+", default=["0000", "0001", "0002"], help="synthetic training seeds")
    bcls.add_argument("--train-frames", type=int, default=100, help="frames per training seed")
    bcls.add_argument("--test-seed", default="0007", help="the held-out synthetic seed")
    bcls.add_argument("--frames", type=int, default=200, help="frames of the held-out seed")
    bcls.add_argument("--json", help="also write the results as JSON here")
    bcls.set_defaults(func=cmd_bench_classify)

    bcal = bsub.add_parser("calibrate", help="fit the calibrated unary (score.model=calibrated) on synthetic "
                                             "training seeds, leave-one-seed-out, for the job's proposer")
    _add_job_options(bcal)
    bcal.add_argument("--seeds", nargs="+", default=["0000", "0001", "0002", "0003", "0004", "0005", "0006"],
                      help="synthetic training seeds, one fold each (default 0000–0006; 0007–0009 are held out)")
    bcal.add_argument("--frames", type=int, default=100, help="frames per seed (default 100)")
    bcal.add_argument("--workers", type=int, default=1, help="seeds mined in parallel processes (default 1)")
    bcal.add_argument("--l2", type=float, default=1.0, help="L2 penalty on the standardised evidence (default 1)")
    bcal.add_argument("--epsilon1", type=float, default=0.0,
                      help="co-selection price for the calibrated unary in the folds (default 0: log-odds 0)")
    bcal.add_argument("--epsilon2", type=float, default=3.0,
                      help="overlap weight for the calibrated unary in the folds (default 3)")
    bcal.add_argument("--no-balance", action="store_true",
                      help="do not weigh unknown objects' tubes up to the known ones' total")
    bcal.add_argument("--json", help="also write the results as JSON here")
    bcal.set_defaults(func=cmd_bench_calibrate)

    bprp = bsub.add_parser("proposals", help="frames/s of the configured proposer on KITTI 0005 (per frame; "
                                             "batched for torch)")
    _add_job_options(bprp)
    bprp.add_argument("--data", default=default_data, help="the shared real-data folder (default: ../shared/data)")
    bprp.add_argument("--frames", type=_frames, default=(0, 9), metavar="A:B", help="KITTI 0005 frames [A, B), "
                                                                               "the first warms up")
    bprp.add_argument("--random-weights", action="store_true",
                      help="torch without proposals.torch.model_path: random initial weights (speed only)")
    bprp.add_argument("--json", help="also write the results as JSON here")
    bprp.set_defaults(func=cmd_bench_proposals)

    bpip = bsub.add_parser("pipeline", help="end-to-end frames/s on 1 and 2 workers, Ray overhead, worker memory, "
                                            "catalogue size and query times (synthetic 1242×375)")
    _add_job_options(bpip)
    bpip.add_argument("--frames", type=int, default=200, help="frames per sequence of the scaling job")
    bpip.add_argument("--sequences", nargs="+", default=["0000", "0001"], help="synthetic sequences of the scaling job")
    bpip.add_argument("--long", action="store_true", help="also a long run (memory vs sequence length; ~10 min on 2 cores)")
    bpip.add_argument("--long-frames", type=int, default=2000, help="frames of the long run")
    bpip.add_argument("--catalog-rows", type=int, default=1_000_000, help="tube-frame rows of the catalogue bench")
    bpip.add_argument("--dir", help="where the bench catalogues go (default: the system temporary folder)")
    bpip.add_argument("--json", help="also write the results as JSON here")
    bpip.set_defaults(func=cmd_bench_pipeline)

    blk = bsub.add_parser("looks", help="recall@20 with the right COCO class (shared ONNX model) on synthetic "
                                        "frames against KITTI 0005 frames 0–15, and the renderer's ms per frame")
    _add_job_options(blk)
    blk.add_argument("--data", default=default_data, help="the shared real-data folder (default: ../shared/data)")
    blk.add_argument("--model", default=str(Path(default_data).parent / "models" / "yolov8n-seg_int8.onnx"),
                     help="YOLO-seg ONNX model (default: ../shared/models/yolov8n-seg_int8.onnx)")
    blk.add_argument("--seeds", nargs="+", default=["0000", "0001", "0002"], help="synthetic sequences")
    blk.add_argument("--frames", type=int, default=34, help="frames per seed")
    blk.add_argument("--step", type=int, default=5, help="plan positions between frames (the first is STEP)")
    blk.add_argument("--n-frames", type=int, default=200, help="length of the synthetic world")
    blk.add_argument("--png", help="write a few frames with the detections drawn to this folder")
    blk.add_argument("--no-kitti", action="store_true", help="skip the KITTI reference")
    blk.add_argument("--json", help="also write the results as JSON here")
    blk.set_defaults(func=cmd_bench_looks)

    bscn = bsub.add_parser("scenarios", help="staged synthetic scenarios (one failure mode each), scene flow on and "
                                             "off: tube recall, IDSW per track, HOTA, flow on the targets")
    _add_job_options(bscn)
    synthetic_job = Path(__file__).resolve().parents[1] / "jobs" / "synthetic.toml"
    if synthetic_job.is_file():
        bscn.set_defaults(config=str(synthetic_job))
    bscn.add_argument("--scenarios", nargs="+", default=None, help="default: all (mining/sources/synthetic/scenarios.py)")
    bscn.add_argument("--frames", type=int, default=None, help="frames per scenario (default: the scenario's, 80)")
    bscn.add_argument("--sequence", default="0000", help="seeds the world around the staged objects")
    bscn.add_argument("--half", action="store_true", help="render at 621x188 (fx 360.77) instead of 1242x375")
    bscn.add_argument("--json", help="also write the results as JSON here")
    bscn.set_defaults(func=cmd_bench_scenarios)

    track = sub.add_parser("track", help="tubes → score → select over one sequence, written as KITTI tracking txt")
    tsub = track.add_subparsers(dest="mode", required=True)
    tdet = tsub.add_parser("detections", help="detections-only mode: 3D detections + egoposes, no images")
    _add_job_options(tdet)
    tdet.add_argument("--sequences", nargs="+", required=True)
    tdet.add_argument("--detections", help="PointRCNN folder (<Class>/<seq>.txt) or result-format folder; "
                                           "default <root>/training/det_pointrcnn")
    tdet.add_argument("--poses", help="folder of <seq>.txt camera-to-world poses; default <root>/training/egoposes_orbslam3")
    tdet.add_argument("--out", required=True)
    tdet.set_defaults(func=cmd_track_detections)
    timg = tsub.add_parser("images", help="the full pipeline on stereo frames (geometry, proposals, tubes)")
    _add_job_options(timg)
    timg.add_argument("--sequence", required=True)
    timg.add_argument("--frames", type=_frames, default=(0, None), metavar="A:B")
    timg.add_argument("--out", required=True)
    timg.set_defaults(func=cmd_track_images)

    ev = sub.add_parser("eval", help="metrics against ground truth")
    esub = ev.add_subparsers(dest="metric", required=True)
    emot = esub.add_parser("kitti-mot", help="HOTA, MOTA, IDSW, IDF1 by the KITTI MOT protocol")
    emot.add_argument("--gt", required=True, help="label_02 folder")
    emot.add_argument("--results", required=True, help="folder of <seq>.txt results")
    emot.add_argument("--sequences", nargs="+", required=True)
    emot.add_argument("--seqmap", help="seqmap with frame counts (else the largest frame seen)")
    emot.add_argument("--classes", nargs="+", default=["Car", "Pedestrian"])
    emot.add_argument("--frames", type=int, help="evaluate only the first N frames of each sequence")
    emot.add_argument("--per-sequence", action="store_true")
    emot.set_defaults(func=cmd_eval_kitti_mot)
    erec = esub.add_parser("recall", help="proposal recall@N (box IoU > 0.5) for known and unknown objects")
    _add_job_options(erec)
    erec.add_argument("--sequence", help="KITTI: run the configured proposer on this sequence")
    erec.add_argument("--frames", type=_frames, default=(0, None), metavar="A:B")
    erec.add_argument("--labels", help="KITTI label_02 file (default: <root>/training/label_02/<sequence>.txt)")
    erec.add_argument("--oxford-labels", help="RobotCar: the 4D-GVT labels_4dgvt folder")
    erec.add_argument("--proposals-json", help="RobotCar: proposal JSON files laid out like the label files")
    erec.add_argument("--funnel", action="store_true", help="KITTI: also mine tubes and print the recall funnel "
                                                             "(proposed → observed → candidate → selected, box IoU "
                                                             "≥ 0.5, per distance and height bin)")
    erec.add_argument("--json", default=None, metavar="PATH", help="KITTI: also write recall@N (and the funnel) "
                                                                   "as JSON here")
    erec.set_defaults(func=cmd_eval_recall)
    esyn = esub.add_parser("synthetic", help="mine a synthetic sequence and score known and unknown objects against "
                                             "its exact truth", description="Mine a synthetic sequence and score it "
                                                                            "against its ground truth.")
    esyn.add_argument("--sequence", default="0000")
    esyn.add_argument("--n-frames", type=int, default=100)
    esyn.add_argument("--config", default=None, help="job TOML (default: built-in defaults)")
    esyn.add_argument("--set", action="append", default=[], help="config override KEY=VALUE")
    esyn.add_argument("--min-visible-px", type=int, default=None,
                      help="ignore objects with fewer visible pixels (default: the protocol's)")
    esyn.add_argument("--max-depth-m", type=float, default=None)
    esyn.add_argument("--json", default=None, metavar="PATH", help="also write the results (metrics, tube counts, "
                                                                   "known/unknown calls) as JSON here")
    esyn.set_defaults(func=cmd_eval_synthetic)
    return parser


def _check_names(args: argparse.Namespace) -> None:
    """Sequence names from the command line are names, never paths (mining/names.py)."""
    for flag in ("sequence", "sequences"):
        value = getattr(args, flag, None)
        for name in [value] if isinstance(value, str) else value or []:
            check_name(name, "sequence", f"--{flag}")


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)
    args.argv = argv
    try:
        _check_names(args)
        return args.func(args)
    except NothingMatched as e:
        print(f"mine {args.command}: {e}", file=sys.stderr)
        return NOTHING_MATCHED
    except (MiningError, ConfigError) as e:
        print(f"mine: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # Ctrl-C: one line, no traceback (Ray's included); 130 = 128 + SIGINT
        resume = " — rerun the same command to resume" if args.command == "submit" else ""
        print(f"interrupted{resume}", file=sys.stderr)
        return INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
