"""The command-line words the ``mine`` commands share: the job options (``--config``, ``--set``,
``--dataset``, ``--root``, ``--option``) and the job config they make, the ``A:B`` frame range,
and the shared data folder. Here, below bench and the CLI, so that the command modules of
pipeline/ and bench/ add their own options without importing the CLI."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from mining.config import JobConfig, load_config, parse_override, validate
from mining.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]
SYNTHETIC_JOB = REPO / "jobs" / "synthetic.toml"  # the default job of the synthetic benches, when present


def frame_range(text: str) -> tuple[int, int | None]:
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
    from mining.pipeline.preflight import check_frames  # here: the preflight's imports cost a second

    try:
        check_frames(frames)
    except ConfigError as e:
        raise argparse.ArgumentTypeError(str(e).removeprefix("--frames ")) from None
    return frames


def add_job_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dataset", help="kitti, kitti-raw, oxford, mcap or synthetic (default: the config's)")
    p.add_argument("--root", help="dataset root folder")
    p.add_argument("--config", help="job config TOML (e.g. jobs/kitti.toml)")
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
        overrides.append(f'source.root="{Path(args.root).as_posix()}"')
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
    p.add_argument("--data", default=default_data(), help="the shared real-data folder (default: ../shared/data)")
