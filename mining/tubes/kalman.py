"""The tube's Kalman filter: constant velocity on the ground plane (REFERENCE.md).

State x = [x, y, z, vx, vz, w, h, l]: the ground footpoint in world coordinates
(metres, y down), the velocity on the ground plane and the 3D size. The filter runs in
either direction of time (dt < 0 for the backward enumeration). filterpy does the
algebra of a tube's filter; this class only builds F, Q, H and R. The backward probe of
tube starts runs many filters at once on stacked arrays (``*_states`` below: filterpy's
equations, agreeing with it to rounding).
"""

from __future__ import annotations

import numpy as np
from filterpy.kalman import KalmanFilter

from mining.tubes.config import KalmanConfig

DIM_X = 8
POS = slice(0, 3)
VEL = slice(3, 5)
SIZE = slice(5, 8)

# Measurement matrices: footpoint + size, optionally with the ground velocity.
H_POS_SIZE = np.zeros((6, DIM_X))
H_POS_SIZE[0:3, 0:3] = np.eye(3)
H_POS_SIZE[3:6, 5:8] = np.eye(3)
H_FULL = np.eye(DIM_X)


def transition(dt: float) -> np.ndarray:
    """Constant velocity on the ground plane over ``dt`` seconds (negative: backwards)."""
    F = np.eye(DIM_X)
    F[0, 3] = dt
    F[2, 4] = dt
    return F


def process_noise(dt: float, cfg: KalmanConfig) -> np.ndarray:
    # REFERENCE's noise is per 0.1 s step; a random walk's variance grows linearly in time.
    scale = abs(dt) / cfg.process_dt_s
    std = np.concatenate([cfg.process_std_position, cfg.process_std_velocity, [cfg.process_std_size] * 3])
    return np.diag(np.square(std)) * scale


def prior_velocity_cov(cfg: KalmanConfig, R_world_cam: np.ndarray | None = None) -> np.ndarray:
    """(2, 2) ground-velocity covariance of a tube started without flow, in the world frame.

    The prior is given along the camera's axes (lateral, depth: depth is the uncertain
    one), so it turns with the camera; with a fixed diagonal in the world, a tube's start
    would depend on which frame the world happens to be (e.g. where a window begins).
    """
    V = np.diag([cfg.initial_var_velocity[0], 0.0, cfg.initial_var_velocity[1]])
    if R_world_cam is not None:
        V = R_world_cam @ V @ R_world_cam.T
    return V[np.ix_([0, 2], [0, 2])]


class TubeFilter:
    """Kalman filter of one tube; ``x`` and ``P`` are filterpy's state and covariance."""

    def __init__(self, footpoint: np.ndarray, cov: np.ndarray, size: np.ndarray,
                 velocity: np.ndarray | None, velocity_cov: np.ndarray | None, cfg: KalmanConfig,
                 R_world_cam: np.ndarray | None = None):
        self.cfg = cfg
        self.kf = KalmanFilter(dim_x=DIM_X, dim_z=DIM_X)
        x = np.zeros(DIM_X)
        x[POS] = footpoint
        x[SIZE] = np.clip(size, 0.0, cfg.max_size_m)
        P = np.zeros((DIM_X, DIM_X))
        P[POS, POS] = cov
        P[SIZE, SIZE] = np.diag(np.square(cfg.measurement_std_size))
        if velocity is not None and np.isfinite(velocity).all():
            x[VEL] = velocity[[0, 2]]
            P[VEL, VEL] = velocity_cov[np.ix_([0, 2], [0, 2])]
        else:
            P[VEL, VEL] = prior_velocity_cov(cfg, R_world_cam)
        self.kf.x = x
        self.kf.P = P

    @property
    def x(self) -> np.ndarray:
        return self.kf.x

    @property
    def P(self) -> np.ndarray:
        return self.kf.P

    def copy(self) -> TubeFilter:
        other = TubeFilter.__new__(TubeFilter)
        other.cfg = self.cfg
        other.kf = KalmanFilter(dim_x=DIM_X, dim_z=DIM_X)
        other.kf.x = self.kf.x.copy()
        other.kf.P = self.kf.P.copy()
        return other

    def F(self, dt: float) -> np.ndarray:
        return transition(dt)

    def Q(self, dt: float) -> np.ndarray:
        return process_noise(dt, self.cfg)

    def predict(self, dt: float) -> None:
        self.kf.predict(F=self.F(dt), Q=self.Q(dt))
        self.kf.x[SIZE] = np.clip(self.kf.x[SIZE], 0.0, self.cfg.max_size_m)

    def R(self, cov: np.ndarray, velocity_cov: np.ndarray | None) -> np.ndarray:
        size_var = np.diag(np.square(self.cfg.measurement_std_size))
        if velocity_cov is None:
            R = np.zeros((6, 6))
            R[0:3, 0:3] = cov
            R[3:6, 3:6] = size_var
            return R
        R = np.zeros((DIM_X, DIM_X))
        R[POS, POS] = cov
        R[VEL, VEL] = velocity_cov[np.ix_([0, 2], [0, 2])]
        R[SIZE, SIZE] = size_var
        return R

    def update(self, footpoint: np.ndarray, cov: np.ndarray, size: np.ndarray,
               velocity: np.ndarray | None, velocity_cov: np.ndarray | None) -> None:
        size = np.clip(size, 0.0, self.cfg.max_size_m)
        if velocity is not None and np.isfinite(velocity).all():
            z = np.concatenate([footpoint, velocity[[0, 2]], size])
            self.kf.update(z, R=self.R(cov, velocity_cov), H=H_FULL)
        else:
            z = np.concatenate([footpoint, size])
            self.kf.update(z, R=self.R(cov, None), H=H_POS_SIZE)

    def position_innovation_cov(self, obs_cov: np.ndarray) -> np.ndarray:
        """(N, 3, 3) innovation covariance of the footpoint for N observation covariances."""
        return self.kf.P[POS, POS][None] + obs_cov


