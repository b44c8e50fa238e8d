"""Stereo visual odometry: 3-point RANSAC, then least squares on stereo reprojection.

Like libviso2 in the original, hypotheses are scored by reprojecting the previous
frame's triangulated points into BOTH the left and the right image at t, and the winner
is refined over its inliers by Gauss–Newton least squares (with one re-selection of
inliers). Unlike the original, a failure is reported (``ok=False`` with a reason and
``T_cur_prev=None``), never replaced by the identity. ``mining/geometry/poses.py`` chains
the per-frame motions into poses.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from mining.geometry.config import EgomotionConfig
from mining.geometry.flow import QuadMatches, project_stereo, triangulate
from mining.types import Egomotion, StereoCalib


def _failed(matches: int, reason: str, inliers: int = 0) -> Egomotion:
    return Egomotion(T_cur_prev=None, inliers=inliers, matches=matches, rmse_px=float("nan"), ok=False, reason=reason)


def _kabsch_batch(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid transforms (R, t) with B ≈ R·A + t for a batch of (k, m, 3) point sets."""
    ca, cb = A.mean(axis=1, keepdims=True), B.mean(axis=1, keepdims=True)
    H = np.einsum("kmi,kmj->kij", A - ca, B - cb)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("kji,kjl->kil", Vt, np.transpose(U, (0, 2, 1)))))
    D = np.tile(np.eye(3), (len(A), 1, 1))
    D[:, 2, 2] = d
    R = np.einsum("kji,kjl,klm->kim", Vt, D, np.transpose(U, (0, 2, 1)))
    t = cb[:, 0] - np.einsum("kij,kj->ki", R, ca[:, 0])
    return R, t


def stereo_errors(T: np.ndarray, points_prev: np.ndarray, uv_left: np.ndarray, uv_right: np.ndarray, calib: StereoCalib) -> np.ndarray:
    """Per point, the larger of the left and right reprojection errors after applying T (px)."""
    moved = points_prev @ T[:3, :3].T + T[:3, 3]
    err = np.full(len(points_prev), np.inf)
    front = moved[:, 2] > 0.1
    pl, pr = project_stereo(moved[front], calib)
    err[front] = np.maximum(np.linalg.norm(pl - uv_left[front], axis=1), np.linalg.norm(pr - uv_right[front], axis=1))
    return err


def _skew(p: np.ndarray) -> np.ndarray:
    """(N, 3) vectors → (N, 3, 3) cross-product matrices."""
    z = np.zeros(len(p))
    return np.stack([np.stack([z, -p[:, 2], p[:, 1]], 1), np.stack([p[:, 2], z, -p[:, 0]], 1), np.stack([-p[:, 1], p[:, 0], z], 1)], 1)


def _refine(
    T0: np.ndarray, X: np.ndarray, uv_l: np.ndarray, uv_r: np.ndarray, calib: StereoCalib, iterations: int
) -> tuple[np.ndarray, bool]:
    """Gauss–Newton on the stereo reprojection error (left + right), as libviso2 does.

    The pose is updated on the left, T ← exp(ω)·T + τ, so the Jacobian of each moved
    point P is [−[P]×, I] and the projection's Jacobian is the usual pinhole one.
    Returns the refined T and whether the update converged.
    """
    R, t = T0[:3, :3].copy(), T0[:3, 3].copy()
    obs = np.concatenate([uv_l, uv_r], axis=1)
    fx, fy, bf = calib.fx, calib.fy, calib.bf
    for _ in range(iterations):
        P = X @ R.T + t
        x, y, z = P[:, 0], P[:, 1], P[:, 2]
        if np.any(z <= 0.1):
            return T0, False
        u = fx * x / z + calib.cx
        v = fy * y / z + calib.cy
        res = (np.stack([u, v, u - bf / z, v], axis=1) - obs).ravel()
        J_proj = np.zeros((len(P), 4, 3))  # d(u_l, v_l, u_r, v_r) / dP
        J_proj[:, 0, 0] = J_proj[:, 2, 0] = fx / z
        J_proj[:, 0, 2] = -fx * x / z**2
        J_proj[:, 2, 2] = -fx * x / z**2 + bf / z**2
        J_proj[:, 1, 1] = J_proj[:, 3, 1] = fy / z
        J_proj[:, 1, 2] = J_proj[:, 3, 2] = -fy * y / z**2
        J_pose = np.concatenate([-_skew(P), np.tile(np.eye(3), (len(P), 1, 1))], axis=2)  # dP / d(ω, τ)
        J = (J_proj @ J_pose).reshape(-1, 6)
        delta = np.linalg.lstsq(J, -res, rcond=None)[0]
        dR = Rotation.from_rotvec(delta[:3]).as_matrix()
        R, t = dR @ R, dR @ t + delta[3:]
        if np.linalg.norm(delta) < 1e-8:
            break
    else:
        if np.linalg.norm(delta) > 1e-5:
            return T0, False
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T, True


