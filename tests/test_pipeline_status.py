"""``mine status`` on a real (tiny) catalogue: done, failed, pending and running windows.

What `mine status` calls running and pending (issue 11, item 6; no Ray: the markers a driver
writes): a window is running while a live driver holds its marker (``mining/pipeline/running.py``);
a marker whose driver process is gone (a driver killed with SIGKILL leaves it behind) makes the
window pending again. Markers of another job's params are ignored.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from mining.catalog.records import JobRecord
from mining.catalog.store import Store
from mining.config import load_config
from mining.errors import InputError
from mining.pipeline.executors import LocalExecutor
from mining.pipeline.running import RunningMarkers
from mining.pipeline.status import job_status, print_status
from mining.pipeline.submit import mine_job
from mining.types import Window
from _jobs import tiny_cfg
from _run import env
from conftest import REPO


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_status_of_a_finished_job_and_of_a_window_planned_later(tmp_path, capsys):
    out = str(tmp_path / "cat")
    summary = mine_job(tiny_cfg(), out, executor=LocalExecutor)
    assert summary.ok == 2 and not summary.failed
    rows = job_status(out)
    assert [(r.window, r.status, r.attempts) for r in rows] == [
        ("0000-0000000-0000006", "done", 1), ("0000-0000006-0000012", "done", 1)]
    assert print_status(out) == 0
    shown = capsys.readouterr().out
    assert "2 windows: 2 done, 0 failed, 0 pending" in shown
    assert "no classifier ran (proposer stereo)" in shown  # status says which proposers classified
    assert "  synthetic/0000: 2/2 windows done; stitched" in shown  # per-sequence progress

    # A window planned but never run (e.g. a job interrupted before it started) is pending.
    store = Store(out)
    record = JobRecord.load(store)
    record.windows.append(Window("synthetic", "0000", (12, 18), (10, 18)))
    record.save(store)
    assert [r.status for r in job_status(out)] == ["done", "done", "pending"]
    assert print_status(out) == 0
    shown = capsys.readouterr().out
    assert "1 pending" in shown and "pending  synthetic/0000-0000012-0000018" in shown


def test_status_without_a_job_names_the_folder(tmp_path):
    with pytest.raises(InputError) as e:
        job_status(str(tmp_path))
    assert "job.json" in str(e.value) and str(tmp_path) in str(e.value)


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_a_stereo_only_job_labels_no_tube_known_or_unknown(tmp_path):
    from mining.catalog.views import connect

    cfg = load_config(REPO / "jobs" / "synthetic.toml", [
        "source.options.n_frames=24", "source.options.width=621", "source.options.height=188",
        "source.options.fx=360.77", "window.core=12", "window.context_before=4", "window.context_after=4"])
    out = str(tmp_path / "cat")
    summary = mine_job(cfg, out, executor=LocalExecutor)
    assert summary.candidates > 0 and summary.tubes > 0
    assert summary.known == summary.unknown == 0 and summary.unclassified == summary.tubes
    assert any("no classifier ran (proposer stereo)" in line for line in summary.lines())
    # ... and the summary ends with the settings that would classify (the demo's last word).
    assert any("--set proposals.proposer=onnx+stereo --set proposals.onnx.model_path=" in line
               for line in summary.lines())
    con = connect(out)
    assert con.sql("SELECT count(*) FROM tubes").fetchone()[0] == summary.candidates
    assert con.sql("SELECT count(*) FROM tubes WHERE known IS NOT NULL OR category IS NOT NULL "
                   "OR classified_frames > 0").fetchone()[0] == 0
    assert con.sql("SELECT count(*) FROM unknown_tubes").fetchone()[0] == 0
    assert con.sql("SELECT count(*) FROM known_tubes").fetchone()[0] == 0
    assert con.sql("SELECT count(*) FROM unclassified_tubes").fetchone()[0] == summary.tubes


def test_working_files_sit_where_hive_readers_skip_them(tmp_path):
    """Parts, caches and running markers live under "_" folders: a Hive-style reader of the
    output folder (pyarrow datasets, Spark) sees the catalogue and the manifest only."""
    import pyarrow.dataset as ds

    out = tmp_path / "cat"
    cfg = tiny_cfg()
    assert mine_job(cfg, str(out), executor=LocalExecutor, keep_cache=True).ok == 2
    parts = list((out / "_parts").rglob("*.part"))
    caches = list((out / "_cache").rglob("*.npz.zst"))
    assert parts and caches, "the job left its working files"
    assert not [p for p in out.iterdir() if p.name in ("parts", "cache", "running")], "no unprefixed working folder"
    files = ds.dataset(str(out), format="parquet", exclude_invalid_files=False).files
    seen = {Path(f).relative_to(out).parts[0] for f in files if f.endswith(".parquet")}
    assert seen == {"catalog", "manifest"}
    # and DuckDB's own glob over the whole folder (which does not skip "_" folders) finds no part
    import duckdb

    files = duckdb.sql(f"SELECT DISTINCT filename FROM read_parquet('{out}/**/*.parquet', filename = true)").fetchall()
    assert files and {Path(f).relative_to(out).parts[0] for (f,) in files} == {"catalog", "manifest"}


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_provisional_views_show_finished_windows_of_sequences_not_stitched_yet(tmp_path):
    """While a sequence waits for its stitch, `provisional_tubes` has its finished windows'
    pieces (provisional = true); the final views do not."""
    import shutil

    from mining.catalog.views import connect

    cfg = load_config(REPO / "jobs" / "synthetic.toml", [
        "source.options.n_frames=24", "source.options.width=621", "source.options.height=188",
        "source.options.fx=360.77", "window.core=12", "window.context_before=4", "window.context_after=4"])
    out = tmp_path / "cat"
    summary = mine_job(cfg, str(out), sequences=["0000", "0001"], executor=LocalExecutor)
    assert summary.ok == 4
    con = connect(out)
    final = {s: n for s, n in con.sql("SELECT sequence, count(*) FROM tubes GROUP BY 1").fetchall()}
    assert final.get("0001", 0) > 0
    assert con.sql("SELECT count(*) FROM provisional_tubes WHERE provisional").fetchone()[0] == 0
    con.close()
    # 0001 as it is before its stitch: windows done, parts written, no compacted files, no marker
    for table in ("tubes", "tube_frames", "frames", "windows"):
        shutil.rmtree(out / "catalog" / table / "synthetic" / "0001", ignore_errors=True)
    (out / "catalog" / "_sequences" / "dataset=synthetic" / "sequence=0001.json").unlink()
    con = connect(out)
    assert con.sql("SELECT count(*) FROM tubes WHERE sequence = '0001'").fetchone()[0] == 0  # final: unchanged
    rows = con.sql("SELECT sequence, provisional, \"window\" FROM provisional_tubes").fetchall()
    assert {(s, p) for s, p, _ in rows} == {("0000", False), ("0001", True)}
    assert sum(s == "0000" for s, _, _ in rows) == final["0000"]
    assert {w for s, _, w in rows if s == "0001"} <= {"0001-0000000-0000012", "0001-0000012-0000024"}
    frames = con.sql("SELECT count(*), count(DISTINCT (tube_id, frame, \"window\")) FROM provisional_tube_frames "
                     "WHERE provisional").fetchone()
    assert frames[0] > 0 and frames[0] == frames[1]
    ids = {r[0] for r in con.sql("SELECT tube_id FROM provisional_tube_frames WHERE provisional").fetchall()}
    assert ids <= {r[0] for r in con.sql("SELECT tube_id FROM provisional_tubes WHERE provisional").fetchall()}


def test_progress_bar_shows_phases_eta_and_the_summarys_frames_per_second(tmp_path, capsys):
    summary = mine_job(tiny_cfg(), str(tmp_path / "cat"), executor=LocalExecutor, progress=True)
    bar = capsys.readouterr().err
    assert "windows 2/2 (0 failed)" in bar and "frames/s" in bar and "ETA" in bar
    assert "track 1" in bar or "observe 1" in bar  # the phase of the step in flight
    line = next(x for x in summary.lines() if x.startswith("time:"))
    assert "frames/s (core frames tracked / mining time)" in line
    assert summary.frames == 12 and 0 < summary.mining_seconds <= summary.seconds
    rate = float(line.split("mining: ")[1].split(" frames/s")[0])
    assert rate == pytest.approx(summary.frames / summary.mining_seconds, rel=0.01)


def test_the_eta_counts_the_work_inside_windows():
    """Before any step has finished, the frames the observe steps report give an estimate (≈);
    then each step's measured seconds per frame weigh the frames observed and tracked."""
    from mining.progress import StepBar

    bar = StepBar(4, False, total_frames=400)
    bar.t0 -= 10.0  # ten seconds into the job
    assert bar.eta() == "ETA —"
    bar.observing = 50  # 50 of 400 frames observed in 10 s: 70 s left
    assert bar.eta().startswith("ETA ≈ ") and float(bar.eta().split()[2]) == pytest.approx(70, abs=2)
    bar.observing = 0
    bar.step_finished("observe", 100, 8.0)  # track's cost still unknown: observation alone, 30 s left
    assert bar.eta().startswith("ETA ≈ ") and float(bar.eta().split()[2]) == pytest.approx(30, abs=1)
    bar.step_finished("track", 100, 2.0)  # a quarter of both steps' work done in 10 s: 30 s left
    assert "≈" not in bar.eta() and float(bar.eta().split()[1]) == pytest.approx(30, abs=1)
    bar.observing = 100  # the next window half observed: (300 - 100)·0.08 + 300·0.02 = 22 of 40 s of work left
    assert float(bar.eta().split()[1]) == pytest.approx(10 * 22 / 18, abs=0.6)
    bar.step_finished("observe", 300, 24.0)
    bar.step_finished("track", 300, 6.0)
    assert bar.eta() == ""


