"""The ``mine`` command line: it parses; the packages act. ``submit``, ``status``, ``query``,
``export``, ``render``, ``config`` and ``view`` are parsed here; every ``mine GROUP NAME`` command of
COMMANDS lives in its module, which offers ``add_arguments(parser)`` and ``run(args)``."""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from typing import Any, NamedTuple

from mining.checks import (MAX_WORKERS, count, memory_size, output_file, output_folder, path_text, positive_float, real,
                           seconds, time_limit, worker_count)
from mining.errors import ConfigError, MiningError, NothingMatched
from mining.export.registry import FORMATS as EXPORT_FORMATS
from mining.names import check_name
from mining.pipeline.arguments import add_job_options, add_overwrite_option, check_paths, frame_range, job_config


INTERRUPTED = 130  # the shell's exit status for a process ended by SIGINT (128 + 2)
NOTHING_MATCHED = 1  # a predicate matched nothing and nothing was written (grep's "no match")


class Command(NamedTuple):
    """``mine GROUP NAME``: its module adds the options (``add_arguments``) and acts (``run``)."""

    group: str
    name: str
    module: str
    help: str
    description: str | None = None


GROUPS = {  # group → (the name its command is parsed into, help), in the order --help lists them
    "inspect": ("stage", "run one stage on a frame range and write its raw outputs"),
    "bench": ("stage", "accuracy and speed on real ground truth"),
    "track": ("mode", "tubes → score → select over one sequence, written as KITTI tracking txt"),
    "eval": ("metric", "metrics against ground truth"),
}

COMMANDS = (  # in the order --help lists them
    Command("inspect", "geometry", "mining.pipeline.inspect_geometry",
            "disparity PNGs, KITTI poses and per-frame quality JSON"),
    Command("bench", "geometry", "mining.bench.geometry", "depth, stereo and egomotion accuracy; ms per step on one core"),
    Command("bench", "tubes", "mining.bench.tubes",
            "ms per frame of localise + tubes + score + select at 20/100/500 proposals"),
    Command("bench", "range", "mining.bench.range", "proposal survival and localisation error against distance "
                                                    "(KITTI 0005 labels, synthetic truth)"),
    Command("bench", "tracking", "mining.bench.tracking",
            "detections-only tubes vs a 2D-IoU Hungarian baseline, KITTI MOT metrics"),
    Command("bench", "crossval", "mining.bench.crossval", "choose the detections-only settings by leave-sequences-out "
                                                          "cross-validation over the KITTI training sequences; report "
                                                          "every fold"),
    Command("bench", "crossval-scenarios", "mining.bench.crossval_scenarios",
            "choose the image pipeline's added settings by leave-one-seed-out cross-validation over the synthetic "
            "scenarios; report every fold"),
    Command("bench", "classify", "mining.bench.classify",
            "known/unknown: fit detectability, calibrate the known margin on training seeds, measure on a held-out "
            "seed and KITTI 0005 (needs the ONNX model)"),
    Command("bench", "calibrate", "mining.bench.calibrate", "fit the calibrated unary (score.model=calibrated) on "
                                                            "synthetic training seeds, leave-one-seed-out, for the "
                                                            "job's proposer"),
    Command("bench", "proposals", "mining.bench.proposals",
            "frames/s of the configured proposer on KITTI 0005 (per frame; batched for torch)"),
    Command("bench", "scale", "mining.bench.scale", "per-stage CPU seconds a frame at 1280×960 (or any source), GPU "
                                                    "rates where CUDA is, and the projection for 806,000 frames on a "
                                                    "stated cluster (--cpus, --gpus), with a chart"),
    Command("bench", "stages", "mining.bench.stages", "the proposal stage fed two ways (explicit actor queues, Ray "
                                                      "Data) on logical GPUs: frames/s, GPU busy share, ramp-up, "
                                                      "object store"),
    Command("bench", "pipeline", "mining.bench.pipeline", "end-to-end frames/s on 1 and 2 workers, Ray overhead, worker "
                                                          "memory, catalogue size and query times (synthetic 1242×375)"),
    Command("bench", "looks", "mining.bench.looks", "recall@20 with the right COCO class (shared ONNX model) on "
                                                    "synthetic frames against KITTI 0005 frames 0–15, and the "
                                                    "renderer's ms per frame"),
    Command("bench", "scenarios", "mining.bench.scenarios", "staged synthetic scenarios (one failure mode each), scene "
                                                            "flow on and off: tube recall, IDSW per track, HOTA, flow "
                                                            "on the targets"),
    Command("track", "detections", "mining.pipeline.detections",
            "detections-only mode: 3D detections + egoposes, no images"),
    Command("track", "images", "mining.pipeline.track_images",
            "the full pipeline on stereo frames (geometry, proposals, tubes)"),
    Command("eval", "kitti-mot", "mining.eval.kitti_mot", "HOTA, MOTA, IDSW, IDF1 by the KITTI MOT protocol"),
    Command("eval", "recall", "mining.bench.recall",
            "proposal recall@N (box IoU > 0.5) for known and unknown objects"),
    Command("eval", "synthetic", "mining.bench.synthetic",
            "mine a synthetic sequence and score known and unknown objects against its exact truth",
            "Mine a synthetic sequence and score it against its ground truth."),
)


