"""The schedule of ``mine submit`` without Ray or files: order, resume, failures, caches.

The windows are drawn by hand: one sequence of three 10-frame windows with 5 frames of
context each side (A: core 0-10, B: 10-20, C: 20-30), so A's context reaches into B,
B's into A and C, and C's into B.
"""

from __future__ import annotations

import subprocess
import sys
from collections import deque

from conftest import REPO
from mining.pipeline.resume import Resume
from mining.pipeline.schedule import Schedule, Task, neighbour_map, neighbours, user_map
from mining.pipeline.steps import StepResult
from mining.types import SequencePlan, StereoCalib, Window, plan_windows

A = Window("synthetic", "s", (0, 10), (0, 15))
B = Window("synthetic", "s", (10, 20), (5, 25))
C = Window("synthetic", "s", (20, 30), (15, 30))
WINDOWS = [A, B, C]
ALL = frozenset({A.name, B.name, C.name})


def label(task: Task) -> tuple[str, str]:
    return task.step, task.target if isinstance(task.target, str) else task.target.name


def ok(task: Task) -> StepResult:
    return StepResult(label(task)[1], True, frames=10 if task.step == "track" else 0)


def failing(*names: tuple[str, str]):
    """Results that fail the tasks labelled ``names`` and succeed otherwise."""
    def result(task: Task) -> StepResult:
        return StepResult(label(task)[1], label(task) not in names, "boom" if label(task) in names else "")
    return result


def drive(schedule: Schedule, result=ok, workers: int = 1) -> tuple[list, list[str], list[Task]]:
    """Run the schedule like the loop does with ``workers`` slots, results coming back
    in the order the tasks were started: (task labels in start order, caches dropped, tasks)."""
    order, dropped, tasks, running = [], [], [], deque()
    while schedule.outstanding or running:
        while len(running) < workers and (task := schedule.next_task()) is not None:
            order.append(label(task))
            tasks.append(task)
            running.append(task)
        assert running, "the schedule waits for a result while nothing runs"
        task = running.popleft()
        dropped += [w.name for w in schedule.on_result(task, result(task))]
    return order, dropped, tasks


# -- neighbour and user maps ---------------------------------------------------------

def test_neighbours_are_the_windows_whose_core_lies_in_the_context():
    nbrs = neighbour_map(WINDOWS)
    assert {k: [w.name for w in v] for k, v in nbrs.items()} == {
        A.name: [A.name, B.name], B.name: [A.name, B.name, C.name], C.name: [B.name, C.name]}


def test_users_are_the_windows_whose_context_holds_the_core():
    # A's context (0-15) takes only 5 frames of B; B's (5-25) reaches A and C.
    narrow = [A, Window("synthetic", "s", (10, 20), (10, 20)), C]
    users = user_map(narrow, neighbour_map(narrow))
    assert [w.name for w in users[A.name]] == [A.name]
    assert [w.name for w in users[narrow[1].name]] == [A.name, narrow[1].name, C.name]
    assert [w.name for w in users[C.name]] == [C.name]


def test_windows_of_other_sequences_are_never_neighbours():
    other = Window("synthetic", "t", (10, 20), (5, 25))
    assert [w.name for w in neighbour_map([A, other])[A.name]] == [A.name]


def test_neighbour_map_equals_the_definition():
    """The sweep finds exactly the windows whose core lies in each context."""
    calib = StereoCalib(700.0, 700.0, 600.0, 180.0, 0.5, 1242, 375)
    windows = []
    for seq, n, core, before, after in (("a", 1000, 100, 30, 30), ("b", 257, 20, 45, 5), ("c", 7, 3, 0, 0)):
        plan = SequencePlan("synthetic", seq, calib, tuple(range(n)), tuple(range(n)))
        windows += plan_windows(plan, core, before, after)
    got = neighbour_map(windows)
    assert len(got) == len(windows)
    for w in windows:
        assert [n.name for n in got[w.name]] == [n.name for n in neighbours(w, windows)]


# -- order ---------------------------------------------------------------------------

def test_a_track_starts_as_soon_as_its_neighbours_are_observed():
    order, _, _ = drive(Schedule(WINDOWS, observe_ahead=0))
    assert order == [("observe", A.name), ("observe", B.name), ("track", A.name), ("observe", C.name),
                     ("track", B.name), ("track", C.name), ("finalize", "s")]


def test_a_ready_track_goes_before_a_queued_observe_beyond_the_look_ahead():
    s = Schedule(WINDOWS, observe_ahead=0)
    for _ in range(2):  # A and B observed: A's neighbours are all in, C is still queued
        t = s.next_task()
        s.on_result(t, ok(t))
    assert label(s.next_task()) == ("track", A.name)
    assert label(s.next_task()) == ("observe", C.name)


