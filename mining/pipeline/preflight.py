"""Preflight: what ``mine submit`` checks in the driver before job.json is written or Ray starts.

A bad setting or model file that only the workers notice fails every window one by one
after Ray has started (thousands of identical FAILED lines on a long recording), and
leaves a job.json by which the fixed command is then refused. So the driver checks,
once, in this order:

1. the whole config: every field's type and rules (``mining.checks``: ranges, multiples,
   choices, proposer names), and the source options against the source's arguments;
2. the frame range: ``--frames 50:10`` is an error, not a job of zero windows;
3. the output: ``--out`` can be written (a probe file, removed at once) and a job.json
   already there can be read;
4. every sequence: planned with only the frames inside the range mattering
   (``Source.plan``), its calibration sane (``check_calib``: finite, positive,
   plausible), its range not empty. A sequence that fails is reported and left out;
   the others run. When none is left, the job fails here;
5. the proposer, made once here: an ONNX model is opened and loaded by onnxruntime, a
   JSON proposal folder is looked up; and the image encoder of ``embed.model_path``, where one
   is set, checked against its contract (``discovery/embed.py``).

Each failure is a MiningError whose message names the key or file, the value and the
rule. Nothing but the probe is written before all of them pass.
"""

from __future__ import annotations

import difflib
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from mining.catalog.integrity import check_versions
from mining.catalog.records import JobRecord
from mining.catalog.store import Store
from mining.checks import clamped_note
from mining.config import JobConfig, validate
from mining.errors import ConfigError, InputError, MiningError
from mining.names import check_name
from mining.pipeline.steps import Job, job_source
from mining.sources.base import Source, check_calib
from mining.types import SequencePlan, Window, plan_windows


@dataclass
class Preflight:
    """The sequences a job can mine, their windows, and the sequences it cannot (with why)."""

    plans: dict[str, SequencePlan]
    windows: list[Window]
    failed: dict[str, str] = field(default_factory=dict)  # sequence → why it cannot be mined
    clamped: dict[str, str] = field(default_factory=dict)  # sequence → what of --frames it has (clamped_note)
    notes: dict[str, str] = field(default_factory=dict)  # sequence → how its source sampled it (SequencePlan.note)



def check_frames(frames: tuple[int, int | None]) -> None:
    """ConfigError for a frame range that holds no frame (or starts before frame 0)."""
    a, b = frames
    if a < 0:
        raise ConfigError(f"--frames {a}:{'' if b is None else b}: the start must be ≥ 0")
    if b is not None and b <= a:
        raise ConfigError(f"--frames {a}:{b} is empty: the end must be greater than the start")


def check_output(out: str) -> None:
    """InputError unless ``out`` is (or can be made) a folder this process can write, and
    a job.json in it can be read; ``versions.SchemaVersionError`` for a catalogue of a newer
    schema version than this code reads, before anything is written."""
    store = Store(out)
    if store.local and Path(store.root).exists() and not Path(store.root).is_dir():
        raise InputError("--out is not a folder", store.root)
    check_versions(store, oldest=False)  # older rows: resumed as before, or set aside by --new-run
    probe = f".preflight-{uuid.uuid4().hex[:12]}"
    try:
        store.write_bytes(probe, b"")
        store.remove(probe)  # the folder stays: the job writes there next
    except OSError as e:
        reason = e.strerror or str(e)
        raise InputError(f"the output folder cannot be written ({reason}); choose another --out", store.root) from None
    JobRecord.load(store)  # a corrupt job.json: InputError naming the file and the key


def checked_plan(source: Source, cfg: JobConfig, sequence: str, frames: tuple[int, int | None]) -> SequencePlan:
    """A sequence's plan for a frame range: frames inside it readable, calibration sane,
    the range not empty; InputError otherwise. For every command that plans a sequence."""
    start, stop = frames
    plan = source.plan(sequence, start, stop)
    r = cfg.run
    check_calib(plan.calib, None, r.calib_fov_deg, r.calib_baseline_m, r.calib_aspect)
    if start >= len(plan):
        raise InputError(f"--frames {start}:{'' if stop is None else stop} holds none of its {len(plan)} frames")
    return plan


def job_sequences(cfg: JobConfig, sequences: list[str] | None, source: Source) -> tuple[list[str], dict[str, str]]:
    """The job's sequence names, and (name → reason) the names of the source's own listing
    that are not safe names (``mining.names``). A name the user gave (``--sequences``, the
    config's ``source.sequences``) that is not safe stops the job: InputError naming it."""
    given, origin = (sequences, "--sequences") if sequences else (cfg.source.sequences, "the config's source.sequences")
    if given:
        return [check_name(s, "sequence", origin) for s in given], {}
    listing = f"the {cfg.source.dataset} source's listing of {cfg.source.root or 'its root'}"
    names, refused = [], {}
    for seq in source.sequences():
        try:
            names.append(check_name(seq, "sequence", listing))
        except InputError as e:
            refused[seq] = str(e)
    return names, refused