def estimate_egomotion(
    matches: QuadMatches, calib: StereoCalib, cfg: EgomotionConfig, use: np.ndarray | None = None
) -> Egomotion:
    """Egomotion T_cur_prev from quad matches; ``use`` selects the rows to estimate from
    (e.g. a bucketed subset), by default all of them."""
    n = len(matches)
    idx = np.arange(n) if use is None else np.asarray(use)
    if len(idx) < max(cfg.min_inliers, 3):
        return _failed(n, f"too few matches: {len(idx)} < {max(cfg.min_inliers, 3)}")
    X_prev = triangulate(matches.uv_prev_left[idx], matches.uv_prev_right[idx], calib)
    X_cur = triangulate(matches.uv_left[idx], matches.uv_right[idx], calib)
    uv_l = matches.uv_left[idx].astype(np.float64)
    uv_r = matches.uv_right[idx].astype(np.float64)

    # RANSAC over minimal 3-point sets: the 3D–3D rigid fit of a triplet is the hypothesis,
    # its support is counted by stereo reprojection (both images) at t.
    rng = np.random.default_rng(cfg.seed)
    triplets = np.argsort(rng.random((cfg.ransac_iterations, len(idx))), axis=1)[:, :3]
    R, t = _kabsch_batch(X_prev[triplets], X_cur[triplets])
    moved = X_prev @ np.transpose(R, (0, 2, 1)) + t[:, None, :]  # (k, n, 3)
    z = moved[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        ul = calib.fx * moved[..., 0] / z + calib.cx
        vl = calib.fy * moved[..., 1] / z + calib.cy
        ur = ul - calib.bf / z
    el = np.hypot(ul - uv_l[:, 0], vl - uv_l[:, 1])
    er = np.hypot(ur - uv_r[:, 0], vl - uv_r[:, 1])
    support = (z > 0.1) & (el <= cfg.inlier_threshold_px) & (er <= cfg.inlier_threshold_px)
    best = int(np.argmax(support.sum(axis=1)))
    inl = support[best]
    if inl.sum() < cfg.min_inliers:
        return _failed(n, f"RANSAC found too few inliers: {int(inl.sum())} < {cfg.min_inliers}", int(inl.sum()))

    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R[best], t[best]
    # Refine, re-select the inliers under the refined motion, refine once more.
    for _ in range(2):
        T, converged = _refine(T, X_prev[inl], uv_l[inl], uv_r[inl], calib, cfg.refine_iterations)
        if not converged:
            return _failed(n, "Gauss–Newton refinement did not converge", int(inl.sum()))
        inl = stereo_errors(T, X_prev, uv_l, uv_r, calib) <= cfg.inlier_threshold_px
        if inl.sum() < cfg.min_inliers:
            return _failed(n, f"too few inliers after refinement: {int(inl.sum())} < {cfg.min_inliers}", int(inl.sum()))
    moved = X_prev[inl] @ T[:3, :3].T + T[:3, 3]
    pl, pr = project_stereo(moved, calib)
    rmse = float(np.sqrt(np.mean(np.concatenate([(pl - uv_l[inl]) ** 2, (pr - uv_r[inl]) ** 2]).sum(axis=1))))
    if not np.isfinite(rmse) or rmse > cfg.max_rmse_px:
        return _failed(n, f"reprojection RMSE {rmse:.2f} px > {cfg.max_rmse_px} px", int(inl.sum()))
    return Egomotion(T_cur_prev=T, inliers=int(inl.sum()), matches=n, rmse_px=rmse, ok=True)