def test_an_observe_step_reports_its_frames_as_it_goes(tmp_path):
    """The worker writes its core-frame count while it observes (what the driver's bar shows
    between window results) and removes it when the step ends."""
    from mining.catalog.layout import observed_path
    from mining.pipeline import steps
    from mining.pipeline.submit import open_job

    cfg = tiny_cfg()
    job, schedule, _ = open_job(cfg, str(tmp_path / "cat"))
    window = schedule.windows[0]
    store = job.store()
    seen = []
    real = steps._FrameReport.__call__

    def spy(self, done):  # the real report, and what the file says right after it
        real(self, done)
        if store.exists(self.path):
            seen.append(steps.observed_so_far(store, [window]))
    steps.FRAME_REPORT_S, old = 0.0, steps.FRAME_REPORT_S
    steps._FrameReport.__call__ = spy
    try:
        result = steps.Observe(job).run(window)
    finally:
        steps._FrameReport.__call__, steps.FRAME_REPORT_S = real, old
    assert result.ok and seen == list(range(1, window.core[1] - window.core[0] + 1))
    assert not store.exists(observed_path(window.dataset, window.sequence, window.name))
    assert steps.observed_so_far(store, [window]) == 0


def test_running_needs_a_live_driver(tmp_path, capsys):
    out = str(tmp_path / "cat")
    mine_job(tiny_cfg(), out, executor=LocalExecutor)
    assert not list((tmp_path / "cat").glob("_running/**/*.json")), "a finished run leaves no marker"
    store = Store(out)
    job = JobRecord.load(store)
    later = [Window("synthetic", "0000", (12, 18), (10, 20)), Window("synthetic", "0000", (18, 24), (16, 24))]
    job.windows += later
    job.save(store)

    live = RunningMarkers(store, job.run_id, job.params_hash)  # this process: alive
    live.mark(later[0], "track")
    # A driver that marked a window and died without clearing it (as SIGKILL leaves it).
    subprocess.run([sys.executable, "-c", "import sys; from mining.catalog.store import Store; "
                    "from mining.pipeline.running import RunningMarkers; from mining.types import Window; "
                    "RunningMarkers(Store(sys.argv[1]), sys.argv[2], sys.argv[3])"
                    ".mark(Window('synthetic', '0000', (18, 24), (16, 24)), 'observe')", out, job.run_id,
                    job.params_hash], check=True, cwd=REPO, env=env())
    assert (tmp_path / "cat" / "_running" / "dataset=synthetic" / "sequence=0000" / f"{later[1].name}.json").exists()

    rows = {r.window: r for r in job_status(out)}
    assert rows[later[0].name].status == "running" and "track step, driver pid" in rows[later[0].name].running
    assert rows[later[1].name].status == "pending"
    assert print_status(out) == 0
    shown = capsys.readouterr().out
    assert "4 windows: 2 done, 0 failed, 1 pending, 1 running" in shown
    assert f"running  synthetic/{later[0].name}  attempts 0  track step, driver pid " in shown

    other = RunningMarkers(store, "other-run", "0" * 16)  # another job's params: not this job's window
    other.mark(later[1], "track")
    assert {r.window: r.status for r in job_status(out)}[later[1].name] == "pending"
    live.clear_all()
    assert {r.window: r.status for r in job_status(out)}[later[0].name] == "pending"


