"""``mine status``: a catalogue's windows done, failed (with the error) and pending
(``pipeline/status.py``), or the cluster's jobs through Ray Jobs (``pipeline/rayjobs.py``)."""

from __future__ import annotations

import argparse

from mining.checks import path_text
from mining.errors import ConfigError


def add_arguments(sts: argparse.ArgumentParser) -> None:
    sts.add_argument("--out", type=path_text, default="out/catalog", help="catalogue folder or URI")
    sts.add_argument("--verify", action="store_true",
                     help="also check every file's sha256 against the manifest (reads the whole catalogue)")
    sts.add_argument("--address", help="http://HEAD:8265: the cluster's Tube Miner jobs through Ray Jobs instead")
    sts.add_argument("--job", help="with --address: one job's status and the end of its logs")


def run(args: argparse.Namespace) -> int:
    if args.address:
        from mining.pipeline.rayjobs import ray_jobs_status

        return ray_jobs_status(args.address, args.job)
    if args.job:
        raise ConfigError("--job needs --address http://HEAD:8265")
    from mining.pipeline.status import print_status

    return print_status(args.out, verify=args.verify)
