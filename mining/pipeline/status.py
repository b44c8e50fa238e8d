"""``mine status``: every planned window of a catalogue, done, failed (with its error) or
pending; and every output file that is not as the manifest recorded it (``integrity.py``:
sizes, and checksums with ``--verify``), with what a resubmission recomputes."""

from __future__ import annotations

from dataclasses import dataclass

from mining.catalog.integrity import Damage, sequence_damage, window_damage
from mining.catalog.layout import JOB, JobRecord, manifest_path
from mining.catalog.lock import current_writer, describe
from mining.catalog.store import Store
from mining.errors import InputError
from mining.proposals.make import classifiers_line


@dataclass
class WindowStatus:
    dataset: str
    sequence: str
    window: str
    status: str  # done | failed | pending
    attempts: int
    error: str


def job_status(out: str) -> list[WindowStatus]:
    store = Store(out)
    job = JobRecord.load(store)
    if job is None:
        raise InputError("no mining job here (job.json missing): run `mine submit --out` first", store.full(JOB))
    rows = []
    for w in job.windows:
        m = manifest_path(w.dataset, w.sequence, w.name)
        if store.exists(m):
            try:
                r = store.read_table(m).to_pylist()[0]
            except (InputError, IndexError):  # named under integrity; a resubmission runs the window again
                rows.append(WindowStatus(w.dataset, w.sequence, w.name, "pending", 0, "manifest row unreadable"))
                continue
            status = r["status"] if r["params_hash"] == job.params_hash else "pending"
            rows.append(WindowStatus(w.dataset, w.sequence, w.name, status, r["attempts"], r["error"] or ""))
        else:
            rows.append(WindowStatus(w.dataset, w.sequence, w.name, "pending", 0, ""))
    return rows


def job_damage(out: str, rows: list[WindowStatus], verify: bool = False) -> list[Damage]:
    """Every file of the job not as recorded: the parts of done windows, the compacted
    files of finalized sequences, unreadable manifest rows."""
    store = Store(out)
    job = JobRecord.load(store)
    by_name = {w.name: w for w in job.windows} if job else {}
    out_: list[Damage] = []
    for r in rows:
        w = by_name.get(r.window)
        if w is None:
            continue
        if r.error == "manifest row unreadable":
            out_.append(Damage(manifest_path(w.dataset, w.sequence, w.name), "unreadable", f"window {w.name}"))
        elif r.status == "done":
            out_ += window_damage(store, w, verify)
    for d, seq in dict.fromkeys((w.dataset, w.sequence) for w in by_name.values()):
        out_ += sequence_damage(store, d, seq, verify) or []
    return out_


def _repair(d: Damage) -> str:
    kind, _, name = d.owner.partition(" ")
    return f"runs window {name} again" if kind == "window" else f"stitches sequence {name} again"


def print_status(out: str, verify: bool = False) -> int:
    """Print the windows' states and every damaged or missing file; exit 1 when any window
    failed or any file is damaged, 0 otherwise."""
    rows = job_status(out)
    counts = {s: sum(r.status == s for r in rows) for s in ("done", "failed", "pending")}
    print(f"{out}: {len(rows)} windows: {counts['done']} done, {counts['failed']} failed, {counts['pending']} pending")
    job = JobRecord.load(Store(out))
    proposer = (job.config.get("proposals") or {}).get("proposer") if job else None
    if proposer:
        print(classifiers_line(str(proposer)))
    for r in rows:
        line = f"{r.status:8s} {r.dataset}/{r.window}  attempts {r.attempts}"
        if r.error:
            line += "  " + r.error.strip().splitlines()[0]
        if r.status != "done":
            print(line)
    writer = current_writer(Store(out))
    if writer:
        print(f"being written now by {describe(writer)}: files of steps in flight may show as damaged below")
    damage = job_damage(out, rows, verify)
    for d in damage:
        print(f"damaged  {d.path}: {d.reason} (a resubmission {_repair(d)})")
    checked = "sizes and checksums" if verify else "sizes; --verify also checks checksums"
    print(f"integrity: {len(damage)} damaged or missing file(s) ({checked})")
    return 1 if counts["failed"] or damage else 0
