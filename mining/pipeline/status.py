"""``mine status``: every planned window of a catalogue, done, failed (with its error) or pending."""

from __future__ import annotations

from dataclasses import dataclass

from mining.catalog.layout import JOB, JobRecord, manifest_path
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
            r = store.read_table(m).to_pylist()[0]
            status = r["status"] if r["params_hash"] == job.params_hash else "pending"
            rows.append(WindowStatus(w.dataset, w.sequence, w.name, status, r["attempts"], r["error"] or ""))
        else:
            rows.append(WindowStatus(w.dataset, w.sequence, w.name, "pending", 0, ""))
    return rows


def print_status(out: str) -> int:
    """Print the windows' states; exit 1 when any failed, 0 otherwise."""
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
    return 1 if counts["failed"] else 0