def test_the_classify_hint_names_settings_that_load_and_only_where_nothing_classified():
    from mining.proposals.make import classify_hint
    from mining.proposals.registry import CLASSIFYING, proposer_names

    assert classify_hint("onnx+stereo") is None and classify_hint("json") is None
    for proposer in ("stereo", "fastsam+stereo"):
        hint = classify_hint(proposer)
        assert "/path/to" not in hint and "in place of MODEL.onnx" in hint  # a placeholder said to be one
        settings = hint[hint.index("--set"):].replace("--set ", "").split()
        cfg = load_config(REPO / "jobs" / "synthetic.toml", settings)  # the hinted settings are valid keys and values
        assert cfg.proposals.proposer == f"onnx+{proposer}"
        assert set(CLASSIFYING) & set(proposer_names(cfg.proposals.proposer))


def test_status_names_what_a_job_left_and_a_resubmission_sweeps_it(tmp_path, capsys):
    """Issue 40: caches a run left (here kept on purpose, as a run killed after its stitch leaves
    them), a temporary of an unfinished write and a foreign file in the cache folder are each
    listed with a count and a size; a resubmission of the finished job removes the caches and the
    temporary, never the foreign file; with nothing left, status says so."""
    out = tmp_path / "cat"
    assert mine_job(tiny_cfg(), str(out), executor=LocalExecutor, keep_cache=True).ok == 2
    caches = sorted((out / "_cache").rglob("*.npz.zst"))
    assert len(caches) == 2, caches
    folder = caches[0].parent
    tmp = folder / f".{caches[0].name}.tmp-0123456789ab"
    tmp.write_bytes(b"x" * 100)
    foreign = folder / "notes.txt"
    foreign.write_text("mine\n")
    capsys.readouterr()
    assert print_status(str(out)) == 0
    shown = capsys.readouterr().out.splitlines()
    cache_line = [ln for ln in shown if ln.startswith("observation caches: 2 (")]
    assert len(cache_line) == 1 and (" MB)" in cache_line[0] or " KB)" in cache_line[0]), shown
    assert [ln for ln in shown if ln.startswith("temporary files: 1 left by unfinished writes (100 B)")], shown
    assert [ln for ln in shown if ln.startswith(f"foreign files in the cache folders: 1 (5 B), e.g. {foreign}")], shown
    assert not [ln for ln in shown if ln.startswith("left over: nothing")], shown

    summary = mine_job(tiny_cfg(), str(out), executor=LocalExecutor)  # finished: nothing to do
    assert summary.ok == 0 and summary.skipped == 2
    assert not list((out / "_cache").rglob("*.npz.zst")) and not tmp.exists(), "the resubmission left them"
    assert foreign.read_text() == "mine\n", "a file no job wrote was removed"
    capsys.readouterr()
    assert print_status(str(out)) == 0
    shown = capsys.readouterr().out.splitlines()
    assert not [ln for ln in shown if ln.startswith(("observation caches", "temporary files"))], shown
    assert [ln for ln in shown if ln.startswith("foreign files in the cache folders: 1 (5 B)")], shown
    foreign.unlink()
    assert print_status(str(out)) == 0
    shown = capsys.readouterr().out.splitlines()
    assert [ln for ln in shown if ln.startswith("left over: nothing")], shown
