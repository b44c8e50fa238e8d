"""``mine label``: scripted triage — one decision for every tube a predicate selects.

    mine label --out OUT --where "known = false AND n_frames < 5" --verdict not_object
    mine label --out OUT --where "tube_id IN ('kitti/0005/0000012.003')" --tag barrier
    mine label --out OUT --group 3 --tag barrier --dry-run        (a group of `mine group`)
    mine label --out OUT --like kitti/0005/0000012.003 --within 0.02 --tag barrier
    mine label --out OUT --undo-like kitti/0005/0000012.003       (take that propagation back)
    mine label --out OUT --compact

The predicate is ``mine export``'s (``predicate.tubes_query``: one SQL expression over the
tubes and their labels, parsed, never pasted), run on the read-only catalogue
(``catalog/triage.py``); the decision is appended as one new labels part (``labels.append``),
so it never waits for, or is lost beside, a viewer or a running job. ``--compact`` merges the
label files under the writer lock. ``--group`` and ``--like`` choose the tubes from what
discovery derived (``discovery/propagate.py``): a group of the unknown set, or the unlabelled tubes
within a cosine distance of one tube, whose labels then carry their source and distance.
"""

from __future__ import annotations

import argparse

from mining.checks import count, path_text, real
from mining.errors import MiningError, NothingMatched
from mining.names import tube_id_argument

# Copies of constants whose module loads pyarrow (slow for `mine label --help`); tests/test_labels.py
# checks each equal to its source.
VERDICTS = ("object", "not_object", "part_of", "duplicate")  # catalog/labels.VERDICTS
MAX_TAG_CHARS = 64  # catalog/labels.MAX_TAG_CHARS
MAX_DISTANCE = 2.0  # cosine distance lies in [0, 2]


def add_arguments(lab: argparse.ArgumentParser) -> None:
    lab.add_argument("--out", type=path_text, default="out/catalog", help="catalogue folder")
    lab.add_argument("--where", help="SQL predicate over the tubes and their labels (as mine export's)")
    lab.add_argument("--group", type=count(-1, 10**9), metavar="G",
                     help="the tubes of group G of `mine group` (-1: those in no group); with --where, those it selects")
    lab.add_argument("--like", type=tube_id_argument, metavar="TUBE_ID", help="the unlabelled tubes near this one (needs --within); each "
                     "label records TUBE_ID and its distance (propagated)")
    lab.add_argument("--within", type=real(0.0, MAX_DISTANCE), metavar="D",
                     help="--like: cosine distance of the descriptors, at most D (0 … 2)")
    lab.add_argument("--undo-like", type=tube_id_argument, metavar="TUBE_ID",
                     help="take back every label propagated from TUBE_ID that no later decision replaced")
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
    chosen = [f for f, v in (("--group", args.group), ("--like", args.like), ("--undo-like", args.undo_like))
              if v is not None]
    if (args.within is not None) != (args.like is not None):
        raise MiningError("--like TUBE_ID and --within D go together")
    if not chosen:
        return run_label(args.out, args.where, args.verdict, args.clear_verdict, args.tag, args.untag, args.author,
                         args.dry_run, args.compact, args.lock_wait)
    if len(chosen) > 1 or args.compact:
        raise MiningError(f"give one of --group, --like, --undo-like, --compact (got {', '.join(chosen)})")
    if args.undo_like is not None:
        if args.where is not None or args.verdict or args.clear_verdict or args.tag or args.untag:
            raise MiningError("--undo-like takes no --where and no decision: it unsets what the propagation set")
        return undo_like(args.out, args.undo_like, args.author, args.dry_run)
    if args.group is not None:
        return label_group(args.out, args.group, args.where, args.verdict, args.clear_verdict, args.tag, args.untag,
                           args.author, args.dry_run)
    return label_like(args.out, args.like, args.within, args.where, args.verdict, args.tag, args.author, args.dry_run)


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


def _what(kind: str, value: str | None, op: str) -> str:
    return ((f"verdict {value}" if op == "set" else "verdict cleared") if kind == "verdict"
            else f"tag {value!r} " + ("added" if op == "set" else "removed"))


