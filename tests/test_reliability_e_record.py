"""A catalogue without a readable job.json is not an empty folder (issue 19, scope item 2).

The adversarial run deleted ``OUT/job.json`` (or moved it away, as its own error message
suggested) and submitted a different job to the same ``--out``: the old catalogue (78 tubes)
was silently replaced (77 tubes), nothing kept under ``_replaced/``. Now such a folder is
refused, naming job.json and offering ``--new-run``, which keeps the old catalogue under
``OUT/_replaced/`` like any other; an unreadable job.json's message no longer says to move
it away, and ``--new-run`` over it works too. ``--new-run`` never moves a catalogue
through a link planted at ``OUT/_replaced``.

Real files, the small synthetic job of ``_reliability_c.py`` mined in this process (the
``mine submit`` case in a process of its own).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mining.catalog.layout import UnreadableRecord
from mining.catalog.safe_files import LinkError
from mining.errors import InputError
from _reliability_c import CLI_SMALL, REPO, copy_of, mine, tables

pytest_plugins = ["_reliability_c_fixtures"]  # base_catalogue: the small job over frames 0:16, mined once


def _files(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


def _catalogue_files(out: Path) -> dict[str, bytes]:
    """The catalogue's files (not the lock, whose content is the last holder's business)."""
    return {k: v for k, v in _files(out).items() if k != ".mine.lock"}


@pytest.mark.parametrize("mode", ["resume", "extend"])
def test_a_catalogue_whose_job_json_is_gone_is_not_mined_over(base_catalogue, tmp_path, mode):
    out = copy_of(base_catalogue, tmp_path / "out")
    (out / "job.json").rename(tmp_path / "job.json.moved-away")
    before = _catalogue_files(out)
    with pytest.raises(InputError) as e:
        mine(out, (0, 8), mode=mode)  # another job: the old code replaced the catalogue with it
    msg = str(e.value)
    assert f"{out / 'job.json'}: missing" in msg and "catalog/" in msg and "--new-run" in msg, msg
    assert "move it away" not in msg
    assert _catalogue_files(out) == before and not (out / "_replaced").exists()


def test_an_unreadable_job_json_says_new_run_not_move_it_away(base_catalogue, tmp_path):
    out = copy_of(base_catalogue, tmp_path / "out")
    (out / "job.json").write_text("{ truncated")
    before = _catalogue_files(out)
    with pytest.raises(UnreadableRecord) as e:
        mine(out)
    assert "--new-run" in str(e.value) and "_replaced" in str(e.value) and "move it away" not in str(e.value)
    assert _catalogue_files(out) == before


@pytest.mark.slow  # mines a window
@pytest.mark.parametrize("damage", ["missing", "unreadable"])
def test_new_run_keeps_a_catalogue_without_a_readable_job_json_under_replaced(base_catalogue, tmp_path, capsys,
                                                                              damage):
    out = copy_of(base_catalogue, tmp_path / "out")
    if damage == "missing":
        (out / "job.json").unlink()
    else:
        (out / "job.json").write_text("{ truncated")
    old = _catalogue_files(out)
    s = mine(out, (0, 8), mode="new")
    assert s.ok == 1 and not s.failed, s.lines()
    moved, = (out / "_replaced").iterdir()
    assert moved.name.startswith("unknown-run-")
    assert str(moved) in capsys.readouterr().err
    kept = {k.split("/", 2)[2]: v for k, v in _files(out).items() if k.startswith("_replaced/")}
    assert kept == old, "every file of the old catalogue is kept, byte for byte"
    assert len(tables(out)["frames"]) == 8
    assert json.loads((out / "job.json").read_text())["identity"]["frames.0000"] == "0:8"


def test_new_run_never_moves_the_catalogue_through_a_link(base_catalogue, tmp_path):
    """``OUT/_replaced`` planted as a link elsewhere: the old code made the run's folder
    there and moved the whole catalogue out of --out."""
    out = copy_of(base_catalogue, tmp_path / "out")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (out / "_replaced").symlink_to(elsewhere, target_is_directory=True)
    before = _catalogue_files(out)
    with pytest.raises(LinkError, match="_replaced: is a link"):
        mine(out, (0, 8), mode="new")
    assert list(elsewhere.iterdir()) == []
    assert _catalogue_files(out) == before


@pytest.mark.slow  # a `mine submit` process (refused before Ray starts)
def test_mine_submit_over_a_catalogue_without_job_json_is_refused_in_one_line(base_catalogue, tmp_path):
    out = copy_of(base_catalogue, tmp_path / "out")
    (out / "job.json").unlink()
    base_tables = tables(out)
    done = subprocess.run([sys.executable, "-m", "mining.cli", "submit", *CLI_SMALL, "--frames", "0:8",
                           "--out", str(out), "--workers", "1", "--no-progress"],
                          cwd=REPO, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(REPO), "RAY_USAGE_STATS_ENABLED": "0"})
    assert done.returncode == 2, done.stdout + done.stderr
    err = done.stderr.strip().splitlines()
    assert len(err) == 1 and "job.json: missing" in err[0] and "--new-run" in err[0], done.stderr
    assert tables(out) == base_tables and not (out / "job.json").exists()