class Parser(argparse.ArgumentParser):
    """A parser whose errors are one line (``mine query: error: argument --threads: …``) with
    where the usage is, instead of the usage text and then the error."""

    def error(self, message: str) -> Any:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


class CommandParser(Parser):
    """The parser of one of COMMANDS. Its module is imported, and adds its options, only when
    the command is parsed (its ``--help`` included): the bench modules pull in OpenCV, SciPy
    and ONNX Runtime, a second and more that ``mine status`` should not wait for."""

    def __init__(self, *args: Any, module: str | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.module = module

    def load_command(self) -> None:
        """Import the command's module (once) and let it add its options."""
        if self.module is not None:
            command = importlib.import_module(self.module)
            self.module = None
            command.add_arguments(self)
            self.set_defaults(func=command.run)

    def parse_known_args(self, args: Any = None, namespace: Any = None) -> Any:
        self.load_command()
        return super().parse_known_args(args, namespace)


def add_commands(sub: Any) -> None:
    """The groups of COMMANDS and their commands, as sub-parsers of ``sub``."""
    for group, (dest, help) in GROUPS.items():
        gsub = sub.add_parser(group, help=help).add_subparsers(dest=dest, required=True, parser_class=CommandParser)
        for c in COMMANDS:
            if c.group == group:
                gsub.add_parser(c.name, module=c.module, help=c.help, description=c.description)


def cmd_submit(args: argparse.Namespace) -> int:
    cfg = job_config(args)
    if args.new_run and args.extend:
        raise ConfigError("--new-run and --extend exclude each other")
    if args.address and args.address.startswith("http"):
        from mining.pipeline.rayjobs import submit_ray_job

        return submit_ray_job(args.address, args.argv, args.out, wait=not args.no_wait)
    if args.no_wait:
        raise ConfigError("--no-wait needs --address http://HEAD:8265 (a job handed to a cluster through Ray Jobs)")
    from mining.pipeline.localray import bind_origin
    from mining.pipeline.submit import mine_on_ray

    mode = "new" if args.new_run else "extend" if args.extend else "resume"
    summary = mine_on_ray(cfg, args.out, args.sequences, args.frames, address=args.address, workers=args.workers,
                          progress=not args.no_progress, mode=mode, verify=args.verify, lock_wait=args.lock_wait,
                          bind_origin=bind_origin(args.host, args.set, args.config))
    for line in summary.lines():
        print(line)
    return 1 if summary.any_failed else 0


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
    return run_query(args.sql, args.out, args.format, args.output, overwrite=args.overwrite, **limits)


def cmd_export(args: argparse.Namespace) -> int:
    from mining.export.run import run_export

    return run_export(args.out, args.where, args.format, args.dest, args.margin, args.images, args.overwrite,
                      args.unknown_class, args.category_from)


# Copies of constants whose modules load pyarrow/DuckDB (slow for every `mine` call); tests/test_labels.py
# checks each equal to its source.
MOTS_MAX_CLASS = 1000  # export/kitti.MOTS_MAX_CLASS
VERDICTS = ("object", "not_object", "part_of", "duplicate")  # catalog/labels.VERDICTS
MAX_TAG_CHARS = 64  # catalog/labels.MAX_TAG_CHARS


def cmd_label(args: argparse.Namespace) -> int:
    from mining.catalog.triage import run_label

    return run_label(args.out, args.where, args.verdict, args.clear_verdict, args.tag, args.untag, args.author,
                     args.dry_run, args.compact, args.lock_wait)


def cmd_render(args: argparse.Namespace) -> int:
    from mining.export.render import run_render

    return run_render(args.out, args.sequence, args.dest, args.where, args.depth, args.fps, args.frames,
                      overwrite=args.overwrite, all_candidates=args.all_candidates)


def cmd_config(args: argparse.Namespace) -> int:
    import difflib
    import json

    from mining.config import JobConfig
    from mining.configdoc import all_keys, matching_keys, source_tag, toml_value, value_at

    given = bool(args.config or args.set or args.dataset or args.root or args.option)
    cfg = job_config(args) if given else JobConfig()
    keys = all_keys()
    shown = matching_keys(keys, args.keys)
    if not shown:
        words = sorted({k.path for k in keys} | {k.path.rsplit(".", 1)[0] + "." for k in keys if "." in k.path})
        near = difflib.get_close_matches(args.keys, words, n=3)
        hint = f"; did you mean {' or '.join(repr(w) for w in near)}?" if near else ""
        raise ConfigError(f"no config key matches {args.keys!r}{hint} (`mine config` lists all {len(keys)})")
    rows = [{"key": k.path, "value": value_at(cfg, k.path), "default": k.default, "source": source_tag(k.comment),
             "type": k.type, "rules": k.rules, "comment": k.comment} for k in shown]
    if args.format == "json":
        print(json.dumps(rows, indent=1, ensure_ascii=False, default=str))
        return 0
    origin = " + ".join(([str(args.config)] if args.config else []) + (["the options given"] if given and (
        args.set or args.option or args.dataset or args.root) else [])) or "the defaults"
    print(f"{len(rows)} of {len(keys)} job config keys, values of {origin}; [where the default comes from]; "
          "rules: docs/CONFIG.md")
    for r in rows:
        value = toml_value(r["value"])
        differs = f"  (default {r['default']})" if value != r["default"] else ""
        print(f"{r['key']} = {value}{differs}  [{r['source']}]")
        if r["comment"]:
            print(f"    {r['comment']}")
    return 0


def _version_text() -> str:
    """The package version, and the catalogue schema it writes."""
    from mining import __version__
    from mining.catalog.schema import SCHEMA_VERSION

    return f"mine (tube-miner) {__version__}, catalogue schema v{SCHEMA_VERSION}"


def cmd_view(args: argparse.Namespace) -> int:
    from mining.view.server import run_view

    return run_view(args.out, args.host, args.port, args.cache, args.log, args.author)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="mine", description="Tube Miner: mine generic object tubes from stereo video.")
    parser.add_argument("--version", action="version", version=_version_text())
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)

    smt = sub.add_parser("submit", help="plan windows and mine them on Ray (local, or a cluster with --address)")
    add_job_options(smt, paths_here=False)
    smt.add_argument("--sequences", nargs="+", help="default: the config's, else every sequence the source finds")
    smt.add_argument("--frames", type=frame_range, default=(0, None), metavar="A:B",
                     help="plan positions [A, B) of every sequence (default: all)")
    smt.add_argument("--out", type=output_folder, default="out/catalog", help="catalogue folder or pyarrow filesystem URI")
    smt.add_argument("--address", help="http://HEAD:8265: hand the job to that cluster through Ray Jobs (--config, "
                                       "--root and --out are made absolute here and read on the cluster); "
                                       "HOST:PORT or auto: run the scheduler here, the work on that cluster; "
                                       "default: start a local Ray on this machine")
    smt.add_argument("--no-wait", action="store_true", help="with --address http://…: print the submission id and "
                                                            "return instead of following the job's logs")
    smt.add_argument("--workers", type=worker_count, help=f"local Ray only: CPUs to use, 1 to {MAX_WORKERS} (default: all)")
    smt.add_argument("--host", metavar="IP", help="local Ray only: the interface every Ray port listens on (default: "
                                                  "the config's run.bind_host, 127.0.0.1). Ray's ports run code "
                                                  "unauthenticated: another interface only on a network you trust")
    smt.add_argument("--no-progress", action="store_true", help="no progress display (without it a log or a pipe gets a line per tenth of the work)")
    smt.add_argument("--extend", action="store_true",
                     help="--out holds this job with a narrower --frames or fewer --sequences: widen it (what differs "
                          "from a clean run of the new range is recomputed); anything else that differs is refused")
    smt.add_argument("--new-run", action="store_true",
                     help="--out holds another job, or catalogue data without a readable job.json: move it aside "
                          "(to OUT/_replaced/<run id>-<time>/, local folders only) and start a new one")
    smt.add_argument("--verify", action="store_true",
                     help="check every recorded checksum before resuming (default: sizes only); damaged files are "
                          "recomputed")
    smt.add_argument("--lock-wait", type=seconds, default=0.0, metavar="SECONDS",
                     help="another submit is writing --out: wait up to this long for it (default: refuse at once)")
    smt.set_defaults(func=cmd_submit)

    sts = sub.add_parser("status", help="windows done, failed (with the error) and pending")
    sts.add_argument("--out", type=path_text, default="out/catalog", help="catalogue folder or URI")
    sts.add_argument("--verify", action="store_true",
                     help="also check every file's sha256 against the manifest (reads the whole catalogue)")
    sts.add_argument("--address", help="http://HEAD:8265: the cluster's Tube Miner jobs through Ray Jobs instead")
    sts.add_argument("--job", help="with --address: one job's status and the end of its logs")
    sts.set_defaults(func=cmd_status)

    qry = sub.add_parser("query", help="read-only SQL (DuckDB) over the catalogue's tables and views")
    qry.add_argument("sql")
    qry.add_argument("--out", type=path_text, default="out/catalog", help="catalogue folder or URI")
    qry.add_argument("--format", choices=["table", "csv", "json", "parquet"], default="table")
    qry.add_argument("--output", type=output_file, help="write here instead of standard output (required for parquet)")
    add_overwrite_option(qry, "--output")
    qry.add_argument("--memory-limit", type=memory_size, help="most memory the query may use, e.g. 4GB; beyond it DuckDB spills to "
                                            "a private temporary folder (default: query.MEMORY_LIMIT, 2GB)")
    qry.add_argument("--threads", type=count(1, 1024), help="threads the query may use (default: query.THREADS, 2)")
    qry.add_argument("--timeout", type=time_limit, metavar="SECONDS",
                     help="stop the query after this many seconds (default: query.TIMEOUT_S, 60)")
    qry.add_argument("--limit", type=count(0, 10**12), metavar="N",
                     help="table output shows at most N rows and the total count (default: query.LIMIT, 50; 0 = all)")
    qry.set_defaults(func=cmd_query)

    exp = sub.add_parser("export", help="tubes matching a SQL predicate, for other tools")
    exp.add_argument("dest", type=output_folder, help="output folder")
    exp.add_argument("--where", default="selected", help="SQL predicate over the tubes table (default: selected)")
    exp.add_argument("--format", choices=list(EXPORT_FORMATS), required=True)
    exp.add_argument("--out", type=path_text, default="out/catalog", help="catalogue folder or URI")
    exp.add_argument("--overwrite", action="store_true",
                     help="DEST holds an earlier export: remove what that export recorded (DEST/.mine-export.json) "
                          "and write this one; other files in DEST are kept")
    exp.add_argument("--margin", type=real(0.0, 10.0), default=None,
                     help="crops: context on each side, as a fraction of the box (default 0.15, at least 8 px)")
    exp.add_argument("--images", action="store_true",
                     help="youtube-vis, tao, burst: also write the video frames (rectified left images, JPEG) the JSON names; "
                          "fiftyone: the videos the manifest names; rerun: the frames, stereo depth and pinhole")
    exp.add_argument("--unknown-class", type=count(1, MOTS_MAX_CLASS - 1), default=None,
                     help="kitti-mots: class id for unknown tubes (default 10, the format's ignore, which MOTS tools drop)")
    exp.add_argument("--category-from", choices=["category", "tag"], default="category",
                     help="tag: a tagged tube's category is its tag (mine label / mine view), as a known class; "
                          "default: the mined category. Every export writes tube_labels.json beside its files")
    exp.set_defaults(func=cmd_export)

    lab = sub.add_parser("label", help="label the tubes a SQL predicate selects (a verdict or a tag), for scripted triage")
    lab.add_argument("--out", type=path_text, default="out/catalog", help="catalogue folder")
    lab.add_argument("--where", help="SQL predicate over the tubes and their labels (as mine export's)")
    lab.add_argument("--verdict", choices=list(VERDICTS), help="set this verdict")
    lab.add_argument("--clear-verdict", action="store_true", help="take the verdict back")
    lab.add_argument("--tag", help=f"add this tag (a free label, at most {MAX_TAG_CHARS} characters)")
    lab.add_argument("--untag", help="remove this tag")
    lab.add_argument("--author", help="who decided (default: the login name)")
    lab.add_argument("--dry-run", action="store_true", help="say how many tubes would be labelled; write nothing")
    lab.add_argument("--compact", action="store_true",
                     help="merge the label files into one (under the writer lock; waits --lock-wait seconds for it)")
    lab.add_argument("--lock-wait", type=real(0.0, 86400.0), default=0.0, metavar="SECONDS",
                     help="--compact: wait this long for a running job's lock (default 0: refuse at once)")
    lab.set_defaults(func=cmd_label)

    rnd = sub.add_parser("render", help="a sequence with its selected tubes drawn (mask, id, category), as a video")
    rnd.add_argument("dest", type=output_file, help="DEST.mp4 (H.264 with PyAV, the `video` extra; without it MPEG-4 Part 2, which "
                                  "browsers do not play) or DEST.webm (VP8); H.264 and VP8 play in browsers")
    rnd.add_argument("--out", type=path_text, default="out/catalog", help="catalogue folder")
    rnd.add_argument("--sequence", required=True)
    rnd.add_argument("--where", help="SQL predicate over the tubes table: draw only the selected tubes it matches")
    rnd.add_argument("--depth", action="store_true", help="add a stereo depth panel beside each frame")
    rnd.add_argument("--fps", type=positive_float(1000.0),  # render.MAX_FPS (not imported here: OpenCV is slow to load)
                     help="frame rate, > 0 and ≤ 1000 (default: the sequence's, from its timestamps)")
    rnd.add_argument("--frames", type=frame_range, default=None, metavar="A:B",
                     help="plan positions [A, B) (default: the frames the catalogue mined)")
    rnd.add_argument("--all-candidates", action="store_true",
                     help="also draw the candidates co-selection left out, dimmed (outline and label, no fill)")
    rnd.add_argument("--overwrite", action="store_true",
                     help="DEST exists: replace it (a plain file only; without this flag an existing DEST is refused)")
    rnd.set_defaults(func=cmd_render)

    cfg = sub.add_parser("config", help="every job config key with its value, default, source and comment")
    cfg.add_argument("keys", nargs="?", metavar="KEYS",
                     help="only the keys starting with this (e.g. tubes. or select.epsilon), else those holding it")
    add_job_options(cfg)
    cfg.add_argument("--format", choices=["text", "json"], default="text")
    cfg.set_defaults(func=cmd_config)

    viw = sub.add_parser("view", help="browse the catalogue in a web browser: a gallery of tubes, a page per tube")
    viw.add_argument("--out", type=path_text, default="out/catalog", help="catalogue folder")
    viw.add_argument("--port", type=count(0, 65535), default=8765, help="port to listen on (default 8765; 0 picks a free one)")
    viw.add_argument("--host", default="127.0.0.1",
                     help="address to listen on (default 127.0.0.1: this machine only; there is no login)")
    viw.add_argument("--cache", type=output_folder, help="folder for rendered pictures (default: tube-miner/view in $XDG_CACHE_HOME or "
                                     "~/.cache, made 0700; refused when not yours alone; not inside the catalogue)")
    viw.add_argument("--log", action="store_true", help="log one line per request on standard error")
    viw.add_argument("--author", help="the author of labels made in this viewer (default: the login name)")
    viw.set_defaults(func=cmd_view)

    add_commands(sub)
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
        check_paths(args)  # before any work: an output that cannot be written is said now, not at the end
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
