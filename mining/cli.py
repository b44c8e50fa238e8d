"""The ``mine`` command line."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

from mining.config import JobConfig, load_config, parse_override
from mining.errors import ConfigError, MiningError


def _frames(text: str) -> tuple[int, int | None]:
    """``a:b`` → (a, b); ``a:`` → (a, None); ``a`` → (a, a + 1)."""
    try:
        if ":" not in text:
            a = int(text)
            return a, a + 1
        a, b = text.split(":", 1)
        return int(a or 0), (int(b) if b else None)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--frames expects a:b, got {text!r}") from None


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
    cfg = load_config(args.config, overrides)
    for o in args.option:
        for k, v in parse_override(o).items():
            cfg.source.options[k] = v
    return cfg


def _open(cfg: JobConfig):
    from mining.sources import open_source

    return open_source(cfg.source.dataset, cfg.source.root or None, **cfg.source.options)


def cmd_inspect_geometry(args: argparse.Namespace) -> int:
    from mining.pipeline.inspect_geometry import inspect_geometry

    cfg = _job_config(args)
    source = _open(cfg)
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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mine", description="Tube Miner: mine generic object tubes from stereo video.")
    sub = parser.add_subparsers(dest="command", required=True)

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
    return parser


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (MiningError, ConfigError) as e:
        print(f"mine: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
