"""The schedule of one ``mine submit``: which step runs next, and what a result unlocks.

Pure bookkeeping over the job's windows — no Ray, no files: the loop in ``submit.py``
asks ``next_task()`` while a worker is free and hands each result to ``on_result``.

* A window's *neighbours* are the windows whose core frames lie in its context (itself
  included); its *users* are the windows whose context holds its core. A window is
  tracked once the observe steps of all its neighbours have reported, so tracking
  starts while later windows are still being observed.
* When a worker is free: a ready track (it writes parts and frees caches), except while
  no more than ``observe_ahead`` tracks are ready and an observe is queued: then the
  observe, so the next tracks' inputs are under way. Tracks-first alone leaves workers idle
  at a job's tail (two sequences of two windows on two workers: one worker tracks the first
  sequence while the other waits for the second's last observe, ~20 % of the wall time;
  ``mine bench pipeline``); the bound keeps the caches waiting for their tracks to a few
  windows. A sequence's finalize has no dependents, so it fills otherwise idle workers. A
  sequence is finalized once all its windows are settled.
* Resume: windows an earlier run finished (``Resume.done``) are skipped, except a window
  tracked while a neighbour had failed (its context was incomplete) when that neighbour
  runs again: it is tracked again too (its observations are cached), so a repaired job
  ends as a clean run would. A sequence whose catalogue already holds exactly its done
  windows is not finalized again, nor one whose catalogue holds a window that failed this
  time (stitching without it would lose what was mined: the catalogue stays as it is, and
  the window's failure is reported).
* Caches: a window's observation cache serves its users and may be dropped once all of
  them are done (they never run again in this job).
"""

from __future__ import annotations

import bisect
from collections import defaultdict, deque
from collections.abc import Mapping
from dataclasses import dataclass
from enum import StrEnum
from typing import TYPE_CHECKING

from mining.pipeline.resume import Resume
from mining.types import Window

if TYPE_CHECKING:
    from mining.pipeline.steps import StepResult


class Step(StrEnum):
    """The three steps (``steps.py``), by the name the executors' workers know them by."""

    OBSERVE = "observe"  # a window's core frames → its observation cache
    TRACK = "track"  # a window's context → its tube pieces and manifest row
    FINALIZE = "finalize"  # a sequence's windows → its catalogue


@dataclass(frozen=True)
class Task:
    """One step to run: ``executor.submit(task.step, *task.args)``."""

    step: Step
    target: Window | str  # the window observed or tracked, or the sequence finalized
    args: tuple

    @property
    def window(self) -> Window | None:
        """The window observed or tracked (None for a finalize)."""
        return self.target if isinstance(self.target, Window) else None

    @property
    def sequence(self) -> str:
        """The sequence the task works on."""
        return self.target.sequence if isinstance(self.target, Window) else self.target

    @property
    def name(self) -> str:
        """The window's name, or the sequence finalized: what its ``StepResult.window`` says."""
        return self.target.name if isinstance(self.target, Window) else self.target


def neighbours(window: Window, windows: list[Window]) -> list[Window]:
    """The windows whose core frames lie in ``window``'s context (itself included)."""
    a, b = window.context
    return [w for w in windows if w.sequence == window.sequence and w.core[0] < b and w.core[1] > a]


def neighbour_map(windows: list[Window]) -> dict[str, list[Window]]:
    """``neighbours`` of every window, by a sweep over each sequence's sorted cores
    (a recording of hours has thousands of windows: no scan over all of them per window)."""
    out: dict[str, list[Window]] = {}
    by_seq: dict[str, list[Window]] = defaultdict(list)
    for w in windows:
        by_seq[w.sequence].append(w)
    for ws in by_seq.values():
        ws = sorted(ws, key=lambda w: w.core[0])
        starts = [w.core[0] for w in ws]
        for w in ws:
            a, b = w.context
            lo = max(0, bisect.bisect_right(starts, a) - 1)
            hi = bisect.bisect_left(starts, b)
            out[w.name] = [n for n in ws[lo:hi] if n.core[0] < b and n.core[1] > a]
    return out


def user_map(windows: list[Window], nbrs: Mapping[str, list[Window]]) -> dict[str, list[Window]]:
    """For every window, the windows whose context holds its core (in ``windows`` order)."""
    users: dict[str, list[Window]] = {w.name: [] for w in windows}
    for w in windows:
        for n in nbrs[w.name]:
            users[n.name].append(w)
    return users


OBSERVE_AHEAD = 2  # ours: observes go before ready tracks while at most this many tracks are ready (caches of ~2 windows wait)


