"""Calibration sanity before a job starts (issue 11, item 7), on real KITTI 0005 frames whose
calibration file is edited: fx = 0 was accepted (16 frames "done" with 0 proposals), NaN
fx was blamed on "left and right swapped?", and a focal length or baseline off by a
factor passed unnoticed. Now the sequence is refused in the driver, naming the file and
the number."""

from __future__ import annotations

import pytest

from _kitti_copy import kitti_copy, set_calib_value
from _run import clean_error, cli


@pytest.fixture
def kitti(tmp_path, kitti_tracking_root):
    return kitti_copy(tmp_path / "kitti", kitti_tracking_root, n_frames=4)


def _submit(capsys, kitti, out, *args):
    return cli(capsys, "submit", "--dataset", "kitti", "--root", str(kitti), "--sequences", "0005",
               "--out", str(out), "--workers", "1", "--no-progress", *args)


@pytest.mark.parametrize("value", ["0.0", "nan", "-721.5377"], ids=["zero", "nan", "negative"])
def test_bad_focal_length_is_refused_naming_file_and_value(tmp_path, capsys, kitti, value):
    calib = kitti / "training" / "calib" / "0005.txt"
    set_calib_value(calib, "P2", 0, value)
    rc, stdout, stderr = _submit(capsys, kitti, tmp_path / "out")
    assert rc == 2, (rc, stdout, stderr)
    line = clean_error(stderr)
    assert str(calib) in line and f"fx = {float(value)!r}" in line and "not a positive finite focal length" in line
    assert "swapped" not in line
    assert not (tmp_path / "out" / "job.json").exists()


@pytest.mark.parametrize("key, index, value, expected", [
    ("P2", 0, "7.215377e+03", "fy / fx"),  # fx ten times too large, fy right
    ("P3", 3, "-3.395242e+05", "baseline"),  # the baseline in millimetres
], ids=["fx-typo", "baseline-mm"])
def test_implausible_calibration_is_refused(tmp_path, capsys, kitti, key, index, value, expected):
    set_calib_value(kitti / "training" / "calib" / "0005.txt", key, index, value)
    rc, stdout, stderr = _submit(capsys, kitti, tmp_path / "out")
    assert rc == 2, (rc, stdout, stderr)
    line = clean_error(stderr)
    assert "kitti/0005" in line and expected in line and "implausible" in line


def test_check_calib_names_each_number():
    from mining.errors import InputError
    from mining.sources.base import check_calib
    from mining.types import StereoCalib

    good = StereoCalib(721.5377, 721.5377, 609.6, 172.9, 0.5327, 1242, 375)
    check_calib(good, None, (5.0, 170.0), (0.01, 5.0), (0.5, 2.0))
    for field, bad, words in (("fx", 0.0, "fx = 0.0"), ("fy", float("nan"), "fy = nan"),
                              ("baseline_m", float("inf"), "baseline_m = inf"), ("cx", 5000.0, "principal point")):
        calib = StereoCalib(**{**good.__dict__, field: bad})
        with pytest.raises(InputError, match=words):
            check_calib(calib, "calib.txt")
    with pytest.raises(InputError, match="field of view"):
        check_calib(StereoCalib(**{**good.__dict__, "fx": 20.0, "fy": 20.0}), None, fov_deg=(5.0, 170.0))
