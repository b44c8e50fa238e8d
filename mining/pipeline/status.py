"""``mine status``: every planned window of a catalogue, and every sequence's stitch.

A window is

* ``done`` or ``failed``: its manifest row says so, with this job's params (a failed
  one shows the first line of its error: the step, the exception type, the message);
* ``running``: a live driver has started its work and not recorded the result
  (``running.py``: the marker, its driver's host and pid, since when);
* ``pending``: neither — never started, or its driver is gone (killed, Ctrl-C).

A sequence is ``stitched`` (its catalogue holds exactly its done windows), ``failed``
(its stitch failed: the manifest's ``stitch`` row, with the error) or ``pending``.
Every output file that is not as the manifest recorded it (``integrity.py``: sizes, and
checksums with ``--verify``) is named, with what a resubmission recomputes; so is every
record that does not read (``catalog/records.py``: a truncated or foreign marker, an
unreadable manifest row), with why. The records are read with the same predicates resume
uses (``resume.py``).
Exits 1 when any window or stitch failed, a sequence could not be planned, or any file is damaged.
What a job left is listed with counts and sizes, one named (``leftovers.py``): observation
caches, temporary files of unfinished writes (``Store.temporaries``) and foreign files in the
cache folders; or one line saying nothing is left. Readers skip them and the next ``mine
submit`` removes the caches of stitched sequences and the temporaries, so they change no exit
status.
"""

from __future__ import annotations

from dataclasses import dataclass

from mining.catalog.integrity import Damage, check_versions, sequence_damage, unreadable_damage, window_damage
from mining.catalog.labels import DAMAGED, damaged_label_files
from mining.catalog.layout import JOB, STITCH_ROW, manifest_path
from mining.catalog.records import JobRecord, ManifestRow, SequenceMarker, Unreadable, UnreadableRecord
from mining.catalog.lock import current_writer, describe
from mining.catalog.store import Store
from mining.errors import InputError
from mining.pipeline.leftovers import leftover_lines
from mining.pipeline.running import driver_alive, read_marker
from mining.proposals.make import classifiers_line


UNREADABLE_ROW = "manifest row unreadable"  # the error of a window whose row does not read


@dataclass
class WindowStatus:
    dataset: str
    sequence: str
    window: str
    status: str  # done | failed | running | pending
    attempts: int
    error: str
    running: str = ""  # for a running window: its step, driver and start time


@dataclass
class SequenceStatus:
    dataset: str
    sequence: str
    status: str  # stitched | failed | pending
    attempts: int
    error: str


def _running(marker: dict) -> str:
    return (f"{marker.get('step', '?')} step, driver pid {marker.get('driver_pid')} on {marker.get('driver_host')}, "
            f"since {marker.get('started')}")


def job_status(out: str) -> list[WindowStatus]:
    store = Store(out)
    job = JobRecord.load(store)
    if job is None:
        raise InputError("no mining job here (job.json missing): run `mine submit --out` first", store.full(JOB))
    rows = []
    for w in job.windows:
        status, attempts, error = "pending", 0, ""
        r = ManifestRow.load(store, w.dataset, w.sequence, w.name)
        if isinstance(r, Unreadable):  # named under integrity; a resubmission runs the window again
            rows.append(WindowStatus(w.dataset, w.sequence, w.name, "pending", 0, UNREADABLE_ROW))
            continue
        if r is not None:
            if r.params_hash == job.params_hash:
                status, error = r.status, r.error
            attempts = r.attempts
        marker = read_marker(store, w)
        if marker is not None and marker.get("params_hash") == job.params_hash and driver_alive(marker):
            rows.append(WindowStatus(w.dataset, w.sequence, w.name, "running", attempts, error, _running(marker)))
        else:
            rows.append(WindowStatus(w.dataset, w.sequence, w.name, status, attempts, error))
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
        if r.error == UNREADABLE_ROW:
            out_.append(Damage(manifest_path(w.dataset, w.sequence, w.name), "unreadable", f"window {w.name}"))
        elif r.status == "done":
            out_ += window_damage(store, w, verify)
    for d, seq in dict.fromkeys((w.dataset, w.sequence) for w in by_name.values()):
        # The compacted files are what every query reads (and checks by checksum, views.py):
        # their checksums always; the parts' only with --verify.
        out_ += sequence_damage(store, d, seq, True) or []
        if isinstance(row := ManifestRow.load(store, d, seq, STITCH_ROW), Unreadable):  # resume stitches it again
            out_.append(unreadable_damage(row, f"sequence {seq}"))
    # Label files are read whole by every query, so their digests are checked here always (they are small).
    out_ += [Damage(rel, why.split(";")[0], "labels") for rel, why in damaged_label_files(store).items()]
    return out_


def _repair(d: Damage) -> str:
    kind, _, name = d.owner.partition(" ")
    if kind == "labels":  # no copy to recompute them from: set aside, so the other labels read
        return f"moves it to {DAMAGED}/; its labels are lost"
    return f"runs window {name} again" if kind == "window" else f"stitches sequence {name} again"


