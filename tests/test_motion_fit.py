"""Speed from a line fitted to footpoints: static objects read "not moving", movers their truth."""

import numpy as np

from mining.catalog.rows import MOTION_K_SIGMA, motion_fit

FPS = 10.0  # KITTI's frame rate
DEPTH_SIGMA_M = 0.5  # a KITTI-like stereo depth σ at ~25 m (Z²/(f·B)·σ_d with f·B ≈ 387 px·m, σ_d ≈ 0.3 px)


def _track(v: np.ndarray, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = np.arange(n) / FPS
    foot = np.array([0.0, 1.6, 25.0]) + t[:, None] * v
    foot[:, 2] += rng.normal(0, DEPTH_SIGMA_M, n)  # depth noise dominates stereo positions
    return t, foot


def test_static_object_is_not_moving_despite_step_noise():
    t, foot = _track(np.zeros(3), 13, seed=5)
    summed = np.linalg.norm(np.diff(foot, axis=0), axis=1).sum()
    speed, sigma, _, _ = motion_fit(t, foot)
    assert summed / (t[-1] - t[0]) > 3.0  # the old summed-steps estimate: metres per second of noise
    assert speed <= MOTION_K_SIGMA * sigma


def test_moving_car_speed_within_its_uncertainty():
    v = np.array([0.0, 0.0, 8.0])
    t, foot = _track(v, 20, seed=7)
    speed, sigma, path, path_sigma = motion_fit(t, foot)
    assert abs(speed - 8.0) < MOTION_K_SIGMA * sigma
    assert speed > MOTION_K_SIGMA * sigma
    assert abs(path - 8.0 * (t[-1] - t[0])) < MOTION_K_SIGMA * path_sigma


def test_smooth_filtered_track_is_floored_by_stereo_noise():
    # a filtered track drifts smoothly (no scatter) by less than its stereo depth noise
    t = np.arange(4) / FPS
    foot = np.array([0.0, 1.6, 60.0]) + t[:, None] * np.array([0.0, 0.0, 6.0])
    foot[:, 0] += np.array([0.0, 0.01, -0.01, 0.0])
    bare, bare_sigma, _, _ = motion_fit(t, foot)
    _, sigma, _, _ = motion_fit(t, foot, np.full(4, 60.0 ** 2 / 387.6 * 0.3))
    assert bare > MOTION_K_SIGMA * bare_sigma  # residuals alone call depth drift "moving"
    assert bare <= MOTION_K_SIGMA * sigma