def _apply(out: str, tubes: list[tuple[str, str, str]], kind: str, value: str | None, op: str, author: str | None,
           dry_run: bool, how: str, source: str | None = None, distances: list[float] | None = None) -> int:
    """Write (or, ``dry_run``, count) one decision's events for ``tubes``; ``how`` says which tubes."""
    from mining.catalog import labels
    from mining.catalog.store import Store

    via = "propagated" if source is not None else "cli"
    table = labels.events(tubes, kind, value, op, author, via=via, source_tube=source, distances=distances)
    what = _what(kind, table["value"][0].as_py(), op)
    if dry_run:
        print(f"mine label: would label {len(tubes)} tubes {how}: {what} (nothing written: --dry-run)")
        return 0
    store = Store(out)
    rel = labels.append(store, table)
    print(f"mine label: {len(tubes)} tubes {how}: {what} by {table['author'][0].as_py()} → {store.full(rel)}")
    return 0


def _catalogue(out: str) -> None:
    from mining.catalog.store import Store

    if not Store(out).root_exists():
        raise MiningError(f"--out {out}: catalogue folder not found")


def label_group(out: str, group: int, where: str | None, verdict: str | None, clear_verdict: bool, tag: str | None,
                untag: str | None, author: str | None, dry_run: bool) -> int:
    """``mine label --group G``: one decision for every tube of group G of ``tube_groups``."""
    from mining.catalog.triage import decision
    from mining.discovery.propagate import in_group

    _catalogue(out)
    kind, value, op = decision(verdict, clear_verdict, tag, untag)
    tubes = in_group(out, group, where)
    if not tubes:
        raise NothingMatched(f"group {group} holds no tube" + (f" that --where {where!r} selects" if where else "")
                             + "; nothing labelled")
    return _apply(out, tubes, kind, value, op, author, dry_run, f"of group {group}")


def label_like(out: str, source: str, within: float, where: str | None, verdict: str | None, tag: str | None,
               author: str | None, dry_run: bool) -> int:
    """``mine label --like TUBE --within D``: propagate a verdict or a tag to the unlabelled
    tubes within cosine distance D of TUBE; each event names TUBE and its distance."""
    from mining.catalog.triage import decision
    from mining.discovery.propagate import like

    _catalogue(out)
    if verdict is None and tag is None:
        raise MiningError("--like propagates a decision: give --verdict V or --tag T")
    kind, value, op = decision(verdict, False, tag, None)
    near = like(out, source, within, where)
    if not near:
        raise NothingMatched(f"no unlabelled tube within distance {within} of {source}; nothing labelled")
    if dry_run:
        for (_, _, tube_id), d in near:
            print(f"{tube_id}  {d:.4g}")
    return _apply(out, [t for t, _ in near], kind, value, op, author, dry_run,
                  f"within {within} of {source}", source, [d for _, d in near])


def undo_like(out: str, source: str, author: str | None, dry_run: bool) -> int:
    """``mine label --undo-like TUBE``: unset what propagations from TUBE set and nobody changed since."""
    from mining.catalog import labels
    from mining.catalog.store import Store
    from mining.discovery.propagate import propagated_from

    _catalogue(out)
    found = propagated_from(out, source)
    if not found:
        raise NothingMatched(f"no label propagated from {source} is in force; nothing taken back")
    tables = [labels.events([t for t, _ in tubes], kind, value, "unset", author, via="propagated", source_tube=source,
                            distances=[d for _, d in tubes]) for (kind, value), tubes in found.items()]
    n = sum(len(t) for t in tables)
    what = ", ".join(f"{_what(kind, value, 'unset')} on {len(tubes)}" for (kind, value), tubes in found.items())
    if dry_run:
        print(f"mine label: would take back {n} labels propagated from {source}: {what} (nothing written: --dry-run)")
        return 0
    import pyarrow as pa

    store = Store(out)
    rel = labels.append(store, pa.concat_tables(tables))
    print(f"mine label: took back {n} labels propagated from {source}: {what} → {store.full(rel)}")
    return 0
