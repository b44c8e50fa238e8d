"""The ``mine`` command line: it parses; the packages act. Every command is a row of COMMANDS:
a top-level verb (``mine submit``, ``status``, ``query``, ``export``, ``label``, ``render``,
``config``, ``view``, ``describe``, ``similar``, ``group``: ``mining/commands/``) or a ``mine GROUP NAME`` command, each in its module,
which offers ``add_arguments(parser)`` and ``run(args)``. ``main`` turns every error a command
raises into one line and its exit status, once."""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from typing import Any, NamedTuple

from mining.errors import MiningError, NothingMatched
from mining.names import check_name
from mining.pipeline.arguments import check_paths


INTERRUPTED = 130  # the shell's exit status for a process ended by SIGINT (128 + 2)
NOTHING_MATCHED = 1  # a predicate matched nothing and nothing was written (grep's "no match")


class Command(NamedTuple):
    """``mine NAME`` (``group`` None: a top-level verb) or ``mine GROUP NAME``: its module adds the
    options (``add_arguments``) and acts (``run``)."""

    group: str | None
    name: str
    module: str
    help: str
    description: str | None = None
    # Its errors are said in its name, ``mine NAME: reason``, as its other lines are (the commands
    # over a catalogue's tubes); the others say ``mine: error: reason``. Either way exit status 2.
    names_errors: bool = False


GROUPS = {  # group → (the name its command is parsed into, help), in the order --help lists them
    "inspect": ("stage", "run one stage on a frame range and write its raw outputs"),
    "bench": ("stage", "accuracy and speed on real ground truth"),
    "track": ("mode", "tubes → score → select over one sequence, written as KITTI tracking txt"),
    "eval": ("metric", "metrics against ground truth"),
}

COMMANDS = (  # in the order --help lists them: the top-level verbs, then the groups' commands
    Command(None, "submit", "mining.commands.submit",
            "plan windows and mine them on Ray (local, or a cluster with --address)"),
    Command(None, "status", "mining.commands.status", "windows done, failed (with the error) and pending"),
    Command(None, "query", "mining.commands.query", "read-only SQL (DuckDB) over the catalogue's tables and views",
            names_errors=True),
    Command(None, "export", "mining.commands.export", "tubes matching a SQL predicate, for other tools",
            names_errors=True),
    Command(None, "label", "mining.commands.label",
            "label the tubes a SQL predicate, a group or a likeness selects (a verdict or a tag), for scripted "
            "triage", names_errors=True),
    Command(None, "describe", "mining.commands.describe",
            "a descriptor for every tube (size, height, distance, motion, shape, class), for similar and group",
            names_errors=True),
    Command(None, "embed", "mining.commands.embed",
            "tube embeddings from an image encoder you bring (ONNX), into the tube_embeddings table", names_errors=True),
    Command(None, "similar", "mining.commands.similar",
            "find more like this: the k tubes nearest a tube by cosine distance of their descriptors",
            names_errors=True),
    Command(None, "group", "mining.commands.group",
            "group the unknown set by density (HDBSCAN over the descriptors) into the tube_groups table",
            names_errors=True),
    Command(None, "render", "mining.commands.render",
            "a sequence with its selected tubes drawn (mask, id, category), as a video", names_errors=True),
    Command(None, "config", "mining.commands.config",
            "every job config key with its value, default, source and comment"),
    Command(None, "view", "mining.commands.view",
            "browse the catalogue in a web browser: a gallery of tubes, a page per tube"),
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
    Command("bench", "similar", "mining.bench.similar", "k = 10 similar-tube queries over 10⁵ and 10⁶ descriptors "
                                                        "(median ms, build s; --compare: the index libraries), and "
                                                        "grouping 10⁵ unknown tubes"),
    Command("bench", "pipeline", "mining.bench.pipeline", "end-to-end frames/s on 1 and 2 workers, Ray overhead, worker "
                                                          "memory, catalogue size and query times (synthetic 1242×375)"),
    Command("bench", "memory", "mining.bench.memory", "resident memory of the driver, workers, Ray's processes and "
                                                     "the object store once per window over one long sequence "
                                                     "(synthetic 414×125): peak and MB per 1,000 frames by role"),
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


NAMES_ERRORS = frozenset(c.name for c in COMMANDS if c.group is None and c.names_errors)


class Parser(argparse.ArgumentParser):
    """A parser whose errors are one line (``mine query: error: argument --threads: …``) with
    where the usage is, instead of the usage text and then the error."""

    def error(self, message: str) -> Any:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


class CommandParser(Parser):
    """The parser of one of COMMANDS (``module``), or of a group of them (no module). Its module
    is imported, and adds its options, only when the command is parsed (its ``--help``
    included): the bench modules pull in OpenCV, SciPy and ONNX Runtime, the catalogue's
    commands DuckDB and Arrow, a second and more that ``mine status`` should not wait for."""

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
    """Every row of COMMANDS as a sub-parser of ``sub`` (a CommandParser each): the top-level
    verbs, then the groups and their commands."""
    for c in COMMANDS:
        if c.group is None:
            sub.add_parser(c.name, module=c.module, help=c.help, description=c.description)
    for group, (dest, help) in GROUPS.items():
        gsub = sub.add_parser(group, help=help).add_subparsers(dest=dest, required=True, parser_class=CommandParser)
        for c in COMMANDS:
            if c.group == group:
                gsub.add_parser(c.name, module=c.module, help=c.help, description=c.description)


def _version_text() -> str:
    """The package version, and the catalogue schema it writes."""
    from mining import __version__
    from mining.catalog.schema import SCHEMA_VERSION

    return f"mine (tube-miner) {__version__}, catalogue schema v{SCHEMA_VERSION}"


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="mine", description="Tube Miner: mine generic object tubes from stereo video.")
    parser.add_argument("--version", action="version", version=_version_text())
    add_commands(parser.add_subparsers(dest="command", required=True, parser_class=CommandParser))
    return parser


