"""The one writer of tubes as KITTI tracking results (`mine track` and `mine export` feed it)."""

from __future__ import annotations

import numpy as np

from mining.formats.kitti_tracking import ResultFrame, ResultTrack, kitti_type, read_kitti_tracking, write_tracking_results


def test_rows_in_frame_order_bottom_centre_in_rect0_and_placeholders(tmp_path):
    box = (10.0, 20.0, 50.0, 80.0)
    tracks = [
        ResultTrack(7, "Car", 3.5, [ResultFrame(1, True, box, (2.0, 1.5, 4.0), (1.0, 0.5, 20.0)),
                                    ResultFrame(2, False, box, (2.0, 1.5, 4.0), (1.0, 0.5, 21.0))]),
        ResultTrack(3, "Misc", 1.25, [ResultFrame(1, True, box, (2.0, np.nan, 4.0), (0.0, 0.0, 9.0)),
                                      ResultFrame(0, True, box, (1.0, 1.0, 1.0), (np.nan, 0.0, 9.0))]),
    ]
    t = np.array([0.06, 0.0, 0.0])
    path = tmp_path / "sub" / "0000.txt"
    assert write_tracking_results(path, tracks, lambda p: p - t) == 3  # the unobserved frame is left out
    rows = read_kitti_tracking(path, require_score=True)
    assert rows.frame.tolist() == [0, 1, 1] and rows.track_id.tolist() == [3, 3, 7]
    np.testing.assert_allclose(rows.location[2], [1.0 - 0.06, 0.5 + 0.75, 20.0])  # bottom centre, rect0
    np.testing.assert_allclose(rows.dimensions[2], [1.5, 2.0, 4.0])  # h w l
    for i in (0, 1):  # no finite position, or no finite size: placeholders
        np.testing.assert_allclose(rows.location[i], [-1000.0] * 3)
        np.testing.assert_allclose(rows.dimensions[i], [-1.0] * 3)
    np.testing.assert_allclose(rows.score, [1.25, 1.25, 3.5])
    # without a map into rectified camera 0 the 3D fields are placeholders; all frames with observed_only=False
    assert write_tracking_results(path, tracks, None, observed_only=False) == 4
    assert (read_kitti_tracking(path).location == -1000.0).all()


def test_kitti_type():
    assert kitti_type("car", True) == "Car" and kitti_type("bus", True) == "Truck"
    assert kitti_type("dog", True) == "Misc"
    # the type follows the known flag: an unknown tube is Misc even when its best guess is car
    assert kitti_type("unknown", False) == "Misc" and kitti_type("unknown", False, "Car") == "Misc"
    assert kitti_type(None, None, "Car") == "Car" and kitti_type(None, None) == "Misc"
