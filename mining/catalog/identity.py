"""The identity of a mining job: everything a catalogue under ``--out`` was made from.

A catalogue is only meaningful as the result of one job, so ``job.json`` records the
job's identity as a flat mapping of named keys, and a resubmission to the same ``--out``
must have the same one (``check_resubmit``):

* ``config.<section>.<key>`` — every result-changing config value (``run.*``, how a
  result is reached, is left out; ``source.root`` and ``source.sequences`` have keys of
  their own);
* ``source.root`` — the dataset root, as an absolute path (URIs as given);
* ``sequences`` — the sequences mined (sorted: planning order changes no result);
* ``frames.<sequence>`` — the plan positions ``a:b`` mined, after clipping to the recording;
* ``unplanned`` — the sequences asked for that could not be planned; once repaired, the
  same command adds them (they had no windows);
* ``recording.<sequence>.frames`` / ``.stamps`` / ``.calib`` — a cheap fingerprint of the
  recording from its plan (no image is decoded): the frame count, a hash of the frame
  indices, timestamps and gaps, and the calibration. Image contents are not part of it
  on purpose: repairing a damaged frame and resubmitting resumes the job (the windows
  that failed on it run again).

A difference is refused naming every differing key (old → new), unless the caller asks
for an *extension* (``--extend``: frame ranges widened, sequences added, nothing else
changed; its windows that differ from a clean run's are recomputed, so the result equals
a clean run of the new range) or a *new run* (``--new-run``: the old catalogue is moved
aside, see ``submit.open_job``).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from mining.config import RENAMED_KEYS, JobConfig, renamed_to
from mining.errors import ConfigError
from mining.types import SequencePlan

MODES = ("resume", "extend", "new")  # what a resubmission to an --out holding a catalogue may do
ABSENT = "(absent)"  # how a key one side lacks is written in a difference


def _flatten(prefix: str, value: Any, out: dict[str, Any]) -> None:
    if isinstance(value, Mapping) and value:
        for k in sorted(value):
            _flatten(f"{prefix}.{k}", value[k], out)
    else:
        out[prefix] = json.loads(json.dumps(value, default=str))  # plain JSON values: compare as stored


def root_key(root: str) -> str:
    """The dataset root as the identity records it: absolute (symlinks resolved), URIs as given."""
    if not root or "://" in root:
        return root
    return str(Path(root).expanduser().resolve())


def recording_fingerprint(plan: SequencePlan) -> dict[str, Any]:
    """A cheap fingerprint of one recording, from its plan (no image is read)."""
    h = hashlib.sha256()
    h.update(json.dumps([list(plan.frames), list(plan.t_ns), list(plan.gaps)]).encode())
    c = plan.calib
    calib = (f"fx={c.fx:.6g} fy={c.fy:.6g} cx={c.cx:.6g} cy={c.cy:.6g} baseline={c.baseline_m:.6g} "
             f"size={c.width}x{c.height}")
    return {"frames": len(plan), "stamps": h.hexdigest()[:16], "calib": calib}


def frame_range(plan: SequencePlan, frames: tuple[int, int | None]) -> tuple[int, int]:
    """The plan positions ``[a, b)`` of ``--frames`` on this recording (as ``plan_windows`` cuts them)."""
    n = len(plan) if frames[1] is None else min(frames[1], len(plan))
    return max(0, frames[0]), n


def job_identity(cfg: JobConfig, plans: Mapping[str, SequencePlan], frames: tuple[int, int | None],
                 unplanned: Sequence[str] = ()) -> dict[str, Any]:
    """The flat identity of a job (module docstring): key → JSON value. ``unplanned``: the
    sequences asked for that could not be planned (left out, named in the summary)."""
    out: dict[str, Any] = {}
    d = cfg.to_dict()
    d.pop("run")  # retries change how a result is reached, not the result (as params_hash)
    d.pop("embed")  # embeddings are written beside the tubes and never change them (as params_hash)
    d["source"] = {k: v for k, v in d["source"].items() if k not in ("root", "sequences")}
    _flatten("config", d, out)
    out["source.root"] = root_key(cfg.source.root)
    out["sequences"] = sorted(plans)
    if unplanned:
        out["unplanned"] = sorted(unplanned)
    for seq, plan in plans.items():
        a, b = frame_range(plan, frames)
        out[f"frames.{seq}"] = f"{a}:{b}"
        for k, v in recording_fingerprint(plan).items():
            out[f"recording.{seq}.{k}"] = v
    return out


def differences(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[tuple[str, Any, Any]]:
    """Every key whose value differs, as (key, old, new); a key one side lacks is ``ABSENT`` there."""
    return [(k, old.get(k, ABSENT), new.get(k, ABSENT)) for k in sorted(old.keys() | new.keys())
            if old.get(k, ABSENT) != new.get(k, ABSENT)]


def _show(v: Any) -> str:
    return v if isinstance(v, str) else json.dumps(v)


def _range(text: str) -> tuple[int, int]:
    a, b = text.split(":")
    return int(a), int(b)


def _sequence_of(key: str) -> str | None:
    if key.startswith("frames."):
        return key[len("frames."):]
    if key.startswith("recording."):
        return key[len("recording."):].rsplit(".", 1)[0]  # sequence names may hold dots
    return None


def _repaired(key: str, old: Any, new: Any, old_id: Mapping[str, Any]) -> bool:
    """A difference the same command makes once a sequence left out at planning is repaired:
    it joins the job (it had no windows, so nothing mined changes)."""
    was_out = set(old_id.get("unplanned") or ())
    if not was_out:
        return False
    if key == "unplanned":
        return True
    if key == "sequences":
        return (isinstance(old, list) and isinstance(new, list) and set(old) <= set(new)
                and set(new) - set(old) <= was_out)
    return _sequence_of(key) in was_out and old == ABSENT


def _extends(key: str, old: Any, new: Any, old_id: Mapping[str, Any]) -> bool:
    """Whether this one difference is something ``--extend`` may do."""
    if key == "sequences":
        return isinstance(old, list) and isinstance(new, list) and set(old) <= set(new)
    if key.startswith("frames."):
        if old == ABSENT:
            return True  # a sequence added
        if new == ABSENT:
            return False
        (a0, b0), (a1, b1) = _range(old), _range(new)
        return a1 <= a0 and b1 >= b0
    if key.startswith("recording."):
        seq = key[len("recording."):].rsplit(".", 1)[0]  # sequence names may hold dots
        return old == ABSENT and f"frames.{seq}" not in old_id  # a new sequence's fingerprint
    return False


def _under(key: str, table: str) -> bool:
    return key == table or key.startswith(table + ".")


def moved_since(identity: Mapping[str, Any]) -> list[tuple[str, str | tuple[str, ...] | None]]:
    """The config moves (``config.RENAMED_KEYS``: old key → new, a tuple of new places, None =
    removed) made after the job of this identity was recorded: its config keys still sit at
    their old places."""
    return [(o, n) for o, n in RENAMED_KEYS.items() if any(_under(k, f"config.{o}") for k in identity)]


def _renamed_identity(identity: Mapping[str, Any]) -> dict[str, Any]:
    """``identity`` with its config keys at today's places (``moved_since``)."""
    out = dict(identity)
    for o, n in moved_since(identity):
        for k in [k for k in out if _under(k, f"config.{o}")]:
            v = out.pop(k)
            for place in renamed_to(n):
                out[f"config.{place}{k[len(f'config.{o}'):]}"] = v
    return out


