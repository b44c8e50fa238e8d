"""The end of ``mine submit``: what a run did, counted from its steps' results, in a few lines.

``run_job`` (``submit.py``) hands every result to ``Summary.count``; ``mine_job`` adds the
whole command's time, the classifiers and the sequences the preflight left out; the CLI
prints ``lines()`` and exits 1 when a window, a stitch or a sequence's planning failed
(``any_failed``). A sequence's stitch is counted apart from its windows: ``failed`` holds
windows, ``stitch_failed`` sequences.
Frames/s is core frames of the windows tracked this run over the mining time (``run_job``'s,
from its first step to its last result); the progress bar counts frames observed over the
same time, which is this rate once every window is tracked.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from mining.pipeline.schedule import Step, Task
from mining.pipeline.steps import StepResult


def _headline(error: str) -> str:
    return error.strip().splitlines()[0] if error.strip() else "unknown error"


@dataclass
class Summary:
    windows: int = 0
    skipped: int = 0
    ok: int = 0
    failed: dict[str, str] = field(default_factory=dict)  # window → error
    stitch_failed: dict[str, str] = field(default_factory=dict)  # "dataset/sequence" whose stitch failed → error
    unplanned: dict[str, str] = field(default_factory=dict)  # "dataset/sequence" left out by the preflight → why
    clamped: list[str] = field(default_factory=list)  # what of a --frames range past a sequence's end was mined
    notes: list[str] = field(default_factory=list)  # how a source sampled a sequence (a stride: the frames skipped)
    frames: int = 0
    tubes: int = 0
    candidates: int = 0
    known: int = 0
    unknown: int = 0
    clutter: int = 0
    unclassified: int = 0
    seconds: float = 0.0  # the whole command: preflight, planning, Ray start, mining
    mining_seconds: float = 0.0  # run_job's: from the first step to the last result (the frames/s denominator)
    started_at: float = 0.0  # unix time of run_job's first step (when the proposal stage could first be busy)
    sequences_written: int = 0
    classifiers: str = ""  # which proposers classified (proposals.make.classifiers_line)
    classify_hint: str = ""  # how to get classes where no proposer gave any (proposals.make.classify_hint)
    recomputed: dict[str, str] = field(default_factory=dict)  # window → why its observation cache did not read back
    swept: list[str] = field(default_factory=list)  # temporary files an interrupted run left, removed by this one
    damaged_labels: list[str] = field(default_factory=list)  # label files --verify set aside (labels/_damaged/…)
    embed: list[str] = field(default_factory=list)  # the embedding stage's lines (embed.model_path set)
    # Where the steps ran (executors' ``placement``): "workers" and "proposal_actors", each a
    # list of {pid, gpu_ids, node, ...}; empty for a job that ran nothing.
    placement: dict[str, list[dict]] = field(default_factory=dict)

    @property
    def any_failed(self) -> bool:
        """A window, a stitch or a sequence's planning failed (``mine submit`` exits 1)."""
        return bool(self.failed or self.stitch_failed or self.unplanned)

    @property
    def nothing_to_do(self) -> bool:
        """Every window was done by an earlier run and this one wrote nothing (a finished job resubmitted)."""
        return (self.windows > 0 and self.skipped == self.windows and not self.ok and not self.any_failed
                and not self.sequences_written and not self.recomputed)

    def lines(self) -> list[str]:
        stitch = f"; stitch: {len(self.stitch_failed)} failed" if self.stitch_failed else ""
        out = [f"windows: {self.ok} ok, {len(self.failed)} failed, {self.skipped} already done (of {self.windows})"
               f"{stitch}",
               *self.clamped, *self.notes]
        if self.nothing_to_do:  # "0 selected … 0.00 frames/s" read as a job that found nothing
            out += ["nothing left to mine: an earlier run did every window; the catalogue's tubes are as they "
                    "were (mine status, mine query)", f"time: {self.seconds:.1f} s in all"]
        else:
            out += [f"tubes written this run: {self.tubes} selected ({self.known} known, {self.unknown} unknown, "
                    f"{self.clutter} clutter, {self.unclassified} unclassified) of {self.candidates} candidates, "
                    f"in {self.sequences_written} sequence(s)",
                    *([self.classifiers] if self.classifiers else []),
                    f"time: {self.seconds:.1f} s in all, {self.mining_seconds:.1f} s mining: "
                    f"{self.frames / max(self.mining_seconds, 1e-9):.2f} frames/s (core frames tracked / mining time)"]
        if self.placement.get("proposal_actors"):
            actors = self.placement["proposal_actors"]
            gpus = ", ".join("+".join(a["gpu_ids"]) or "none" for a in actors)
            out.append(f"proposal stage: {len(actors)} actor(s) on GPUs [{gpus}] proposed "
                       f"{sum(a['frames'] for a in actors)} frames; {len(self.placement.get('workers', []))} CPU "
                       f"worker(s) did the rest")
            if (busy := self.stage_busy()) is not None:
                out.append(f"proposal stage busy {100 * busy['share']:.0f} % of the mining time from its first "
                           f"second ({busy['busy_s']:.1f} actor-s of {len(actors)} × {self.mining_seconds:.1f} s); "
                           f"every actor had work {busy['all_busy_after_s']:.1f} s in")
        if self.classify_hint:
            out.append(self.classify_hint)
        out += self.embed
        if self.damaged_labels:  # said apart and loud: these labels are lost unless the user has a copy
            out.append(f"DAMAGED LABELS: {len(self.damaged_labels)} label file(s) did not match their sha256 and were "
                       f"moved aside, their labels lost: {', '.join(self.damaged_labels)}")
        if self.swept:
            more = f" and {len(self.swept) - 1} more" if len(self.swept) > 1 else ""
            out.append(f"swept {len(self.swept)} temporary file(s) an interrupted run left: {self.swept[0]}{more}")
        for w, e in sorted(self.failed.items()):
            out.append(f"FAILED {w}: {_headline(e)}")
        for seq, e in sorted(self.stitch_failed.items()):
            out.append(f"FAILED {seq} (stitching): {_headline(e)}")
        if self.unplanned:
            out.append(f"sequences left out: {len(self.unplanned)} could not be planned (the others ran); "
                       "fix them and rerun the same command")
        for seq, e in sorted(self.unplanned.items()):
            out.append(f"FAILED {seq} (planning): {_headline(e)}")
        for w, e in sorted(self.recomputed.items()):
            out.append(f"RECOMPUTED {w}: its observation cache did not read back ({e})")
        return out

    def stage_busy(self) -> dict[str, float] | None:
        """The proposal actors' busy share of the mining time (the GPU busy share where they hold GPUs):
        their time inside ``propose`` over actors × ``mining_seconds``, and how long after the first step
        every actor had had its first batch (the ramp-up); None without a proposal stage or its times."""
        actors = self.placement.get("proposal_actors") or []
        if not actors or self.mining_seconds <= 0 or any(a.get("busy_s") is None for a in actors):
            return None
        firsts = [a.get("first_t") for a in actors]
        ramp = (max(firsts) - self.started_at) if all(f is not None for f in firsts) and self.started_at else float("nan")
        busy = sum(a["busy_s"] for a in actors)
        return {"share": busy / (len(actors) * self.mining_seconds), "busy_s": busy, "all_busy_after_s": ramp}

    def count(self, task: Task, result: StepResult, dataset: str) -> None:
        """Add the result of a task."""
        if result.recomputed:  # an observe step that observed again
            self.recomputed[task.name] = result.recomputed
        if task.step == Step.TRACK:
            self.frames += result.frames
            if result.ok:
                self.ok += 1
            else:
                self.failed[task.name] = result.error
        elif task.step == Step.FINALIZE:
            if not result.ok:
                self.stitch_failed[f"{dataset}/{task.name}"] = result.error
                return
            self.sequences_written += 1
            t = result.tubes
            self.tubes += t.selected
            self.candidates += t.candidates
            self.known += t.known
            self.unknown += t.unknown
            self.clutter += t.clutter
            self.unclassified += t.unclassified
