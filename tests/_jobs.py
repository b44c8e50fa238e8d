"""The small synthetic jobs the tests mine, and what a job wrote (its tables, its files).

* SMALL: half-size frames, 8-frame windows with 4-frame contexts (so tubes cross window
  borders), mined in this process on a ``LocalExecutor``: real files, real DuckDB, no Ray
  where Ray is not the point. ``base_catalogue`` (conftest.py) is it over frames 0:16, mined
  once per session; tests damage or resubmit to a copy (``copy_of``).
* TINY: 12 frames at 320×96, two 6-frame windows (seconds of work once Ray is up), for a
  ``mine submit`` on a local Ray.
* SYNTHETIC: 8 frames, planned in a second (for commands refused before anything runs).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pyarrow as pa

from conftest import REPO
from mining.catalog.views import connect
from mining.config import JobConfig, load_config
from mining.pipeline.executors import LocalExecutor
from mining.pipeline.submit import mine_job
from mining.pipeline.summary import Summary

SEQ = "0000"
N_FRAMES = 24
SMALL = ["window.core=8", "window.context_before=4", "window.context_after=4",
         f"source.options={{n_frames={N_FRAMES}, width=621, height=188}}"]
# The same job on the command line (`mine submit`).
CLI_SMALL = ["--config", str(REPO / "jobs" / "synthetic.toml"), "--sequences", SEQ,
             *(a for s in SMALL[:3] for a in ("--set", s)),
             "--option", f"n_frames={N_FRAMES}", "--option", "width=621", "--option", "height=188"]
BASE_FRAMES = (0, 16)  # two windows: [0, 8) and [8, 16)

TINY = ["--dataset", "synthetic", "--sequences", "0000", "--option", "n_frames=12", "--option", "width=320",
        "--option", "height=96", "--option", "fx=186.0", "--set", "window.core=6", "--set", "window.context_before=2",
        "--set", "window.context_after=2"]
TINY_WINDOWS = ["0000-0000000-0000006", "0000-0000006-0000012"]

SYNTHETIC = ["--dataset", "synthetic", "--sequences", "0000", "--option", "n_frames=8", "--option", "width=621",
             "--option", "height=188"]


def small_cfg(*overrides: str) -> JobConfig:
    return load_config(REPO / "jobs" / "synthetic.toml", [*SMALL, *overrides])


def tiny_cfg() -> JobConfig:
    """TINY as a job config (``mine_job`` in this process)."""
    return load_config(REPO / "jobs" / "synthetic.toml", [
        "source.options.n_frames=12", "source.options.width=320", "source.options.height=96",
        "source.options.fx=186.0", "window.core=6", "window.context_before=2", "window.context_after=2"])


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
    """A copy of ``base_catalogue`` (conftest.py) to damage or resubmit to."""
    shutil.copytree(base[0], dst)
    return dst


def files(out: Path) -> dict[str, bytes]:
    """Every file under ``out``: relative path → bytes."""
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


def catalogue_files(out: Path) -> dict[str, bytes]:
    """The catalogue's files (not the lock, whose content is the last holder's business)."""
    return {k: v for k, v in files(out).items() if k != ".mine.lock"}


def to_hive_layout(out: Path) -> None:
    """Rewrite ``out``'s compacted tables as schema v2 wrote them: under hive folders
    ``catalog/<table>/dataset=D/sequence=S/``, without ``dataset`` / ``sequence`` in the files,
    the tubes rows, job.json and the sequence markers at v2 (each marker's files recorded
    again at their hive paths, with their sizes and sha256)."""
    import hashlib

    import pyarrow.parquet as pq

    moved = {}
    for f in sorted((out / "catalog").glob("*/*/*/*.parquet")):
        table, d, s = f.relative_to(out / "catalog").parts[:3]
        if table.startswith("_") or d.startswith("dataset="):
            continue
        t = pq.read_table(f)
        t = t.drop_columns(["dataset", "sequence"])
        if "schema_version" in t.column_names:
            i = t.schema.get_field_index("schema_version")
            t = t.set_column(i, t.schema.field(i), pa.array([2] * len(t), t.schema.field(i).type))
        dst = out / "catalog" / table / f"dataset={d}" / f"sequence={s}" / f.name
        dst.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(t, dst, compression="zstd")
        f.unlink()
        moved[str(f.relative_to(out))] = str(dst.relative_to(out))
    for p in list((out / "catalog").glob("*/*/*")):
        if p.is_dir() and not any(p.iterdir()):
            p.rmdir()
            if not any(p.parent.iterdir()):
                p.parent.rmdir()
    for m in (out / "catalog" / "_sequences").rglob("*.json"):
        rec = json.loads(m.read_text())
        rec["files"] = {moved.get(k, k): v for k, v in rec["files"].items()}
        for rel in rec["files"]:
            data = (out / rel).read_bytes()
            rec["files"][rel] = {"size": len(data), "sha256": hashlib.sha256(data).hexdigest()}
        rec["schema_version"] = 2
        m.write_text(json.dumps(rec, indent=1))
    job = json.loads((out / "job.json").read_text())
    job["schema_version"] = 2
    (out / "job.json").write_text(json.dumps(job, indent=1))
