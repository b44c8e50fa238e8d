"""``mine submit``: plan windows and mine them on Ray (a local Ray, a running cluster, or a job
handed to a cluster through Ray Jobs). The work is ``pipeline/submit.py``'s (``mine_on_ray``)
and ``pipeline/rayjobs.py``'s; this module parses and reports."""

from __future__ import annotations

import argparse
from pathlib import Path

from mining.checks import MAX_WORKERS, output_folder, seconds, worker_count
from mining.errors import ConfigError
from mining.pipeline.arguments import add_job_options, frame_range, job_config


def add_arguments(smt: argparse.ArgumentParser) -> None:
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
    smt.add_argument("--host", metavar="IP", help="local Ray only: 127.0.0.1 (the config's run.bind_host by default), "
                                                  "or 0.0.0.0 / :: for every interface; Ray keeps no other address to "
                                                  "itself, so any other is refused. Ray's ports run code "
                                                  "unauthenticated: every interface only on a network you trust")
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


def check_out_beside_root(out: str, root: str | None) -> None:
    """ConfigError when the catalogue ``out`` would lie inside the source's ``root`` (local folders,
    or one URI under another): the source's next listing would read the catalogue's folders as data."""
    if not root or not out:
        return
    if "://" in out or "://" in root:  # URIs: the path before any ?options, one under the other
        bare_out, bare_root = (u.split("?")[0].rstrip("/") for u in (out, root))
        inside = "://" in out and "://" in root and bare_out.startswith(bare_root + "/")
    else:
        inside = Path(out).resolve().is_relative_to(Path(root).resolve())
    if inside:
        raise ConfigError(f"--out {out} lies inside the source's root {root}: the source would list the catalogue "
                          "as data on the next submit; put the catalogue beside the data, not in it")


def run(args: argparse.Namespace) -> int:
    """0 when every window was mined, 1 when some failed (the summary says which)."""
    cfg = job_config(args)
    check_out_beside_root(args.out, cfg.source.root)
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
