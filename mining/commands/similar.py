"""``mine similar``: find more like this — the k tubes nearest a tube by cosine distance over
their descriptors (``--vector descriptor``, run ``mine describe`` first) or their image
embeddings (``--vector embedding``, run ``mine embed`` first); ``discovery/similar.py``.

    mine similar --out OUT kitti/0005/0000012.003 -k 20 --where "call = 'unknown'"
"""

from __future__ import annotations

import argparse
import json

from mining.checks import count, path_text
from mining.errors import MiningError
from mining.names import tube_id_argument

DEFAULT_K = 10  # ours: a screenful


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("tube_id", type=tube_id_argument, help="the tube to find more like (e.g. kitti/0005/0000012.003)")
    p.add_argument("--out", type=path_text, default="out/catalog", help="catalogue folder")
    p.add_argument("-k", type=count(1, 10_000), default=DEFAULT_K, help=f"how many tubes (default {DEFAULT_K})")
    p.add_argument("--where", help="SQL predicate over the tubes and their labels (as mine export's): search only these")
    p.add_argument("--vector", choices=["descriptor", "embedding"], default="descriptor",
                   help="compare the tubes' descriptors (mine describe, the default) or their image embeddings (mine embed)")
    p.add_argument("--model", help="with --vector embedding: which model (its file name or a sha256 prefix), where "
                                   "the catalogue holds embeddings of several")
    p.add_argument("--format", choices=["table", "json"], default="table")


def run(args: argparse.Namespace) -> int:
    from mining.discovery.similar import SHOWN, nearest  # here: pyarrow and DuckDB take a while to load

    if args.model is not None and args.vector != "embedding":
        raise MiningError("--model names an embedding model: give it with --vector embedding")
    rows = nearest(args.out, args.tube_id, args.k, args.where, args.vector, args.model)
    if not rows:
        raise MiningError(f"no tube matches --where {args.where!r}")
    if args.format == "json":
        print(json.dumps(rows, indent=1))
        return 0
    cells = [[("" if r[c] is None else f"{r[c]:.4g}" if c == "distance" else str(r[c])) for c in SHOWN] for r in rows]
    widths = [max(len(c), *(len(row[j]) for row in cells)) for j, c in enumerate(SHOWN)]
    print("  ".join(c.ljust(w) for c, w in zip(SHOWN, widths)))
    for row in cells:
        print("  ".join(v.ljust(w) for v, w in zip(row, widths)))
    return 0
