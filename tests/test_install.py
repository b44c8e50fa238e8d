"""A non-editable install (what `pip install tube-miner` gives a user) carries what `mine` reads at
run time: the catalogue's views, `mine view`'s pages and the fitted weights, so it opens a catalogue
from anywhere."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from conftest import REPO


@pytest.mark.slow
def test_installed_package_queries_a_catalogue(catalogue, tmp_path):
    out, tables = catalogue
    site = tmp_path / "site"
    # The build's own scratch (build/, *.egg-info) would land in the checkout; copy the sources instead.
    src = tmp_path / "src"
    files = subprocess.run(["git", "-C", str(REPO), "ls-files", "-z", "--", "pyproject.toml", "README.md", "mining"],
                           check=True, capture_output=True).stdout.decode().split("\0")
    for rel in filter(None, files):
        if (REPO / rel).is_file():
            (src / rel).parent.mkdir(parents=True, exist_ok=True)
            (src / rel).write_bytes((REPO / rel).read_bytes())
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--target",
                    str(site), str(src)], check=True, capture_output=True, timeout=300)
    assert (site / "mining" / "catalog" / "views.sql").is_file()
    assert (site / "mining" / "view" / "static" / "index.html").is_file()
    assert (site / "mining" / "score" / "fits" / "rows.toml").is_file()
    code = ("import mining, sys; from mining.cli import main; "
            "assert mining.__file__.startswith(sys.argv[1]), mining.__file__; "
            "sys.exit(main(['query', '--out', sys.argv[2], '--format', 'csv', "
            "'SELECT count(*) AS n FROM selected_tubes']))")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["PYTHONPATH"] = str(site)
    done = subprocess.run([sys.executable, "-c", code, str(site), str(out)], capture_output=True, text=True,
                          cwd=tmp_path, env=env, timeout=300)
    assert done.returncode == 0, done.stderr
    n_selected = sum(t["selected"] for t in tables["tubes"].to_pylist())
    assert [v.strip('"') for v in done.stdout.split()] == ["n", str(n_selected)]
