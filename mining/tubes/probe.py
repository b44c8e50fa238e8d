"""The backward probe of tube starts, for all of a frame's start candidates at once.

REFERENCE.md "Start": a filter runs backwards from an unexplained observation up to five
frames and needs an inlier in each of the first three back-steps; the earliest inlier is
where the tube is re-initialised and replayed forwards. The probe only proposes that
start, so it compares warped boxes (``TubeConfig.probe_with_boxes``). Here the filters of
all candidates are rows of one array: one Kalman step, one warp of all their points and
one gating pass over candidates × observations per back-step, under the forward
association's gates and score (``gating.best_pairs``: ``TubeConfig.association``,
``gate_jitter_px``).
"""

from __future__ import annotations

import numpy as np

from mining.boxes import paired_box_iou, size_similarity
from mining.tubes.config import TubeConfig
from mining.tubes.gating import GROUND, best_pairs, paired_obs_boxes, view_edge_gates
from mining.tubes.kalman import POS, VEL, initial_states, predict_states, update_states
from mining.tubes.warp import predict_boxes
from mining.tubes.world import WorldObservations


def probe_back(world: WorldObservations, cands: np.ndarray, past: list[WorldObservations],
               cfg: TubeConfig, velocity: np.ndarray | None = None, velocity_cov: np.ndarray | None = None,
               states: bool = False):
    """Earliest inlier (frame, observation) of each start candidate ``cands`` (observations
    of ``world``), probing ``past`` newest first; None where a required back-step has none
    or the candidate's mask has too few points to warp.

    ``velocity`` (C, 3) and ``velocity_cov`` (C, 3, 3), world frame, start the filters from
    a velocity hypothesis instead of the observations' own (flow, or the prior). With
    ``states`` the filters' final ground velocity (C, 2) and its covariance (C, 2, 2) come
    back too: the motion the probe found, for the forward replay to start from.
    """
    n = len(cands)
    pts = [world.points(int(j)) for j in cands]
    alive = np.array([p is not None for p in pts], bool)
    size = world.frame.observations.size
    if velocity is None:
        velocity, velocity_cov = world.velocity[cands], world.velocity_covariance[cands]
    x, P = initial_states(world.footpoint[cands], world.covariance[cands], size[cands], velocity,
                          velocity_cov, cfg.kalman, world.frame.pose[:3, :3])
    last_t = np.full(n, world.frame.t_ns, np.int64)  # when each probe's points were observed
    earliest_k = np.full(n, -1)  # back-step of the earliest inlier (−1: the candidate itself)
    earliest_j = np.asarray(cands, np.int64).copy()
    t_cur = world.frame.t_ns
    for k, w in enumerate(past):
        x, P = predict_states(x, P, (w.frame.t_ns - t_cur) / 1e9, cfg.kalman)
        t_cur = w.frame.t_ns
        idx = np.flatnonzero(alive)
        if idx.size == 0:
            break
        # Points move by the filtered velocity × the time since they were observed.
        vel = np.stack([x[idx, 3], np.zeros(idx.size), x[idx, 4]], axis=1)
        shifts = vel * (w.frame.t_ns - last_t[idx])[:, None] / 1e9
        boxes = predict_boxes([pts[c] for c in idx], shifts, w.frame.pose, w.frame.calib)
        has_box = np.isfinite(boxes[:, 0])
        idx, boxes = idx[has_box], boxes[has_box]
        gate, cut = view_edge_gates(boxes, w.boxes, [pts[c].open_sides for c in idx], cfg)
        gate &= w.usable[None, :]
        r, c = np.nonzero(gate)
        cr = idx[r]
        rows, obs, _, _ = best_pairs(r, c, paired_box_iou(boxes[r], paired_obs_boxes(w.boxes, r, c, cut)), x[cr][:, POS],
                                     P[cr][:, POS, POS], w.footpoint[c], w.covariance[c], cfg, pred_box=boxes[r])
        m = idx[rows]
        if k < cfg.backward_required:
            alive[:] = False
            alive[m] = True
        if m.size == 0:
            continue
        x[m], P[m] = update_states(x[m], P[m], w.footpoint[obs], w.covariance[obs], w.frame.observations.size[obs],
                                   w.velocity[obs], w.velocity_covariance[obs], cfg.kalman)
        for c_i, j in zip(m, obs):
            p = w.points(int(j))
            if p is not None:  # a mask too small to warp keeps the older points
                pts[c_i], last_t[c_i] = p, w.frame.t_ns
        earliest_k[m], earliest_j[m] = k, obs
    starts = [None if not alive[i] else ((world if earliest_k[i] < 0 else past[earliest_k[i]]), int(earliest_j[i]))
              for i in range(n)]
    if states:
        return starts, x[:, VEL].copy(), P[:, VEL, VEL].copy()
    return starts