# ours: how many of the source's sequence names an "absent sequence" message lists
MAX_LISTED_SEQUENCES = 10


def _absent_sequences(given: list[str], source: Source) -> dict[str, str]:
    """Given names the source does not list (name → why, with the nearest name it has:
    ``5`` → ``0005``); empty where the source cannot list its sequences."""
    try:
        have = sorted(source.sequences())
    except Exception:  # a source that cannot list: each sequence's own plan says what is wrong
        return {}
    listed = ", ".join(have[:MAX_LISTED_SEQUENCES]) + (" …" if len(have) > MAX_LISTED_SEQUENCES else "")
    out = {}
    for seq in given:
        if seq in have:
            continue
        near = [h for h in have if h.lstrip("0") == seq.lstrip("0")] or difflib.get_close_matches(seq, have, n=1)
        hint = f"; did you mean {near[0]!r}?" if near else ""
        out[seq] = f"no sequence {seq!r}{hint} (have: {listed or 'none'})"
    return out


def plan_sequences(cfg: JobConfig, sequences: list[str] | None = None,
                   frames: tuple[int, int | None] = (0, None)) -> Preflight:
    """Plan every sequence of the job; a sequence that cannot be mined is reported, not fatal,
    unless none can (then InputError listing why for each)."""
    source = job_source(Job(cfg, "", "", {}))
    seqs, refused = job_sequences(cfg, sequences, source)
    dataset = cfg.source.dataset
    if not seqs and not refused:
        looked = f": looked for {source.layout}" if source.layout else ""
        raise InputError(f"no {dataset} sequences found under {cfg.source.root or 'its root'}{looked}",
                         cfg.source.root or None)
    w = cfg.window
    pf = Preflight({}, [])
    pf.failed.update(refused)  # names of the source's listing that are not safe names: left out
    # a name the user gave that the source does not list: its failure says what the source has
    absent = _absent_sequences(seqs, source) if (sequences or cfg.source.sequences) else {}
    for seq in seqs:
        try:
            plan = checked_plan(source, cfg, seq, frames)
        except MiningError as e:
            pf.failed[seq] = "; ".join([str(e)] + ([absent[seq]] if seq in absent else []))
            continue
        except Exception as e:  # bad data an adapter did not foresee: still that sequence's failure only
            pf.failed[seq] = "; ".join([f"{type(e).__name__}: {e}"] + ([absent[seq]] if seq in absent else []))
            continue
        pf.plans[seq] = plan
        if (note := clamped_note(seq, frames, len(plan))) is not None:
            pf.clamped[seq] = note
        if plan.note:  # e.g. a stride: what was skipped, and how many frames the job reads
            a, b = frames[0], len(plan) if frames[1] is None else min(frames[1], len(plan))
            pf.notes[seq] = f"sequence {seq}: {plan.note}; {max(0, b - a)} frames read"
        pf.windows += plan_windows(plan, w.core, w.context_before, w.context_after, frames[0], frames[1])
    if not pf.plans:
        raise InputError("no sequence can be mined: " + "; ".join(f"{dataset}/{s}: {e}" for s, e in pf.failed.items()))
    return pf


def check_proposer(cfg: JobConfig, plans: dict[str, SequencePlan]) -> None:
    """Make the configured proposer once (loads an ONNX model, finds a JSON folder)."""
    from mining.proposals.make import make_proposer
    from mining.proposals.registry import proposer_names

    calib = next(iter(plans.values())).calib
    try:
        make_proposer(cfg.proposals, (calib.height, calib.width))
    except MiningError:
        raise
    except Exception as e:  # onnx / onnxruntime raise their own types for an unreadable model
        what = f"proposals.proposer = {cfg.proposals.proposer!r}"
        if "onnx" in proposer_names(cfg.proposals.proposer):
            what += f", proposals.onnx.model_path = {cfg.proposals.onnx.model_path!r}"
        raise ConfigError(f"{what}: the proposer cannot be made: {type(e).__name__}: {e}") from None


def preflight(cfg: JobConfig, out: str, sequences: list[str] | None = None,
              frames: tuple[int, int | None] = (0, None)) -> Preflight:
    """Every check of the module docstring, in its order; the sequences to mine."""
    validate(cfg)
    check_frames(frames)
    if sequences or cfg.source.sequences:  # names the user gave: refused before anything is written
        given = sequences or cfg.source.sequences
        [check_name(s, "sequence", "--sequences" if sequences else "the config's source.sequences") for s in given]
    pf = plan_sequences(cfg, sequences, frames)
    check_proposer(cfg, pf.plans)
    if cfg.embed.model_path:  # the embedding stage's model: refused now, not after the mining
        from mining.discovery.embed import Encoder

        Encoder(cfg.embed.model_path, cfg.embed, "cpu")
    check_output(out)  # last: a job refused for anything else leaves no --out folder behind
    return pf
