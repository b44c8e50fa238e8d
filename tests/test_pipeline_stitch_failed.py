"""Stitching around a window that failed after its observations were cached.

A window whose track step fails (e.g. its parts could not be written: a full disk) leaves
its observation cache behind, so its neighbours' tubes run through its core frames as
context. Its own frames rows are missing, so the stitch must leave those context rows
out; before, ``stitch_sequence`` looked up their positions and raised ``KeyError``.
"""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pytest

from mining.catalog.layout import part_path
from mining.catalog.store import Store
from mining.config import load_config
from mining.pipeline.executors import LocalExecutor
from mining.pipeline.stitch import stitch_sequence
from mining.pipeline.submit import mine_job
from mining.sources.synthetic import SyntheticSource
from mining.catalog.rows import RunInfo
from mining.types import plan_windows

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow  # a 24-frame job in this process


def test_the_stitch_leaves_out_a_failed_windows_core(tmp_path):
    cfg = load_config(REPO / "jobs" / "synthetic.toml", [
        "source.options.n_frames=24", "source.options.width=621", "source.options.height=188",
        "source.options.fx=360.77", "window.core=8", "window.context_before=4", "window.context_after=4"])
    out = tmp_path / "catalog"
    assert mine_job(cfg, str(out), ["0000"], executor=LocalExecutor).ok == 3
    plan = SyntheticSource(**cfg.source.options).plan("0000")
    windows = plan_windows(plan, 8, 4, 4)
    assert len(windows) == 3
    store = Store(str(out))
    parts = {t: [store.read_table(part_path(t, "synthetic", "0000", w.name)) for w in windows]
             for t in ("tubes", "tube_frames", "frames")}
    middle = windows[1]
    reach = [r["frame"] for k in (0, 2) for r in parts["tube_frames"][k].select(["frame"]).to_pylist()
             if middle.core[0] <= r["frame"] < middle.core[1]]
    assert reach, "no neighbour's tube runs into the middle core: nothing to test"

    # The middle window failed: only its neighbours' parts are stitched.
    kept = [windows[0], windows[2]]
    tables = {t: pa.concat_tables([parts[t][0], parts[t][2]]) for t in parts}
    result = stitch_sequence(kept, tables["tubes"], tables["tube_frames"], tables["frames"], cfg,
                             RunInfo("synthetic", "0000", "run", cfg.params_hash))
    frames = set(result["tube_frames"].column("frame").to_pylist())
    assert frames & set(range(*windows[0].core)) and frames & set(range(*windows[2].core))
    assert not frames & set(range(*middle.core)), "tube frames in the failed window's core"
