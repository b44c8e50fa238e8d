"""``mine label``: scripted triage — one decision for every tube a predicate selects.

    mine label --out OUT --where "known = false AND n_frames < 5" --verdict not_object
    mine label --out OUT --where "tube_id IN ('kitti/0005/0000012.003')" --tag barrier
    mine label --out OUT --compact

The predicate is ``mine export``'s (``predicate.tubes_query``: one SQL expression over the
tubes and their labels, parsed, never pasted), run on the read-only catalogue
(``catalog/triage.py``); the decision is appended as one new labels part (``labels.append``),
so it never waits for, or is lost beside, a viewer or a running job. ``--compact`` merges the
label files under the writer lock.
"""

from __future__ import annotations

import argparse

from mining.checks import path_text, real
from mining.errors import MiningError, NothingMatched

# Copies of constants whose module loads pyarrow (slow for `mine label --help`); tests/test_labels.py
# checks each equal to its source.
VERDICTS = ("object", "not_object", "part_of", "duplicate")  # catalog/labels.VERDICTS
MAX_TAG_CHARS = 64  # catalog/labels.MAX_TAG_CHARS


def add_arguments(lab: argparse.ArgumentParser) -> None:
    lab.add_argument("--out", type=path_text, default="out/catalog", help="catalogue folder")
    lab.add_argument("--where", help="SQL predicate over the tubes and their labels (as mine export's)")
    lab.add_argument("--verdict", choices=list(VERDICTS), help="set this verdict")
    lab.add_argument("--clear-verdict", action="store_true", help="take the verdict back")
    lab.add_argument("--tag", help=f"add this tag (a free label, at most {MAX_TAG_CHARS} characters)")
    lab.add_argument("--untag", help="remove this tag")
    lab.add_argument("--author", help="who decided (default: the login name)")
    lab.add_argument("--dry-run", action="store_true", help="say how many tubes would be labelled; write nothing")
    lab.add_argument("--compact", action="store_true",
                     help="merge the label files into one (under the writer lock; waits --lock-wait seconds for it)")
    lab.add_argument("--lock-wait", type=real(0.0, 86400.0), default=0.0, metavar="SECONDS",
                     help="--compact: wait this long for a running job's lock (default 0: refuse at once)")


def run(args: argparse.Namespace) -> int:
    return run_label(args.out, args.where, args.verdict, args.clear_verdict, args.tag, args.untag, args.author,
                     args.dry_run, args.compact, args.lock_wait)


def run_label(out: str, where: str | None, verdict: str | None = None, clear_verdict: bool = False,
              tag: str | None = None, untag: str | None = None, author: str | None = None,
              dry_run: bool = False, compact: bool = False, lock_wait_s: float = 0.0) -> int:
    """`mine label`: 0 when labelled (or compacted); NothingMatched (``cli.main``: exit 1) when
    no tube matches; MiningError otherwise (``cli.main``: one line, exit status 2)."""
    from mining.catalog import labels  # here: pyarrow and DuckDB take a while to load
    from mining.catalog.store import Store
    from mining.catalog.triage import decision, matching_tubes

    store = Store(out)
    if not store.root_exists():
        raise MiningError(f"--out {out}: catalogue folder not found")
    if compact:
        if where is not None or verdict or clear_verdict or tag or untag:
            raise MiningError("--compact takes no --where and no decision")
        merged, kept = labels.compact(store, lock_wait_s)
        print(f"mine label: {out}: merged {merged} label files into one ({kept} events)" if merged
              else f"mine label: {out}: nothing to compact ({kept} events in at most one file)")
        return 0
    if where is None:
        raise MiningError("give --where PREDICATE (the tubes to label), e.g. --where \"known = false\"")
    kind, value, op = decision(verdict, clear_verdict, tag, untag)
    tubes = matching_tubes(out, where)
    if not tubes:
        raise NothingMatched(f"no tube matches --where {where!r}; nothing labelled")
    table = labels.events(tubes, kind, value, op, author, via="cli")
    value = table["value"][0].as_py()
    what = ((f"verdict {value}" if op == "set" else "verdict cleared") if kind == "verdict"
            else f"tag {value!r} " + ("added" if op == "set" else "removed"))
    if dry_run:
        print(f"mine label: would label {len(tubes)} tubes: {what} (nothing written: --dry-run)")
        return 0
    rel = labels.append(store, table)
    print(f"mine label: {len(tubes)} tubes: {what} by {table['author'][0].as_py()} → {store.full(rel)}")
    return 0
