"""Pose chaining and plane moving (mining/geometry/poses.py): segments start where no egomotion
links a frame to the one before it, and a carried plane keeps the world's ground points on it."""

from __future__ import annotations

import numpy as np

from mining.geometry.poses import PoseChain, chain_egomotion, chain_poses, move_plane
from mining.types import GroundPlane


def _motion(yaw: float, t: tuple[float, float, float]) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[:3, 3] = t
    return T


def test_poses_chain_within_a_segment_and_restart_where_no_egomotion_links_frames():
    A, B = _motion(0.02, (0.1, 0.0, -1.0)), _motion(-0.01, (0.0, 0.02, -0.9))
    # frame 0: its own world; 1: chained; 2: failed egomotion; 3: chained; 4: after a missing frame (position 5)
    got = chain_poses([0, 1, 2, 3, 5], [A, A, None, B, B])
    assert [s for _, s in got] == [0, 0, 1, 1, 2]
    np.testing.assert_allclose(got[0][0], np.eye(4))
    np.testing.assert_allclose(got[1][0], np.linalg.inv(A))  # pose_cur = pose_prev · T_cur_prev⁻¹
    np.testing.assert_allclose(got[2][0], np.eye(4))
    np.testing.assert_allclose(got[3][0], np.linalg.inv(B))
    np.testing.assert_allclose(got[4][0], np.eye(4))
    chain = PoseChain()  # the frame loop's form: the same poses, step by step
    for (pose, segment), T in zip(got[:4], [A, A, None, B]):
        p, s = chain.step(T)
        np.testing.assert_array_equal(p, pose)
        assert s == segment


def test_chain_egomotion_is_one_world_nan_after_a_failure():
    A = _motion(0.02, (0.1, 0.0, -1.0))
    poses = chain_egomotion([None, A, None, A])
    np.testing.assert_allclose(poses[1], np.linalg.inv(A))
    assert np.isnan(poses[2:]).all()


def test_a_moved_plane_holds_the_same_ground_points_in_the_next_camera():
    n = np.array([0.0, -1.0, 0.0])
    plane = GroundPlane(n, 1.65, 1234, True)  # 1.65 m below the camera
    T = _motion(0.05, (0.2, 0.01, -1.2))
    moved = move_plane(plane, T)
    ground_prev = np.array([[3.0, 1.65, 10.0], [-2.0, 1.65, 25.0]])
    ground_cur = ground_prev @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(ground_cur @ moved.normal + moved.d, 0.0, atol=1e-12)
    assert moved.ok and moved.inliers == 1234 and np.isclose(np.linalg.norm(moved.normal), 1.0)
