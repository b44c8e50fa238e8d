"""`mine submit` refuses a catalogue inside the source's root before anything is written: the
source's next listing would read the catalogue's folders as data (a RobotCar root lists them
as traversals)."""

from __future__ import annotations

import os

import pytest
from _run import cli, clean_error

from mining.commands.submit import check_out_beside_root
from mining.errors import ConfigError


def test_a_catalogue_inside_the_root_is_refused_in_one_line_before_anything_is_written(tmp_path, capsys):
    root = tmp_path / "robotcar"
    root.mkdir()
    rc, _, err = cli(capsys, "submit", "--dataset", "oxford", "--root", str(root), "--workers", "1",
                     "--out", str(root / "catalog"))
    line = clean_error(err)
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert f"--out {root / 'catalog'} lies inside the source's root {root}" in line, line
    assert os.listdir(root) == [], "nothing written"


@pytest.mark.parametrize(("out", "root", "inside"), [
    ("/data/rc/catalog", "/data/rc", True),
    ("/data/rc", "/data/rc", True),
    ("/data/rc-out", "/data/rc", False),  # a sibling whose name starts the same
    ("/data/out", "/data/rc", False),
    ("s3://b/rc/catalog?region=eu-west-2", "s3://b/rc?region=eu-west-2", True),
    ("s3://b/rc-catalog", "s3://b/rc/", False),
    ("s3://b/rc/catalog", "/data/rc", False),  # one local, one remote: never the same place
])
def test_inside_means_the_same_folder_or_below_it(out, root, inside):
    if inside:
        with pytest.raises(ConfigError, match="lies inside the source's root"):
            check_out_beside_root(out, root)
    else:
        check_out_beside_root(out, root)


def test_a_relative_out_is_compared_where_it_resolves(tmp_path, monkeypatch):
    (tmp_path / "data").mkdir()
    monkeypatch.chdir(tmp_path / "data")
    with pytest.raises(ConfigError):
        check_out_beside_root("out", str(tmp_path / "data"))
    check_out_beside_root("../out", str(tmp_path / "data"))