def _check_names(args: argparse.Namespace) -> None:
    """Sequence names from the command line are names, never paths (mining/names.py)."""
    for flag in ("sequence", "sequences"):
        value = getattr(args, flag, None)
        for name in [value] if isinstance(value, str) else value or []:
            check_name(name, "sequence", f"--{flag}")


BROKEN_PIPE = 141  # the shell's status of a writer whose reader went away: 128 + SIGPIPE (13)


def main(argv: list[str] | None = None) -> int:
    """Parse ``argv`` and run the command. Every error it raises is one line on standard error
    and an exit status, here and nowhere else: NothingMatched ``mine NAME: …``, 1; a MiningError
    ``mine: error: …`` (in the name of a command that ``names_errors``, ``mine NAME: …``, once
    it runs: the checks of the options before it are mine's), 2; Ctrl-C ``interrupted``, 130."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)
    args.argv = argv
    said = "mine: error"
    try:
        _check_names(args)
        check_paths(args)  # before any work: an output that cannot be written is said now, not at the end
        if args.command in NAMES_ERRORS:
            said = f"mine {args.command}"
        return args.func(args)
    except NothingMatched as e:
        print(f"mine {args.command}: {e}", file=sys.stderr)
        return NOTHING_MATCHED
    except MiningError as e:
        print(f"{said}: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader stopped reading (`mine config | head`): stop quietly, as `cat` does
        # The interpreter flushes stdout at exit and would fail again: point it at /dev/null first.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return BROKEN_PIPE
    except KeyboardInterrupt:  # Ctrl-C: one line, no traceback (Ray's included); 130 = 128 + SIGINT
        resume = " — rerun the same command to resume" if args.command == "submit" else ""
        print(f"interrupted{resume}", file=sys.stderr)
        return INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