# --- many filters at once (the backward probe of all of a frame's start candidates) ----


def initial_states(footpoint: np.ndarray, cov: np.ndarray, size: np.ndarray, velocity: np.ndarray,
                   velocity_cov: np.ndarray, cfg: KalmanConfig,
                   R_world_cam: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(C, 8) states and (C, 8, 8) covariances of C fresh filters, as ``TubeFilter`` starts
    them; rows of ``velocity`` with NaN start from the prior velocity variance."""
    n = len(footpoint)
    x = np.zeros((n, DIM_X))
    P = np.zeros((n, DIM_X, DIM_X))
    x[:, POS] = footpoint
    x[:, SIZE] = np.clip(size, 0.0, cfg.max_size_m)
    P[:, POS, POS] = cov
    P[:, SIZE, SIZE] = np.diag(np.square(cfg.measurement_std_size))
    has_vel = np.isfinite(velocity).all(axis=1)
    x[has_vel, VEL] = velocity[has_vel][:, [0, 2]]
    P[has_vel, VEL, VEL] = velocity_cov[has_vel][:, [0, 2]][:, :, [0, 2]]
    P[np.ix_(~has_vel, [3, 4], [3, 4])] = prior_velocity_cov(cfg, R_world_cam)
    return x, P


def predict_states(x: np.ndarray, P: np.ndarray, dt: float, cfg: KalmanConfig) -> tuple[np.ndarray, np.ndarray]:
    """``TubeFilter.predict`` for (C, 8) states and (C, 8, 8) covariances."""
    F, Q = transition(dt), process_noise(dt, cfg)
    x = x @ F.T
    P = F @ P @ F.T + Q
    x[:, SIZE] = np.clip(x[:, SIZE], 0.0, cfg.max_size_m)
    return x, P


def update_states(x: np.ndarray, P: np.ndarray, footpoint: np.ndarray, cov: np.ndarray, size: np.ndarray,
                  velocity: np.ndarray, velocity_cov: np.ndarray, cfg: KalmanConfig) -> tuple[np.ndarray, np.ndarray]:
    """``TubeFilter.update`` for C filters, each with its own measurement (NaN velocity
    rows: footpoint and size only); filterpy's equations on stacked arrays."""
    x, P = x.copy(), P.copy()
    size = np.clip(size, 0.0, cfg.max_size_m)
    has_vel = np.isfinite(velocity).all(axis=1)
    size_var = np.diag(np.square(cfg.measurement_std_size))
    for full, H in ((True, H_FULL), (False, H_POS_SIZE)):
        rows = np.flatnonzero(has_vel == full)
        if rows.size == 0:
            continue
        m = H.shape[0]
        R = np.zeros((rows.size, m, m))
        R[:, 0:3, 0:3] = cov[rows]
        R[:, m - 3:, m - 3:] = size_var
        parts = [footpoint[rows]]
        if full:
            R[:, VEL, VEL] = velocity_cov[rows][:, [0, 2]][:, :, [0, 2]]
            parts.append(velocity[rows][:, [0, 2]])
        z = np.concatenate(parts + [size[rows]], axis=1)
        xr, Pr = x[rows], P[rows]
        y = z - xr @ H.T
        PHT = Pr @ H.T
        K = PHT @ np.linalg.inv(H @ PHT + R)
        x[rows] = xr + (K @ y[:, :, None])[:, :, 0]
        I_KH = np.eye(DIM_X) - K @ H
        P[rows] = I_KH @ Pr @ I_KH.transpose(0, 2, 1) + K @ R @ K.transpose(0, 2, 1)
    return x, P