def check_resubmit(old: Mapping[str, Any], new: Mapping[str, Any], out: str, mode: str = "resume") -> None:
    """Refuse a resubmission whose identity differs from the catalogue's, naming every
    differing key; ``mode="extend"`` admits wider frame ranges and added sequences only.
    A record from before identities (``legacy_identity``: no ``sequences`` key) is
    compared on the keys it has.

    A catalogue recorded before a config key moved (``moved_since``) is refused in both
    modes, saying so: its rows carry the params hash of the old layout, which this version
    never computes, so nothing of it could be resumed (the differences left after the move
    are named too)."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if mode == "new":
        return
    moves = moved_since(old)
    if moves:
        old = _renamed_identity(old)
    complete = "sequences" in old
    diffs = [(k, o, n) for k, o, n in differences(old, new)
             if (complete or o != ABSENT) and not _repaired(k, o, n, old)]
    lines = "\n".join(f"  {k}: {_show(o)} → {_show(n)}" for k, o, n in diffs)
    if moves:
        what = "; ".join(f"{o} moved to {' and '.join(renamed_to(n))}" if n else f"{o} was removed" for o, n in moves)
        rest = f" Beyond the move, this job also differs in {len(diffs)} key(s):\n{lines}\n" if diffs else " "
        raise ConfigError(
            f"{out} holds a catalogue made before {what}: its job.json records the old keys and its rows carry "
            f"the params hash of that layout, so this version can neither resume nor extend it.{rest}"
            "Use --new-run to start a new catalogue there (the old one is moved aside), another --out, "
            "or the version of the code that made it.")
    if not diffs:
        return
    if mode == "extend":
        bad = [k for k, o, n in diffs if not _extends(k, o, n, old)]
        if not bad:
            return
        raise ConfigError(
            f"{out}: --extend only widens frame ranges and adds sequences; this job also changes "
            f"{', '.join(bad)}. Every difference from the catalogue's job:\n{lines}\n"
            "Use --new-run to start a new catalogue there (the old one is moved aside), or another --out.")
    raise ConfigError(
        f"{out} holds the catalogue of another job; this one differs in {len(diffs)} key(s):\n{lines}\n"
        "Resubmit the same job to resume it; --extend to widen its frame ranges or add sequences "
        "(the result equals a clean run of the new range); --new-run to start a new catalogue there "
        "(the old one is moved aside); or use another --out.")


def legacy_identity(config: Mapping[str, Any]) -> dict[str, Any]:
    """What a ``job.json`` without an identity still tells: its config keys and source root."""
    d = {k: v for k, v in config.items() if k != "run"}
    src = dict(d.get("source") or {})
    root = src.pop("root", "")
    src.pop("sequences", None)
    d["source"] = src
    out: dict[str, Any] = {}
    _flatten("config", d, out)
    out["source.root"] = root_key(root)
    return out
