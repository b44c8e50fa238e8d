"""The one rule for names (``mining/names.py``, issue 11 item 2): every real sequence name
of the shared datasets passes it, everything that could act as a path (or a hive key, a
hidden file, a command-line flag) does not, and ``inside`` follows symbolic links."""

from __future__ import annotations

import os

import pytest

from mining.errors import InputError
from mining.names import MAX_NAME_LENGTH, check_name, check_tube_id, inside, tube_folder
from mining.sources import open_source


def test_the_real_sequence_names_are_names(kitti_tracking_root, kitti_raw_root):
    names = open_source("kitti", str(kitti_tracking_root)).sequences() + \
            open_source("kitti-raw", str(kitti_raw_root)).sequences()
    assert "0005" in names and "2011_09_26_drive_0001_sync" in names
    names += ["2014-12-09-13-21-02", "training_0005", "0000", "rosbag2_2024_01_31-12_00_00_0", "a" * MAX_NAME_LENGTH]
    for name in names:
        assert check_name(name, "sequence", "test") == name


@pytest.mark.parametrize("name", ["", ".", "..", "../x", "a/b", "a\\b", "/abs", ".hidden", "-rf", "a..b", "a b",
                                  "sequence=x", "x\n", "caf\u00e9", "a*", "a" * (MAX_NAME_LENGTH + 1), 5, None])
def test_anything_else_is_refused_naming_it_and_its_origin(name):
    with pytest.raises(InputError) as e:
        check_name(name, "sequence", "--sequences")
    assert repr(name) in str(e.value) and "--sequences" in str(e.value)


def test_tube_ids_and_their_folders():
    assert tube_folder("kitti/0005/0000012.003-1") == "kitti_0005_0000012.003-1"
    assert check_tube_id("kitti-raw/2011_09_26_drive_0005_sync/0000001.000", "t")
    for bad in ("..", "a/../../x", "/kitti/0005/1.0", "kitti//1.0", "kitti/0005/", "kitti/.x/1.0"):
        with pytest.raises(InputError, match="tube id"):
            tube_folder(bad)


def test_inside_follows_links(tmp_path):
    dest = tmp_path / "dest"
    (dest / "real").mkdir(parents=True)
    os.symlink(tmp_path, dest / "link")
    assert inside(dest, "real/a.png") == dest / "real" / "a.png"
    for escape in ("../x", "link/x", str(tmp_path / "x")):
        with pytest.raises(InputError, match="outside"):
            inside(dest, escape)
