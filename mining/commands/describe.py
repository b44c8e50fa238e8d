"""``mine describe``: a descriptor for every tube of the catalogue, stored beside it
(``discovery/describe.py``); only the sequences whose tubes changed since the last run are
computed again.

    mine describe --out OUT
"""

from __future__ import annotations

import argparse

from mining.checks import path_text
from mining.errors import MiningError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=path_text, default="out/catalog", help="catalogue folder")
    p.add_argument("--force", action="store_true", help="describe every sequence again, even those up to date")


def run(args: argparse.Namespace) -> int:
    from mining.catalog.store import Store  # here: pyarrow and DuckDB take a while to load
    from mining.discovery.describe import describe
    from mining.discovery.descriptors import DESCRIPTOR_VERSION, DIM

    store = Store(args.out)
    if not store.root_exists():
        raise MiningError(f"--out {args.out}: catalogue folder not found")
    done = describe(store, args.force)
    if not done.computed and not done.kept:
        raise MiningError(f"--out {args.out}: no finished sequence to describe (`mine status` says what is running)")
    n_new, n_kept = sum(c[2] for c in done.computed), sum(c[2] for c in done.kept)
    print(f"mine describe: {len(done.computed)} sequences described ({n_new} tubes), {len(done.kept)} up to date "
          f"({n_kept} tubes), {len(done.removed)} removed; descriptors {DESCRIPTOR_VERSION}, {DIM} components "
          "(SELECT * FROM tube_descriptors)")
    return 0
