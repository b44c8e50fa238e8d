"""Shared pieces of the reliability suite's identity, locking and integrity cases (issue 11, items 4-5).

One small synthetic job (half-size frames, 8-frame windows with 4-frame contexts, so tubes
cross window borders) mined in this process on a ``LocalExecutor``: real files, real
DuckDB, no Ray where Ray is not the point.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from mining.catalog.views import connect
from mining.config import JobConfig, load_config
from mining.pipeline.executors import LocalExecutor
from mining.pipeline.submit import mine_job
from mining.pipeline.summary import Summary

REPO = Path(__file__).resolve().parents[1]
SEQ = "0000"
N_FRAMES = 24
SMALL = ["window.core=8", "window.context_before=4", "window.context_after=4",
         f"source.options={{n_frames={N_FRAMES}, width=621, height=188}}"]
# The same job on the command line (`mine submit`).
CLI_SMALL = ["--config", str(REPO / "jobs" / "synthetic.toml"), "--sequences", SEQ,
             *(a for s in SMALL[:3] for a in ("--set", s)),
             "--option", f"n_frames={N_FRAMES}", "--option", "width=621", "--option", "height=188"]
BASE_FRAMES = (0, 16)  # two windows: [0, 8) and [8, 16)


def small_cfg(*overrides: str) -> JobConfig:
    return load_config(REPO / "jobs" / "synthetic.toml", [*SMALL, *overrides])


def mine(out: Path, frames: tuple[int, int | None] = BASE_FRAMES, cfg: JobConfig | None = None,
         **kw) -> Summary:
    """The small job mined into ``out`` in this process."""
    return mine_job(cfg or small_cfg(), str(out), [SEQ], frames, executor=LocalExecutor, **kw)


def tables(out: Path) -> dict[str, list[tuple]]:
    """The catalogue's tubes, tube_frames and frames, every column but the run id, in a fixed order."""
    con = connect(out)
    try:
        return {"tubes": con.sql("SELECT * EXCLUDE (run_id) FROM tubes ORDER BY tube_id").fetchall(),
                "tube_frames": con.sql("SELECT * FROM tube_frames ORDER BY tube_id, frame").fetchall(),
                "frames": con.sql("SELECT * FROM frames ORDER BY frame").fetchall()}
    finally:
        con.close()


def copy_of(base: tuple[Path, dict], dst: Path) -> Path:
    """A copy of ``base_catalogue`` (``_reliability_c_fixtures.py``) to damage or resubmit to."""
    shutil.copytree(base[0], dst)
    return dst
