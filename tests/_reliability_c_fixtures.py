"""The session fixture of the reliability suite's identity, lock and integrity files: one base
job mined once for all three (each file names this module in ``pytest_plugins``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from _reliability_c import mine, tables


@pytest.fixture(scope="session")
def base_catalogue(tmp_path_factory) -> tuple[Path, dict]:
    """The small job over frames 0:16, mined once: (folder, its tables). Tests copy it."""
    out = tmp_path_factory.mktemp("reliability_c") / "base"
    s = mine(out)
    assert s.ok == 2 and not s.failed, s.lines()
    t = tables(out)
    assert t["tubes"] and len(t["frames"]) == 16, "the base job found no tubes: comparisons would be empty"
    return out, t
