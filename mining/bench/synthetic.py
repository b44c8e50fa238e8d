"""``mine eval synthetic``: mine a synthetic sequence and score it against its exact ground truth.

The driver of the synthetic protocol (``mining/eval/synthetic.py``, which defines the
protocol and its metrics): it runs the pipeline on the synthetic source, keeps each
frame's ground truth compactly, and hands both to ``evaluate_synthetic``. It also keeps
each frame's proposal masks, before and after the geometric filter, for the recall funnel
(``mining/eval/funnel.py``: where between proposal and selection each object is lost), and
scores discovery over the tubes on unknown objects (``mining/eval/discovery.py``): the tubes
become catalogue rows as the pipeline writes them (``catalog/rows.py``), whose descriptors and
grouping are the product's own (``mining/discovery/``).
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Iterator

import numpy as np

from mining.catalog import safe_files
from mining.catalog.rows import RunInfo, frame_rows, to_table, tube_row
from mining.checks import count, input_file, output_file, positive_float
from mining.config import JobConfig, load_config
from mining.errors import InputError
from mining.discovery.descriptors import DESCRIPTOR_VERSION, descriptors
from mining.discovery.groups import centre_distances, group_vectors
from mining.eval.discovery import discovery_metrics, format_discovery
from mining.eval.funnel import StageFrame, evaluate_funnel, format_funnel, stage_frame
from mining.eval.synthetic import GtFrame, evaluate_synthetic, format_synthetic, gt_frame
from mining.pipeline.arguments import add_overwrite_option
from mining.pipeline.frames import frame_records
from mining.pipeline.mine import mine_tubes
from mining.progress import Ticker
from mining.proposals.make import classifiers_line
from mining.score.unary import unary_groups, unary_line
from mining.sources import open_source
from mining.types import MinedTube, TrackingFrame


def run_synthetic(sequence: str, n_frames: int, cfg: JobConfig, start: int = 0, stop: int | None = None,
                  **protocol) -> tuple[list[MinedTube], dict]:
    """Mine a synthetic sequence of ``n_frames`` frames over positions [start, stop) and evaluate.

    ``n_frames`` is the source's sequence length (it fixes the world); ``stop`` defaults to it.
    ``protocol`` takes ``evaluate_synthetic``'s keyword arguments. The results carry the
    ground truth as ``results["truths"]`` (frame → GtFrame) for re-evaluation, the recall
    funnel (``evaluate_funnel``, same protocol) as ``results["funnel"]``, discovery over the tubes
    on unknown objects (``discovery``) as ``results["discovery"]`` and the wall time as
    ``results["seconds"]``.
    """
    options = {k: v for k, v in cfg.source.options.items() if k != "n_frames"}
    src = open_source("synthetic", None, n_frames=n_frames, **options)
    plan = src.plan(sequence)
    stop = len(plan) if stop is None else stop
    truths: dict[int, GtFrame] = {}
    # the funnel's proposal stages: the proposer's masks, and those the geometric filter kept
    stages: dict[str, dict[int, StageFrame]] = {"proposed": {}, "observed": {}}
    t0 = time.perf_counter()

    ticker = Ticker(f"synthetic {sequence}", stop - start)

    def frames() -> Iterator[TrackingFrame]:
        # keep only the compact truth: a FrameRecord holds full-frame arrays
        for k, rec in enumerate(frame_records(src, plan, start, stop, cfg)):
            ticker.tick(k)
            if rec.frame.truth is None:
                raise InputError("synthetic frame without ground truth", frame=rec.frame.index)
            truths[rec.frame.index] = gt_frame(rec.frame.truth)
            stages["proposed"][rec.frame.index] = stage_frame(rec.proposals)
            stages["observed"][rec.frame.index] = stage_frame(rec.tracking.observations.proposals)
            yield rec.tracking

    mined = mine_tubes(frames(), cfg)
    ticker.close()
    t1 = time.perf_counter()
    results = evaluate_synthetic(mined, truths, **protocol)
    shared = ("iou_threshold", "similarity", "min_visible_px", "max_depth_m", "track_cover")
    results["funnel"] = evaluate_funnel(truths, mined, stages, alpha=cfg.score.alpha, beta=cfg.score.beta,
                                        groups=unary_groups(cfg.score, cfg.proposals.proposer),
                                        tube_split=results["tube_split"],
                                        **{k: v for k, v in protocol.items() if k in shared})
    results["discovery"] = discovery(mined, results["tube_kind"], RunInfo("synthetic", sequence, "eval", "", plan.calib.bf))
    results["seconds"] = {"mine": t1 - t0, "eval": time.perf_counter() - t1}
    results["sequence"] = sequence
    results["truths"] = truths
    return mined, results


def discovery(mined: list[MinedTube], tube_kind: dict[int, str], run: RunInfo) -> dict:
    """``discovery_metrics`` over the selected tubes with a true kind (those on unknown objects),
    in tube id order: their rows as the pipeline writes them, the product's descriptors of them,
    its grouping (``group_vectors``' defaults for that many tubes) and centre distances."""
    on = sorted((m for m in mined if m.selected and m.tube.tube_id in tube_kind), key=lambda m: m.tube.tube_id)
    ids = [str(m.tube.tube_id) for m in on]
    tubes = to_table([tube_row(m, t, run) for m, t in zip(on, ids)], "tubes")
    frames = to_table([r for m, t in zip(on, ids) for r in frame_rows(m, t)], "tube_frames")
    vectors = descriptors(tubes, frames)
    kinds = [tube_kind[m.tube.tube_id] for m in on]
    labels, _ = group_vectors(vectors)
    out = discovery_metrics(vectors, kinds, labels, centre_distances(vectors, labels))
    # the rows, so that sequences' sections can be pooled later (``pooled_discovery``)
    return out | {"descriptor_version": DESCRIPTOR_VERSION,
                  "rows": [{"tube_id": int(m.tube.tube_id), "kind": k, "group": int(g), "vector": v.tolist()}
                           for m, k, g, v in zip(on, kinds, labels, vectors)]}


def pool_rows(path: str) -> tuple[list[dict], str | None]:
    """The discovery rows and sequence of an earlier ``--json`` result, of this descriptor recipe."""
    try:
        with open(path, encoding="utf-8") as f:
            doc = json.load(f)
        rows, version = doc["discovery"]["rows"], doc["discovery"]["descriptor_version"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InputError(f"not a `mine eval synthetic --json` result with discovery rows ({type(e).__name__})",
                         path) from None
    if version != DESCRIPTOR_VERSION:
        raise InputError(f"descriptors of recipe {version}, this one is {DESCRIPTOR_VERSION}: run it again", path)
    return rows, doc.get("sequence")


def pooled_discovery(section: dict, paths: list[str]) -> dict:
    """``discovery_metrics`` over this sequence's tubes and those of earlier ``--json`` results
    (``paths``), grouped together as ``mine group`` groups a catalogue's whole unknown set."""
    rows, sequences = list(section["rows"]), []
    for path in paths:
        more, sequence = pool_rows(path)
        rows += more
        sequences.append(sequence)
    vectors = np.array([r["vector"] for r in rows], np.float64).reshape(len(rows), -1)
    labels, _ = group_vectors(vectors)
    out = discovery_metrics(vectors, [r["kind"] for r in rows], labels, centre_distances(vectors, labels))
    return out | {"pooled_with": sequences}


def run_synthetic_eval(sequence: str, n_frames: int, cfg: JobConfig, json_out: str | None = None,
                       overwrite: bool = False, pool: list[str] | None = None, **protocol) -> int:
    """`mine eval synthetic`: run, print the table, optionally write the results as JSON to
    ``json_out``; ``pool``: earlier results whose discovery rows are pooled with this sequence's."""
    for path in pool or []:  # before the mining: a bad file is found in milliseconds, not minutes
        pool_rows(path)
    mined, results = run_synthetic(sequence, n_frames, cfg, **protocol)
    if pool:
        results["discovery"]["pooled"] = pooled_discovery(results["discovery"], pool)
    print(f"synthetic {sequence}, {n_frames} frames, proposer {cfg.proposals.proposer}: "
          f"mined in {results['seconds']['mine']:.0f} s")
    print(format_synthetic(results))
    print(format_discovery(results["discovery"]))
    if pool:
        print("pooled with " + ", ".join(map(str, results["discovery"]["pooled"]["pooled_with"])) + ": "
              + format_discovery(results["discovery"]["pooled"]))
    print(format_funnel(results["funnel"]))
    print(classifiers_line(cfg.proposals.proposer))
    print(unary_line(cfg.score, cfg.proposals.proposer))
    if json_out:
        doc = {k: v for k, v in results.items() if k != "truths"}
        doc |= {"proposer": cfg.proposals.proposer, "n_frames": n_frames}
        safe_files.write_file(json_out, json.dumps(doc, indent=1, default=_plain).encode(), overwrite)
    return 0


def _plain(x):
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(type(x).__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine eval synthetic``'s options (a config and overrides, no source: the sequence is synthetic)."""
    p.add_argument("--sequence", default="0000")
    p.add_argument("--n-frames", type=count(), default=100, help="frames of the sequence (default 100)")
    p.add_argument("--config", type=input_file, default=None, help="job TOML (default: built-in defaults)")
    p.add_argument("--set", action="append", default=[], help="config override KEY=VALUE")
    p.add_argument("--min-visible-px", type=count(0, 10**8), default=None,
                   help="ignore objects with fewer visible pixels (default: the protocol's)")
    p.add_argument("--max-depth-m", type=positive_float(1e4), default=None,
                   help="ignore objects farther than this (default: the protocol's)")
    p.add_argument("--json", type=output_file, default=None, metavar="PATH",
                   help="also write the results (metrics, tube counts, known/unknown calls) as JSON here")
    p.add_argument("--pool", type=input_file, action="append", default=[], metavar="JSON",
                   help="an earlier --json result of another sequence: discovery is also scored over its tubes "
                        "and these together, grouped as one catalogue (repeatable)")
    add_overwrite_option(p, "the --json file")


def run(args: argparse.Namespace) -> int:
    """``mine eval synthetic``."""
    protocol = {"max_depth_m": args.max_depth_m}
    if args.min_visible_px is not None:
        protocol["min_visible_px"] = args.min_visible_px
    return run_synthetic_eval(args.sequence, args.n_frames, load_config(args.config, args.set), json_out=args.json,
                              overwrite=args.overwrite, pool=args.pool, **protocol)