def displacement_hypotheses(world: WorldObservations, cands: np.ndarray, prev: WorldObservations,
                            cfg: TubeConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Velocity hypotheses of start candidates from their displacement to the frame before.

    For candidate j and each usable observation k of ``prev`` within reach,
    v = (f_j − f_k) / Δt on the ground plane, with covariance (Σ_j + Σ_k) / Δt² (the two
    footpoints' triangulation covariances; their correlation with the position is left
    out). Within reach: |v| ≤ ``start_max_speed_mps`` — a bound on speed, so the search
    radius grows with the frame interval; and box sizes that agree once scaled by the depth
    ratio (a pre-check of the probe's own size gate). At most ``start_hypotheses`` per
    candidate, the slowest first (objects are more often slow than fast). Returns (rows into ``cands``,
    velocity (H, 3), velocity covariance (H, 3, 3)), world frame, y = 0.
    """
    dt = (world.frame.t_ns - prev.frame.t_ns) / 1e9
    usable = np.flatnonzero(prev.usable)
    empty = (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3)))
    if dt <= 0 or usable.size == 0 or cands.size == 0 or cfg.start_hypotheses <= 0:
        return empty
    d = world.footpoint[cands][:, None, GROUND] - prev.footpoint[usable][None, :, GROUND]  # (C, U, 2)
    speed = np.linalg.norm(d, axis=2) / dt
    reach = speed <= cfg.start_max_speed_mps
    # The same object seen at depth z_k looks z_j / z_k times as large: a pair whose boxes'
    # sizes disagree beyond that fails the probe's first size gate, so it is not probed (the
    # gate here is looser, squared, since a box cut at the image border does not scale).
    # Boxes scaled by their own depth compare as the depth-ratio-scaled boxes do.
    # Sizes grow by the gates' jitter tolerance as the probe's size gate does (δ px at depth z is δ·z px·m).
    reach &= size_similarity(_at_unit_depth(world, cands, cfg.gate_jitter_px),
                             _at_unit_depth(prev, usable, cfg.gate_jitter_px)) > cfg.gate_size_similarity**2
    order = np.argsort(np.where(reach, speed, np.inf), axis=1, kind="stable")[:, :cfg.start_hypotheses]
    rows = np.repeat(np.arange(cands.size), order.shape[1])
    cols = order.ravel()
    keep = reach[rows, cols]
    rows, cols = rows[keep], cols[keep]
    if rows.size == 0:
        return empty
    vel = np.zeros((rows.size, 3))
    vel[:, GROUND] = d[rows, cols] / dt
    cov = np.zeros((rows.size, 3, 3))
    both = world.covariance[cands[rows]] + prev.covariance[usable[cols]]
    cov[:, 0, 0], cov[:, 0, 2] = both[:, 0, 0], both[:, 0, 2]
    cov[:, 2, 0], cov[:, 2, 2] = both[:, 2, 0], both[:, 2, 2]
    return rows, vel, cov / (dt * dt)


def _at_unit_depth(w: WorldObservations, idx: np.ndarray, pad_px: float = 0.0) -> np.ndarray:
    """Boxes of observations ``idx``, ``pad_px`` wider and taller, scaled by their camera
    depth (their size at 1 m, in px·m)."""
    b, z = w.boxes[idx], w.frame.observations.position[idx, 2]
    bw, bh = b[:, 2] - b[:, 0] + pad_px, b[:, 3] - b[:, 1] + pad_px
    return np.stack([np.zeros_like(z), np.zeros_like(z), bw * z, bh * z], axis=1)