def test_within_the_look_ahead_a_queued_observe_goes_first():
    s = Schedule(WINDOWS, observe_ahead=1)
    for _ in range(2):
        t = s.next_task()
        s.on_result(t, ok(t))
    assert label(s.next_task()) == ("observe", C.name)  # one track ready (A): within the look-ahead
    assert label(s.next_task()) == ("track", A.name)  # nothing left to observe: the track


def _makespan(schedule: Schedule, seconds: dict[str, float], workers: int) -> float:
    """Event simulation: each step takes ``seconds[step]``; a free worker asks for the next task."""
    t, busy = 0.0, []  # (finish time, task)
    while schedule.outstanding or busy:
        while len(busy) < workers and (task := schedule.next_task()) is not None:
            busy.append((t + seconds[task.step], task))
        busy.sort(key=lambda x: x[0])
        t, task = busy.pop(0)
        schedule.on_result(task, ok(task))
    return t


def test_the_look_ahead_keeps_two_workers_busy_at_the_tail():
    """Two sequences of two 100-frame windows on two workers, the bench's job, with its step
    times (observe 41 s, track 16 s a window): tracks-first idles a worker for ~30 s waiting for
    the second sequence's last observe; with the look-ahead the makespan is the work over two."""
    windows = [Window("synthetic", s, (a, a + 100), (max(a - 30, 0), min(a + 130, 200)))
               for s in ("0000", "0001") for a in (0, 100)]
    seconds = {"observe": 41.0, "track": 16.0, "finalize": 1.5}
    work = 4 * (41.0 + 16.0) + 2 * 1.5
    tracks_first = _makespan(Schedule(windows, observe_ahead=0), seconds, 2)
    ahead = _makespan(Schedule(windows), seconds, 2)
    assert ahead < tracks_first
    assert ahead <= 1.05 * work / 2 < 0.95 * tracks_first


def test_finalize_only_fills_a_worker_nothing_else_needs():
    solo = Window("synthetic", "r", (0, 10), (0, 10))  # a sequence of one window, settled first
    order, _, _ = drive(Schedule([solo, A, B, C]), workers=2)
    assert order.index(("finalize", "r")) > order.index(("observe", C.name))
    assert order.index(("finalize", "r")) > order.index(("track", solo.name))
    assert order[-1] == ("finalize", "s")


def test_a_track_is_given_its_neighbours_and_their_observe_results():
    _, _, tasks = drive(Schedule(WINDOWS))
    track_b = next(t for t in tasks if label(t) == ("track", B.name))
    window, nbrs, observed = track_b.args
    assert window == B and nbrs == [A, B, C]
    assert [r.window for r in observed] == [A.name, B.name, C.name] and all(r.ok for r in observed)


def test_finalize_is_given_the_sequence_its_windows_and_the_done_ones():
    _, _, tasks = drive(Schedule(WINDOWS))
    assert tasks[-1].args == ("s", WINDOWS, sorted(ALL))


def test_nothing_is_outstanding_once_all_ran():
    s = Schedule(WINDOWS)
    drive(s)
    assert not s.outstanding and s.next_task() is None


def test_nothing_can_start_while_tracks_wait_for_running_observes():
    s = Schedule(WINDOWS)
    started = [s.next_task() for _ in range(3)]
    assert [label(t)[0] for t in started] == ["observe"] * 3
    assert s.next_task() is None and s.outstanding


# -- resume --------------------------------------------------------------------------

def test_a_finished_job_has_nothing_to_do():
    s = Schedule(WINDOWS, Resume({w.name: True for w in WINDOWS}, {"s": ALL}))
    assert s.nothing_to_do and s.skipped == 3 and s.todo == []
    assert s.next_task() is None and not s.outstanding


def test_a_fresh_job_runs_every_window():
    s = Schedule(WINDOWS)
    assert not s.nothing_to_do and s.skipped == 0 and s.todo == WINDOWS


def test_done_windows_are_only_observed_for_a_neighbour_that_runs_again():
    order, _, _ = drive(Schedule(WINDOWS, Resume({A.name: True, C.name: True})))
    assert order == [("observe", A.name), ("observe", B.name), ("observe", C.name),
                     ("track", B.name), ("finalize", "s")]


def test_a_done_window_far_from_the_rerun_is_not_observed():
    far = Window("synthetic", "s", (30, 40), (25, 40))
    order, _, _ = drive(Schedule([A, B, C, far], Resume({B.name: True, C.name: True, far.name: True})))
    assert ("observe", far.name) not in order and ("observe", C.name) not in order
    assert ("track", A.name) in order


def test_window_tracked_with_incomplete_context_runs_again_with_its_repaired_neighbour():
    # A was tracked while B had failed; B runs again now, so A is tracked again too.
    s = Schedule(WINDOWS, Resume({A.name: False, C.name: True}))
    assert s.todo == [A, B] and s.skipped == 1


