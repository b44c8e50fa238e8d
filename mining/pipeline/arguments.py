"""The command-line words the ``mine`` commands share: the job options (``--config``, ``--set``,
``--dataset``, ``--root``, ``--option``) and the job config they make, the ``A:B`` frame range,
the shared data folder, ``--overwrite`` and the check of every output an option names. Here,
below bench and the CLI, so that the command modules of pipeline/ and bench/ add their own
options without importing the CLI.

Every option is checked before any work starts (``docs/OPERATING.md``): a number or a path by
its type at parse time (``mining.checks``: ``count``, ``real``, ``input_file``,
``output_file`` …), and an output once more by ``check_paths`` after parsing: its folder can
be written and an existing file is replaced only with ``--overwrite``
(``safe_files.check_output_file``)."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from mining.catalog import safe_files
from mining.checks import (MAX_FRAMES, LocalInput, OutputFile, OutputFolder, input_file, input_folder, input_path,
                           local_input)
from mining.config import JobConfig, load_config, parse_override, validate
from mining.errors import ConfigError
from mining.names import shown

REPO = Path(__file__).resolve().parents[2]
SYNTHETIC_JOB = REPO / "jobs" / "synthetic.toml"  # the default job of the synthetic benches, when present


# -- outputs ----------------------------------------------------------------------------------


def add_overwrite_option(p: argparse.ArgumentParser, what: str = "the file") -> None:
    """``--overwrite`` for a command that writes a file: without it an existing file is refused."""
    p.add_argument("--overwrite", action="store_true",
                   help=f"replace {what} when it exists (a plain file only: a link or a folder is refused either "
                        "way); without this flag an existing file is refused before any work")


def option_name(dest: str) -> str:
    """The option of an argparse ``dest``: ``json`` → ``--json``, ``dest`` → ``DEST``."""
    return "DEST" if dest == "dest" else "--" + dest.replace("_", "-")


def check_paths(args: argparse.Namespace) -> None:
    """The outputs the parsed options name, checked before any work (InputError naming the
    option): each file by ``safe_files.check_output_file`` (``--overwrite`` where the command
    has it), each folder to be one (or absent) where something can be written; and each
    ``LocalInput`` to exist."""
    if str(getattr(args, "address", None) or "").startswith("http"):
        return  # handed to a cluster through Ray Jobs: its paths are the cluster's, checked there
    overwrite = bool(getattr(args, "overwrite", False))
    for dest, value in sorted(vars(args).items()):
        if isinstance(value, LocalInput):
            if not os.path.exists(value):
                raise safe_files.refusal(value, "no such file or folder", option_name(dest))
        elif isinstance(value, OutputFile):
            safe_files.check_output_file(value, overwrite, option_name(dest))
        elif isinstance(value, OutputFolder):
            if os.path.lexists(value) and not os.path.isdir(value):
                raise safe_files.refusal(value, "exists and is not a folder", option_name(dest))
            safe_files.check_writable_folder(Path(value), option_name(dest))


# -- words ----------------------------------------------------------------------------------


def frame_range(text: str) -> tuple[int, int | None]:
    """``a:b`` → (a, b); ``a:`` → (a, None); ``a`` → (a, a + 1). An empty range is an error."""
    try:
        if not text.isascii():
            raise ValueError(text)
        if ":" not in text:
            a = int(text)
            frames = a, a + 1
        else:
            a, b = text.split(":", 1)
            frames = int(a or 0), (int(b) if b else None)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expects A:B, got {shown(text)!r}") from None
    if max(f for f in frames if f is not None) > MAX_FRAMES:
        raise argparse.ArgumentTypeError(f"positions must be ≤ {MAX_FRAMES}, got {text}")
    from mining.pipeline.preflight import check_frames  # here: the preflight's imports cost a second

    try:
        check_frames(frames)
    except ConfigError as e:
        raise argparse.ArgumentTypeError(str(e).removeprefix("--frames ")) from None
    return frames


frame_range.kind = "number"  # type: ignore[attr-defined]  # tests/test_cli_hostile.py tries hostile numbers on it


def add_job_options(p: argparse.ArgumentParser, paths_here: bool = True) -> None:
    """The job options; ``paths_here=False`` where ``--root`` and ``--config`` may name files
    of the machine the job runs on (``mine submit`` in a container's entrypoint, or handed on
    with ``--address http://…``): then they are checked after parsing (``check_paths``), where
    the command runs, not by the parser."""
    p.add_argument("--dataset", help="kitti, kitti-raw, oxford, mcap or synthetic (default: the config's)")
    p.add_argument("--root", type=input_path if paths_here else local_input, help="dataset root folder or pyarrow filesystem URI (s3://…)")
    p.add_argument("--config", type=input_file if paths_here else local_input,
                   help="job config TOML (e.g. jobs/kitti.toml)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value, e.g. geometry.stereo.num_disparities=96")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="source option, e.g. pair=narrow (oxford) or n_frames=2000 (synthetic)")


def job_config(args: argparse.Namespace) -> JobConfig:
    """The job config of the job options (and ``--host``, where the command has it), validated."""
    overrides = list(args.set)
    if args.dataset:
        overrides.append(f"source.dataset={args.dataset!r}".replace("'", '"'))
    if args.root:
        root = args.root if "://" in args.root else Path(args.root).as_posix()  # a URI as given (Path folds its //)
        overrides.append(f'source.root="{root}"')
    if getattr(args, "host", None):
        overrides.append(f"run.bind_host={args.host!r}".replace("'", '"'))
    cfg = load_config(args.config, overrides)
    for o in args.option:
        for k, v in parse_override(o).items():
            cfg.source.options[k] = v
    validate(cfg)  # the options too: an unknown key or a wrong type fails here, naming it
    return cfg


def default_data() -> str:
    """The shared real-data folder: $TUBE_MINER_DATA, else ``../shared/data`` beside the repository."""
    return os.environ.get("TUBE_MINER_DATA", str(REPO.parent / "shared" / "data"))


def add_data_option(p: argparse.ArgumentParser) -> None:
    # a Path default: argparse checks a given --data (type), not the default, which may be absent
    p.add_argument("--data", type=input_folder, default=Path(default_data()),
                   help="the shared real-data folder (default: ../shared/data)")
