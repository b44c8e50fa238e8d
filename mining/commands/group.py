"""``mine group``: group the unknown set by density (HDBSCAN over the tube descriptors,
``discovery/groups.py``) into the ``tube_groups`` table; describes what is stale first.

    mine group --out OUT [--min-size 10]
    mine query --out OUT "SELECT \\"group\\", count(*) FROM tube_groups GROUP BY 1 ORDER BY 2 DESC"
    mine label --out OUT --group 3 --tag barrier --dry-run
"""

from __future__ import annotations

import argparse

from mining.checks import count, path_text
from mining.errors import MiningError

# Copies of constants whose module loads scikit-learn (slow for `mine group --help`);
# tests/test_discovery.py checks each equal to its source.
MIN_GROUP_SIZE = 10  # discovery/groups.MIN_GROUP_SIZE
MAX_GROUPS = 400  # discovery/groups.MAX_GROUPS
MIN_SAMPLES = 5  # discovery/groups.MIN_SAMPLES
SELECTIONS = ("leaf", "eom")  # discovery/groups.SELECTIONS, the first the default


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=path_text, default="out/catalog", help="catalogue folder")
    p.add_argument("--min-size", type=count(2, 1_000_000),
                   help=f"fewest tubes in a group (HDBSCAN min_cluster_size; default: {MIN_GROUP_SIZE}, or enough "
                        f"that at most {MAX_GROUPS} groups fit)")
    p.add_argument("--selection", choices=SELECTIONS, default=SELECTIONS[0],
                   help="HDBSCAN's choice of groups: leaf (default, the finest stable ones) or eom (excess of mass)")
    p.add_argument("--min-samples", type=count(1, 1000), default=MIN_SAMPLES,
                   help=f"neighbours that make a tube's region dense (HDBSCAN min_samples; default {MIN_SAMPLES})")
    p.add_argument("--force", action="store_true", help="group again even when nothing changed")


def run(args: argparse.Namespace) -> int:
    from mining.catalog.store import Store  # here: scikit-learn, pyarrow and DuckDB take a while to load
    from mining.discovery.describe import describe
    from mining.discovery.groups import group_unknown

    store = Store(args.out)
    if not store.root_exists():
        raise MiningError(f"--out {args.out}: catalogue folder not found")
    described = describe(store)
    g = group_unknown(store, args.min_size, args.min_samples, args.selection, args.force)
    if not g.tubes:
        raise MiningError(f"--out {args.out}: the unknown set is empty (no selected tube with call 'unknown'): "
                          "nothing to group")
    new = f"described {len(described.computed)} sequences first; " if described.computed else ""
    how = f"grouped in {g.seconds:.1f} s" if g.recomputed else "unchanged since the last run"
    print(f"mine group: {new}{g.tubes} unknown tubes in {g.groups} groups, {g.noise} in none (group -1); {how} "
          "(SELECT * FROM tube_groups)")
    return 0