def test_window_with_complete_context_does_not_run_again_with_its_neighbour():
    s = Schedule(WINDOWS, Resume({A.name: True, C.name: True}))
    assert s.todo == [B]


def test_incomplete_context_is_kept_when_no_neighbour_runs_again():
    s = Schedule(WINDOWS, Resume({A.name: False, B.name: True, C.name: True}, {"s": ALL}))
    assert s.nothing_to_do


def test_all_done_but_never_finalized_only_finalizes():
    order, _, _ = drive(Schedule(WINDOWS, Resume({w.name: True for w in WINDOWS})))
    assert order == [("finalize", "s")]


def test_catalogue_of_other_windows_is_finalized_again():
    s = Schedule(WINDOWS, Resume({w.name: True for w in WINDOWS}, {"s": frozenset({A.name, B.name})}))
    assert not s.nothing_to_do and s.todo == []
    assert label(s.next_task()) == ("finalize", "s")


def test_only_sequences_with_work_are_finalized():
    other = Window("synthetic", "t", (0, 10), (0, 10))
    s = Schedule([*WINDOWS, other], Resume({w.name: True for w in WINDOWS}, {"s": ALL}))
    order, _, _ = drive(s)
    assert order == [("observe", other.name), ("track", other.name), ("finalize", "t")]


# -- failures ------------------------------------------------------------------------

def test_a_failed_observe_still_lets_its_users_track_with_the_failure():
    order, _, tasks = drive(Schedule(WINDOWS), failing(("observe", B.name)))
    assert [o for o in order if o[0] == "track"] == [("track", A.name), ("track", B.name), ("track", C.name)]
    track_a = next(t for t in tasks if label(t) == ("track", A.name))
    assert [r.ok for r in track_a.args[2]] == [True, False]


def test_a_failed_track_is_left_out_of_the_finalize():
    _, _, tasks = drive(Schedule(WINDOWS), failing(("track", B.name)))
    assert label(tasks[-1]) == ("finalize", "s") and tasks[-1].args[2] == sorted([A.name, C.name])



def test_a_stitched_window_that_fails_when_run_again_keeps_the_catalogue():
    # The catalogue holds A, B and C; B's parts were lost and its rerun fails (e.g. a full
    # disk): stitching A and C alone would drop B's tubes, so the sequence is not finalized.
    s = Schedule(WINDOWS, Resume({A.name: True, C.name: True}, {"s": ALL}))
    order, _, _ = drive(s, failing(("track", B.name)))
    assert ("track", B.name) in order and ("finalize", "s") not in order
    # repaired: B runs and the sequence is stitched again with it
    order, _, tasks = drive(Schedule(WINDOWS, Resume({A.name: True, C.name: True}, {"s": ALL})))
    assert label(tasks[-1]) == ("finalize", "s") and tasks[-1].args[2] == sorted(ALL)

def test_a_sequence_whose_windows_all_failed_is_still_finalized():
    _, _, tasks = drive(Schedule(WINDOWS), failing(*[("track", w.name) for w in WINDOWS]))
    assert label(tasks[-1]) == ("finalize", "s") and tasks[-1].args[2] == []


def test_a_failed_finalize_ends_the_schedule():
    s = Schedule(WINDOWS)
    order, _, _ = drive(s, failing(("finalize", "s")))
    assert order[-1] == ("finalize", "s") and not s.outstanding and s.next_task() is None


# -- caches --------------------------------------------------------------------------

def test_a_cache_is_dropped_once_every_window_it_serves_is_done():
    s = Schedule(WINDOWS)
    dropped_after = {}
    for _ in range(7):
        t = s.next_task()
        dropped_after[label(t)] = [w.name for w in s.on_result(t, ok(t))]
    assert dropped_after[("track", A.name)] == []  # A's cache also serves B, not done yet
    assert dropped_after[("track", B.name)] == [A.name]  # B's serves C too
    assert dropped_after[("track", C.name)] == [B.name, C.name]


def test_observes_never_drop_caches():
    s = Schedule(WINDOWS)
    for _ in range(3):
        t = s.next_task()
        assert s.on_result(t, ok(t)) == []


def test_each_cache_is_dropped_once():
    _, dropped, _ = drive(Schedule(WINDOWS), workers=3)
    assert sorted(dropped) == sorted(ALL)


def test_a_failed_track_keeps_the_caches_it_needs():
    _, dropped, _ = drive(Schedule(WINDOWS), failing(("track", B.name)))
    assert dropped == []  # every cache serves B, which may run again


def test_caches_of_done_windows_go_once_the_rerun_window_is_done():
    _, dropped, _ = drive(Schedule(WINDOWS, Resume({A.name: True, C.name: True})))
    assert sorted(dropped) == sorted(ALL)


# -- purity --------------------------------------------------------------------------

def test_the_schedule_needs_no_ray():
    code = "import sys, mining.pipeline.schedule; assert 'ray' not in sys.modules, 'ray imported'"
    subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True)
