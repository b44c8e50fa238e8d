"""Nothing executes from the output folder (issue 11, item 1): a pickle payload planted at
every observation-cache path, old (``.pkl``) and new, never runs on a resubmit.

The job is a real synthetic recording mined in this process (LocalExecutor, real files):
the observe steps run, then someone who can write to ``--out`` replaces every cache with
a payload whose ``__reduce__`` writes a marker file, and the job is resubmitted."""

from __future__ import annotations

import pytest

import builtins
import pickle
from pathlib import Path

from mining.catalog.store import Store
from mining.catalog.views import connect
from mining.config import load_config
from mining.pipeline.executors import LocalExecutor
from mining.pipeline.steps import Observe
from mining.pipeline.submit import mine_job, open_job

REPO = Path(__file__).resolve().parents[1]
# Every name an observation cache has had: pickle before issue 11, zstd-framed NPZ since.
CACHE_NAMES = ("{w}.pkl", "{w}.npz.zst")


def _cfg():
    return load_config(REPO / "jobs" / "synthetic.toml", [
        "source.options.n_frames=12", "source.options.width=320", "source.options.height=96",
        "source.options.fx=186.0", "window.core=6", "window.context_before=2", "window.context_after=2"])


class _Payload:
    """Unpickling this runs ``code``: what an attacker plants."""

    def __init__(self, code: str):
        self.code = code

    def __reduce__(self):
        return builtins.exec, (self.code,)


def _tubes(out: str) -> list[tuple]:
    con = connect(out)
    try:
        return con.execute("SELECT tube_id, t_start, t_end, n_frames, round(score, 9), selected FROM tubes "
                           "ORDER BY tube_id").fetchall()
    finally:
        con.close()


@pytest.mark.slow  # over ~2.5 s: the fast tier stays under 3 minutes
def test_planted_pickles_never_run_on_resubmit(tmp_path):
    marker = tmp_path / "pwned"
    payload = pickle.dumps(_Payload(f"open({str(marker)!r}, 'w').write('ran')"))
    pickle.loads(payload)  # the control: the payload is live
    assert marker.read_text() == "ran"
    marker.unlink()

    cfg = _cfg()
    clean = str(tmp_path / "clean")
    assert mine_job(cfg, clean, executor=LocalExecutor).ok == 2

    # A job whose observe steps ran and whose driver died before any track.
    out = str(tmp_path / "out")
    job, schedule, _ = open_job(cfg, out)
    for w in schedule.windows:
        assert Observe(job).run(w).ok
    store = Store(out)
    planted = []
    for w in schedule.windows:
        for name in CACHE_NAMES:
            rel = f"_cache/obs/dataset={w.dataset}/sequence={w.sequence}/{name.format(w=w.name)}"
            store.write_bytes(rel, payload)
            planted.append(rel)
    assert len(planted) == 4 and all(store.exists(rel) for rel in planted)

    summary = mine_job(cfg, out, executor=LocalExecutor)  # the resubmission

    assert not marker.exists(), "a planted pickle ran"
    assert summary.ok == 2 and not summary.failed
    assert sorted(summary.recomputed) == [w.name for w in schedule.windows], "the planted caches are reported"
    assert _tubes(out) == _tubes(clean), "the recomputed windows give the clean run's catalogue"
    assert not any(store.exists(rel) for rel in planted), "the caches (and the old .pkl ones) are gone after use"