class Schedule:
    """The windows of a job, what is left to run of them, and in which order."""

    def __init__(self, windows: list[Window], resume: Resume | None = None, observe_ahead: int = OBSERVE_AHEAD):
        resume = resume or Resume()
        self.observe_ahead = observe_ahead
        self.windows = list(windows)
        self.by_seq: dict[str, list[Window]] = defaultdict(list)
        for w in self.windows:
            self.by_seq[w.sequence].append(w)
        self.nbrs = neighbour_map(self.windows)
        self.users = user_map(self.windows, self.nbrs)

        # Resume: done windows are skipped, unless tracked with an incomplete context
        # and a neighbour runs again.
        done = set(resume.done)
        rerun = {w.name for w in self.windows if w.name not in done}
        for w in self.windows:
            if w.name in done and not resume.done[w.name] and any(n.name in rerun for n in self.nbrs[w.name]):
                done.discard(w.name)
        self.skipped = len(done)
        self.todo = [w for w in self.windows if w.name not in done]
        self.to_finalize = {s for s, ws in self.by_seq.items()
                            if any(w.name not in done for w in ws)
                            or resume.finalized.get(s) != {w.name for w in ws if w.name in done}}

        # Queues: every observe a pending track needs, tracks whose observes have all
        # reported, sequences whose windows are all settled.
        need_obs = {n.name for w in self.todo for n in self.nbrs[w.name]}
        self._observe: deque[Window] = deque(w for w in self.windows if w.name in need_obs)
        self._todo_names = {w.name for w in self.todo}
        self._waiting = {w.name: len(self.nbrs[w.name]) for w in self.todo}  # observe results a track waits for
        self._blocked = sum(1 for n in self._waiting.values() if n > 0)
        self._ready: deque[Window] = deque()
        self._observed: dict[str, StepResult] = {}
        self.ok: dict[str, set[str]] = {s: {w.name for w in ws if w.name in done} for s, ws in self.by_seq.items()}
        self._left = {s: sum(1 for w in ws if w.name not in done) for s, ws in self.by_seq.items()}
        self._held = dict(resume.finalized)
        self._finalize: deque[str] = deque(s for s in sorted(self.to_finalize) if self._left[s] == 0 and self._loses_nothing(s))
        self._dropped: set[str] = set()

    def _loses_nothing(self, sequence: str) -> bool:
        """Whether stitching the sequence's done windows keeps every window its catalogue holds."""
        held = self._held.get(sequence)
        return held is None or held <= self.ok[sequence]

    @property
    def nothing_to_do(self) -> bool:
        """No window to run and no sequence to finalize: a finished job resubmitted."""
        return not self.todo and not self.to_finalize

    @property
    def outstanding(self) -> bool:
        """Some task is queued, or some track still waits for observe results."""
        return bool(self._ready or self._observe or self._blocked or self._finalize)

    def next_task(self) -> Task | None:
        """The task to run next, or None while nothing can start before a result comes."""
        if self._ready and (len(self._ready) > self.observe_ahead or not self._observe):
            w = self._ready.popleft()
            nb = self.nbrs[w.name]
            return Task(Step.TRACK, w, (w, nb, [self._observed[n.name] for n in nb]))
        if self._observe:
            w = self._observe.popleft()
            return Task(Step.OBSERVE, w, (w,))
        if self._finalize:
            seq = self._finalize.popleft()
            return Task(Step.FINALIZE, seq, (seq, self.by_seq[seq], sorted(self.ok[seq])))
        return None

    def on_result(self, task: Task, result: StepResult) -> list[Window]:
        """Take the result of ``task`` (a failed one when the step could not run);
        returns the windows whose observation caches no track needs any more."""
        if task.step == Step.OBSERVE:
            w = task.target
            self._observed[w.name] = result
            for u in self.users[w.name]:
                if u.name in self._todo_names:
                    self._waiting[u.name] -= 1
                    if self._waiting[u.name] == 0:
                        self._blocked -= 1
                        self._ready.append(u)
            return []
        if task.step == Step.TRACK:
            w = task.target
            served: list[Window] = []
            if result.ok:
                ok = self.ok[w.sequence]
                ok.add(w.name)
                served = [n for n in self.nbrs[w.name]
                          if n.name not in self._dropped and all(m.name in ok for m in self.users[n.name])]
                self._dropped.update(n.name for n in served)
            self._left[w.sequence] -= 1
            if self._left[w.sequence] == 0 and w.sequence in self.to_finalize and self._loses_nothing(w.sequence):
                self._finalize.append(w.sequence)
            return served
        return []