def sequence_status(out: str, windows: list[WindowStatus] | None = None) -> list[SequenceStatus]:
    """The stitch of every sequence the job planned."""
    store = Store(out)
    job = JobRecord.load(store)
    if job is None:
        raise InputError("no mining job here (job.json missing): run `mine submit --out` first", store.full(JOB))
    windows = job_status(out) if windows is None else windows
    seqs: dict[tuple[str, str], set[str]] = {}
    for w in windows:
        seqs.setdefault((w.dataset, w.sequence), set())
        if w.status == "done":
            seqs[(w.dataset, w.sequence)].add(w.window)
    out_rows = []
    for (d, s), done in seqs.items():
        row = ManifestRow.load(store, d, s, STITCH_ROW)
        row = row if isinstance(row, ManifestRow) else None  # an unreadable one is named under integrity
        if row is not None and row.params_hash == job.params_hash:
            out_rows.append(SequenceStatus(d, s, "failed", row.attempts, row.error))
            continue
        marker = SequenceMarker.load(store, d, s)  # an unreadable one is named under integrity
        stitched = isinstance(marker, SequenceMarker) and marker.of_job(job.params_hash) and set(marker.windows) == done
        out_rows.append(SequenceStatus(d, s, "stitched" if stitched else "pending", 0 if row is None else row.attempts,
                                       ""))
    return out_rows


def _printable(name: str) -> str:
    """A sequence name as it can be printed: itself, or its repr when it holds anything odd (a
    name that failed planning may be why it failed)."""
    return name if name.isprintable() and name.strip() == name and name else repr(name)


def _first_line(text: str) -> str:
    return text.strip().splitlines()[0] if text.strip() else ""


def print_status(out: str, verify: bool = False) -> int:
    """Print the windows' and sequences' states and every damaged or missing file; exit 1
    when any window or stitch failed or any file is damaged, 0 otherwise."""
    check_versions(Store(out))  # a newer catalogue schema: one line, before anything is reported
    rows = job_status(out)
    seqs = sequence_status(out, rows)
    counts = {s: sum(r.status == s for r in rows) for s in ("done", "failed", "pending", "running")}
    running = f", {counts['running']} running" if counts["running"] else ""
    print(f"{out}: {len(rows)} windows: {counts['done']} done, {counts['failed']} failed, {counts['pending']} pending"
          f"{running}")
    stitched = {s: sum(q.status == s for q in seqs) for s in ("stitched", "failed", "pending")}
    print(f"sequences: {stitched['stitched']} stitched, {stitched['failed']} failed to stitch, "
          f"{stitched['pending']} not stitched yet (of {len(seqs)})")
    job = JobRecord.load(Store(out))
    unplanned = job.unplanned if job else {}
    cfg = None
    try:
        cfg = job.job_config(Store(out).full(JOB)) if job else None
    except UnreadableRecord as e:  # the windows and files are still reported; the config's lines are not
        print(f"config unreadable: {e} (its proposer and dataset are not shown)")
    if unplanned:
        print(f"sequences not planned: {len(unplanned)} (the last submit left them out; fix them and submit again)")
    for q in seqs:  # per sequence: how far its windows are
        own = [r for r in rows if (r.dataset, r.sequence) == (q.dataset, q.sequence)]
        n = {s: sum(r.status == s for r in own) for s in ("done", "running", "failed")}
        extra = "".join(f", {n[s]} {s}" for s in ("running", "failed") if n[s])
        print(f"  {q.dataset}/{q.sequence}: {n['done']}/{len(own)} windows done{extra}; {q.status}")
    if cfg is not None and cfg.proposals.proposer:
        print(classifiers_line(cfg.proposals.proposer))
    for r in rows:
        if r.status == "done":
            continue
        line = f"{r.status:8s} {r.dataset}/{r.window}  attempts {r.attempts}"
        if r.running:
            line += "  " + r.running
        elif r.error:
            line += "  " + _first_line(r.error)
        print(line)
    for q in seqs:
        if q.status == "failed":
            print(f"{'failed':8s} {q.dataset}/{q.sequence} stitching  attempts {q.attempts}  {_first_line(q.error)}")
    dataset = cfg.source.dataset if cfg is not None else "?"
    for seq, why in sorted(unplanned.items()):
        print(f"{'failed':8s} {dataset}/{_printable(seq)} planning  {_first_line(why)}")
    writer = current_writer(Store(out))
    if writer:
        print(f"being written now by {describe(writer)}: files of steps in flight may show as damaged below")
    damage = job_damage(out, rows, verify)
    for d in damage:
        # A plain resubmission checks sizes only: damage of the same size needs --verify to be redone.
        how = "a resubmission with --verify" if d.reason.startswith("sha256") else "a resubmission"
        print(f"damaged  {d.path}: {d.reason} ({how} {_repair(d)})")
    checked = ("sizes and checksums" if verify else
               "sizes and checksums of the catalogue's files, sizes of the windows' parts; --verify also checks their checksums")
    print(f"integrity: {len(damage)} damaged or missing file(s) ({checked})")
    for line in leftover_lines(Store(out), bool(writer)):  # looked at, never removed: that is the next submit's
        print(line)
    return 1 if counts["failed"] or stitched["failed"] or damage or unplanned else 0
