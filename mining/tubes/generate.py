"""Tube generation: extend, start (forward-backward enumeration), end, tube NMS.

Frame by frame (REFERENCE.md "Tube generation"):

1. **Extend** every live tube: Kalman prediction over the frame interval from the
   timestamps, mask prediction by 3D warping, gating (footpoint Mahalanobis distance, box
   IoU, 2D size similarity, mask IoU; optionally tolerant of a few pixels of jitter) and
   the association score mask IoU × Gaussian density of the footpoint (or, with
   ``association = "normalised"``, × the density relative to its peak, which means the same
   at every depth: ``gating.py``). Each tube takes its best gated observation; one observation
   may feed several tubes (co-selection resolves them later).
2. **End** tubes that leave the view, whose gap grows too long, or whose predicted mask
   vanishes.
3. **Start** tubes from observations no tube took: run a filter backwards up to five
   frames, requiring an inlier in each of the first three back-steps, then re-initialise
   at the earliest inlier and replay forwards. Duplicates of existing tubes are dropped.
4. **Tube NMS** among tubes older than four frames.

The start model. A probe needs a velocity to predict where the object was. The first
hypothesis is the observation's own motion: its scene flow, or without flow the prior
(zero mean, variance along the camera's lateral and depth axes). That prior cannot reach
an object that moves fast across the image (a car overtaking close by moves ~1.4 m a
frame): the warped box misses its last position, and no tube would ever start where
flow is missing. So a start must not depend on flow: for each observation the first
hypothesis could not start and that has no flow, a small set of velocity hypotheses comes from its
displacement to the observations of the frame before (multiple-hypothesis starts, as in
MHT):

    v_jk = (f_j − f_k) / Δt,   Σ_v = (Σ_j + Σ_k) / Δt²,   |v_jk| ≤ v_max

on the ground plane (f: footpoints, Σ: their triangulation covariances), at most
``start_hypotheses`` per observation, the slowest first. The speed bound v_max is
physical (``start_max_speed_mps``), so the search radius v_max·Δt scales with the frame
interval. Each hypothesis runs the same backward probe under the same gates and needs
the same back-step inliers: constant velocity must hold over four frames, which random
pairings do not. An observation lying mostly inside one a tube took this frame is part of
a tracked object and gets no hypotheses (its tube would only compete with the object's
own in co-selection). Of a candidate's surviving hypotheses the one that reached furthest
back wins; the probe's filtered velocity seeds the forward replay (where the earliest
inlier has no flow of its own), and from then on the tube's filter carries the
object's own motion into every box and mask prediction, so a fast object is gated and
scored against where it is going, not where it was.

Tubes never cross a segment border (a failed egomotion): nothing relates the poses on
either side of it.
"""

from __future__ import annotations

import copy
import dataclasses
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mining.boxes import box_ioa, cut_at_sides, paired_box_iou
from mining.masks import areas, clip_rle, mask_ioa, mask_iou
from mining.tubes.config import TubeConfig
from mining.tubes.gating import GROUND, best_pairs, mahalanobis2, paired_obs_boxes, view_edge_gates
from mining.tubes.kalman import POS, SIZE, TubeFilter, predict_states, prior_velocity_cov
from mining.tubes.probe import displacement_hypotheses, probe_back
from mining.tubes.warp import MaskPoints, predict_box, predict_mask
from mining.tubes.world import WorldObservations
from mining.types import TrackingFrame, Tube, TubeFrame


@dataclass
class Prediction:
    rle: dict | None  # None: a box-only prediction
    box: np.ndarray
    open_sides: np.ndarray | None = None  # sides where the view ended the points (MaskPoints.open_sides)


@dataclass
class LiveTube:
    """A tube while it is extended: the tube so far and the generator's tracking state."""

    tube: Tube
    kf: TubeFilter
    points: MaskPoints  # 3D points of the last observed mask (world), warped to predict the next
    last_observed_t_ns: int
    gap: int = 0  # frames since the last observation
    at_last_observation: tuple[np.ndarray, np.ndarray] | None = None  # the filter's (x, P) just after it
    start: tuple[int, int, bool] | None = None  # (frame, observation, True) it was replayed from with its own motion


def _predicted_frame(x: np.ndarray, frame: TrackingFrame, pred: Prediction) -> TubeFrame:
    """A frame of a tube without an observation: the filter's state and the predicted mask."""
    R, t = frame.pose[:3, :3], frame.pose[:3, 3]
    return TubeFrame(
        frame=frame.index, t_ns=frame.t_ns, observed=False, obs_index=-1, rle=pred.rle, box=pred.box,
        footpoint_world=x[POS].copy(), velocity_world=np.array([x[3], 0.0, x[4]]), size=x[SIZE].copy(),
        position_cam=(x[POS] - t) @ R, objectness=np.nan, mask_iou=np.nan, motion_density=np.nan,
    )


class TubeGenerator:
    """Feed frames in time order with ``step``; ``finish`` returns every tube made.

    ``nms_score(tube)`` ranks tubes for tube NMS (the caller's unary score: the generator
    does not score).
    """

    def __init__(self, cfg: TubeConfig, nms_score: Callable[[Tube], float], first_id: int = 0):
        self.cfg = cfg
        self.nms_score = nms_score
        self.live: list[LiveTube] = []
        self.ended: list[Tube] = []
        self.history: deque[WorldObservations] = deque(maxlen=cfg.backward_steps)
        self.next_id = first_id
        self._nms_ious: dict[tuple[int, int], dict[int, float]] = {}  # tube NMS: (id, id) → frame → mask IoU
        self.dormant: list[LiveTube] = []  # ended by a gap, waiting ``join_max_gap_s`` for a tube that continues them
        self.recent: deque[TrackingFrame] = deque()  # the frames a join may fill a gap over

    # --- per frame -------------------------------------------------------------------

    def step(self, frame: TrackingFrame) -> None:
        world = WorldObservations.of(frame, self.cfg.view_edge_px if self.cfg.view_edges else -1.0)
        if self.history and self.history[-1].frame.segment != frame.segment:
            self._end_all("segment")
            self.history.clear()
            self.recent.clear()
        taken = self._extend(world) if self.history else set()
        self._start(world, taken)
        self._tube_nms()
        self.history.append(world)
        self._forget(frame)

    def finish(self) -> list[Tube]:
        self._end_all("sequence end")
        tubes = sorted(self.ended, key=lambda t: t.tube_id)
        self.ended = []
        return tubes

    # --- extend ---------------------------------------------------------------------

    def _extend(self, world: WorldObservations) -> set[int]:
        """Extend the live tubes; returns the observations they took."""
        prev = self.history[-1].frame
        dt = (world.frame.t_ns - prev.t_ns) / 1e9
        survivors, predictions = [], []
        for tube in self.live:
            tube.kf.predict(dt)
            pred = self._predict(tube, world.frame)
            reason = self._left_view(tube, pred, world.frame)
            if reason:
                tube.tube.end_reason = reason
                self._end(tube)
                continue
            survivors.append(tube)
            predictions.append(pred)
        self.live = survivors
        choice, terms = self._associate(self.live, predictions, world)
        keep = []
        for tube, pred, j, (iou, dens) in zip(self.live, predictions, choice, terms):
            if j >= 0:
                self._observe(tube, world, j, iou, dens)
            else:
                self._miss(tube, world, pred)
                if tube.gap > self._gap_limit(tube):
                    tube.tube.end_reason = "gap"
                    if self.cfg.join_max_gap_s > 0:
                        self.dormant.append(tube)
                    else:
                        self._end(tube)
                    continue
            keep.append(tube)
        self.live = keep
        return set(int(j) for j in choice if j >= 0)

    def _predict(self, tube: LiveTube, frame: TrackingFrame, box_only: bool = False) -> Prediction | None:
        shift = np.array([tube.kf.x[3], 0.0, tube.kf.x[4]]) * (frame.t_ns - tube.last_observed_t_ns) / 1e9
        sides = tube.points.open_sides
        if box_only:
            box = predict_box(tube.points, shift, frame.pose, frame.calib)
            return None if box is None else Prediction(None, box, sides)
        out = predict_mask(tube.points, shift, frame.pose, frame.calib, self.cfg.warp_close_px)
        return None if out is None else Prediction(*out, sides)

    def _left_view(self, tube: LiveTube, pred: Prediction | None, frame: TrackingFrame) -> str:
        if pred is None:
            return "mask left the image"
        if areas([pred.rle])[0] <= self.cfg.min_predicted_mask_px:
            return "predicted mask too small"
        R, t = frame.pose[:3, :3], frame.pose[:3, 3]
        cam = (tube.kf.x[POS] - t) @ R
        if cam[2] < self.cfg.min_depth_m:
            return "behind the camera"
        if cam[2] > self.cfg.max_depth_m:
            return "too far"
        u = frame.calib.fx * cam[0] / cam[2] + frame.calib.cx
        margin = self.cfg.lateral_margin * frame.calib.width
        if u < -margin or u > frame.calib.width + margin:
            return "left the view laterally"
        return ""

    def _gap_limit(self, tube: LiveTube) -> int:
        return min(self.cfg.max_gap_frames, max(1, round(self.cfg.gap_inlier_factor * tube.tube.n_inliers)))

    def _gap_jitter(self, tube: LiveTube, frame: TrackingFrame) -> float:
        """Pixels of jitter a prediction over a gap tolerates: the gate's own plus the
        predicted footpoint's lateral standard deviation seen in the image."""
        R, t = frame.pose[:3, :3], frame.pose[:3, 3]
        cam = (tube.kf.x[POS] - t) @ R
        cov = R.T @ tube.kf.P[POS, POS] @ R
        sigma_px = frame.calib.fx * np.sqrt(max(cov[0, 0], 0.0)) / max(cam[2], self.cfg.min_depth_m)
        return self.cfg.gate_jitter_px + self.cfg.join_gate_sigmas * sigma_px

    def _associate(self, tubes: list[LiveTube], preds: list[Prediction], world: WorldObservations,
                   jitter_px: float | None = None):
        """Best gated observation per tube (−1: none) and its (mask IoU, density)."""
        T, N = len(tubes), len(world)
        choice = np.full(T, -1, np.int64)
        terms = [(np.nan, np.nan)] * T
        if T == 0 or N == 0:
            return choice, terms
        obs = world.frame.observations
        pboxes = np.array([p.box for p in preds], np.float64)
        cfg = self.cfg if jitter_px is None else dataclasses.replace(self.cfg, gate_jitter_px=jitter_px)
        gate, cut = view_edge_gates(pboxes, world.boxes, [p.open_sides for p in preds], cfg)
        gate &= world.usable[None, :]
        r, c = np.nonzero(gate)
        if r.size == 0:
            return choice, terms
        rows, cols = np.unique(r), np.unique(c)
        if all(preds[i].rle is not None for i in rows):
            ious = mask_iou([preds[i].rle for i in rows], [obs.proposals.rles[j] for j in cols])
            iou = ious[np.searchsorted(rows, r), np.searchsorted(cols, c)]
            frame_box = np.array([0.0, 0.0, world.frame.calib.width, world.frame.calib.height]) if cut else None
            for i in cut:  # the observations' masks up to the view edge, for the pairs gated with row i
                pairs = np.flatnonzero(r == i)
                if pairs.size:
                    view = cut_at_sides(frame_box, pboxes[i], preds[i].open_sides)[0]
                    iou[pairs] = mask_iou([preds[i].rle], [clip_rle(obs.proposals.rles[j], view) for j in c[pairs]])[0]
        else:  # a box-only prediction (the backward probe) is compared by box IoU
            iou = paired_box_iou(pboxes[r], paired_obs_boxes(world.boxes, r, c, cut))
        mean = np.array([t.kf.x[POS] for t in tubes])
        pos_cov = np.array([t.kf.P[POS, POS] for t in tubes])
        took, j, iou, dens = best_pairs(r, c, iou, mean[r], pos_cov[r], world.footpoint[c], world.covariance[c],
                                        cfg, pred_box=pboxes[r])
        choice[took] = j
        for i, a, d in zip(took, iou, dens):
            terms[i] = (float(a), float(d))
        return choice, terms

    def _observe(self, tube: LiveTube, world: WorldObservations, j: int, iou: float, dens: float) -> None:
        frame, obs = world.frame, world.frame.observations
        tube.kf.update(world.footpoint[j], world.covariance[j], obs.size[j], *world.velocity_or_none(j))
        pts = world.points(j)
        if pts is not None:
            tube.points = pts
            tube.last_observed_t_ns = frame.t_ns
        tube.gap = 0
        tube.tube.frames.append(self._tube_frame(tube, frame, j, iou, dens))
        tube.at_last_observation = (tube.kf.x.copy(), tube.kf.P.copy())

    def _miss(self, tube: LiveTube, world: WorldObservations, pred: Prediction) -> None:
        tube.gap += 1
        tube.tube.frames.append(_predicted_frame(tube.kf.x, world.frame, pred))

    def _tube_frame(self, tube: LiveTube, frame: TrackingFrame, j: int, iou: float, dens: float) -> TubeFrame:
        obs = frame.observations
        x = tube.kf.x
        p = obs.proposals
        post = None if p.posterior is None else p.posterior[j]
        weight = 1.0 if p.class_weight is None else float(p.class_weight[j])
        return TubeFrame(
            frame=frame.index, t_ns=frame.t_ns, observed=True, obs_index=int(j), rle=obs.proposals.rles[j],
            box=np.asarray(obs.proposals.boxes[j], np.float64), footpoint_world=x[POS].copy(),
            velocity_world=np.array([x[3], 0.0, x[4]]), size=x[SIZE].copy(), position_cam=obs.position[j].copy(),
            objectness=float(obs.proposals.objectness[j]), mask_iou=iou, motion_density=dens, posterior=post,
            class_weight=weight,
        )

    # --- start ----------------------------------------------------------------------

    def _new_tube(self, world: WorldObservations, j: int,
                  motion: tuple[np.ndarray, np.ndarray] | None = None) -> LiveTube | None:
        """A tube started at observation j. Its velocity: the observation's scene flow where
        it has one, else ``motion`` (a probe's ground velocity (2,) and covariance (2, 2)),
        else the prior."""
        frame, obs = world.frame, world.frame.observations
        pts = world.points(j)
        if pts is None:
            return None
        vel, vel_cov = world.velocity_or_none(j)
        if vel is None and motion is not None:
            vel, vel_cov = np.zeros(3), np.zeros((3, 3))
            vel[GROUND] = motion[0]
            vel_cov[np.ix_(GROUND, GROUND)] = motion[1]
        kf = TubeFilter(world.footpoint[j], world.covariance[j], obs.size[j], vel, vel_cov,
                        self.cfg.kalman, frame.pose[:3, :3])
        tube = LiveTube(Tube(tube_id=-1, segment=frame.segment), kf, pts, frame.t_ns)
        tube.tube.frames.append(self._tube_frame(tube, frame, j, np.nan, np.nan))
        tube.at_last_observation = (kf.x.copy(), kf.P.copy())
        return tube

    def _start(self, world: WorldObservations, taken: set[int]) -> None:
        if len(self.history) < self.cfg.backward_required:
            return
        cands = np.array([j for j in np.flatnonzero(world.usable) if int(j) not in taken], np.int64)
        everyone = cands  # the displacement hypotheses consider every candidate the probe below misses
        # Own-motion starts that would fail their first backward step's footpoint gate end here.
        cands = cands[self._may_step_back(world, cands, self.history[-1])]
        past = list(self.history)[::-1]  # newest first
        if self.cfg.probe_with_boxes:
            starts = probe_back(world, cands, past, self.cfg)
        else:
            starts = [self._probe_one(world, int(j), past, box_only=False) for j in cands]
        # (earliest inlier, its observation, the motion to replay from; None: the observation's own)
        found = [(w, j, None) for w, j in (s for s in starts if s is not None)]
        found += self._start_from_displacements(world, everyone, cands[[s is not None for s in starts]], past, taken)
        new: list[LiveTube] = []
        # Candidates whose probes end at the same inlier replay to the same tube: replay once.
        replayed = self._known_replays()
        todo: dict[tuple[int, int, bool], tuple[WorldObservations, int, tuple | None]] = {}
        for w0, j0, motion in found:
            todo.setdefault((w0.frame.index, j0, motion is None), (w0, j0, motion))
        todo = {k: v for k, v in todo.items() if k not in replayed}
        replayed.update(zip(todo, self._replay(world, list(todo.values()))))
        done: set[tuple[int, int, bool]] = set()
        for w0, j0, motion in found:
            key = (w0.frame.index, j0, motion is None)
            seen = key in done or key not in todo
            done.add(key)
            tube = replayed[key]
            if tube is None or self._duplicate(tube.tube, [t.tube for t in self.live + new]):
                continue
            tube = copy.deepcopy(tube) if seen else tube
            tube.start = key if motion is None else None
            if not self._join(tube, w0):
                tube.tube.tube_id = self.next_id
                self.next_id += 1
            new.append(tube)
        self.live.extend(new)

    def _known_replays(self) -> dict[tuple[int, int, bool], LiveTube | None]:
        """Replays already made: a replay from an observation's own motion is deterministic,
        so one from where a live tube started is that tube again, a duplicate (None: not
        replayed at all; most starts under a permissive gate are such duplicates)."""
        return {t.start: None for t in self.live if t.start is not None}

    def _probe_one(self, world: WorldObservations, j: int, past: list[WorldObservations],
                   box_only: bool) -> tuple[WorldObservations, int] | None:
        """The backward probe of one candidate: its earliest inlier, or None. Used with full
        mask prediction (``probe_with_boxes`` off); ``probe_back`` does the box-only probe
        of all candidates at once, and must agree with this one."""
        probe = self._new_tube(world, j)
        if probe is None:
            return None
        earliest = (world, j)
        t_cur = world.frame.t_ns
        for k, w in enumerate(past):
            probe.kf.predict((w.frame.t_ns - t_cur) / 1e9)
            t_cur = w.frame.t_ns
            pred = self._predict(probe, w.frame, box_only=box_only)
            choice, terms = ([-1], None) if pred is None else self._associate([probe], [pred], w)
            if choice[0] < 0:
                if k < self.cfg.backward_required:
                    return None
                continue
            self._observe(probe, w, int(choice[0]), *terms[0])
            earliest = (w, int(choice[0]))
        return earliest

    def _start_from_displacements(self, world: WorldObservations, cands: np.ndarray, started: np.ndarray,
                                  past: list[WorldObservations], taken: set[int]) -> list[tuple[WorldObservations, int, tuple]]:
        """Starts of candidates the observation's own motion could not start: the backward
        probe from each velocity hypothesis (``displacement_hypotheses``), the same required
        back-step inliers. Per candidate, the hypothesis whose probe reached furthest back
        (then the slowest); its filtered ground velocity seeds the forward replay.

        No hypotheses for a candidate with scene flow of its own (its probe started from a
        measured velocity: flow sharpens a start, the hypotheses stand in where it is
        missing), nor for one whose mask lies mostly inside a mask a tube took this frame:
        a part of a tracked object (a proposal of its lower half, say), whose tube would
        only compete with the object's own in co-selection."""
        left = np.setdiff1d(cands, started)
        left = left[~np.isfinite(world.velocity[left]).all(axis=1)]
        left = left[~self._part_of_taken(world, left, taken)]
        rows, vel, vel_cov = displacement_hypotheses(world, left, past[0], self.cfg)
        if rows.size == 0:
            return []
        starts, v, v_cov = probe_back(world, left[rows], past, self.cfg, vel, vel_cov, states=True)
        best: dict[int, tuple[int, int]] = {}  # candidate → (depth of its earliest inlier, hypothesis)
        for h, (r, s) in enumerate(zip(rows, starts)):
            if s is None:
                continue
            depth = -1 if s[0] is world else next(k for k, w in enumerate(past) if w is s[0])
            if int(r) not in best or depth > best[int(r)][0]:  # hypotheses come slowest first: ties keep it
                best[int(r)] = (depth, h)
        return [(starts[h][0], starts[h][1], (v[h], v_cov[h])) for _, h in (best[r] for r in sorted(best))]

    def _part_of_taken(self, world: WorldObservations, cands: np.ndarray, taken: set[int]) -> np.ndarray:
        """Which candidates' masks lie at least ``start_part_ioa`` inside a taken observation's mask."""
        out = np.zeros(cands.size, bool)
        took = np.array(sorted(taken), np.int64)
        if cands.size == 0 or took.size == 0:
            return out
        near = box_ioa(world.boxes[cands], world.boxes[took]) >= self.cfg.start_part_ioa  # masks inside need boxes inside
        rows = np.flatnonzero(near.any(axis=1))
        if rows.size:
            rles = world.frame.observations.proposals.rles
            ioa = mask_ioa([rles[j] for j in cands[rows]], [rles[j] for j in took])
            out[rows] = ((ioa >= self.cfg.start_part_ioa) & near[rows]).any(axis=1)
        return out

    def _replay(self, world: WorldObservations,
                starts: list[tuple[WorldObservations, int, tuple[np.ndarray, np.ndarray] | None]]) -> list[LiveTube | None]:
        """Re-initialise a tube at each earliest inlier (w0, j0[, motion]) and replay it
        forwards up to now; None where its mask left the image or it ends unobserved.

        The replays are independent (each tube takes its own best gated observation), so
        they step through the frames together: one association pass per frame for all
        the tubes replaying through it, the same result as one replay at a time.
        """
        tubes = [self._new_tube(w0, j0, motion) for w0, j0, motion in starts]
        t_prev = [w0.frame.t_ns for w0, _, _ in starts]
        for w in [*self.history, world]:
            active = [i for i, (w0, _, _) in enumerate(starts)
                      if tubes[i] is not None and w.frame.index > w0.frame.index]
            preds = []
            for i in list(active):
                tube = tubes[i]
                tube.kf.predict((w.frame.t_ns - t_prev[i]) / 1e9)
                t_prev[i] = w.frame.t_ns
                pred = self._predict(tube, w.frame)
                if pred is None:
                    tubes[i] = None
                    active.remove(i)
                else:
                    preds.append(pred)
            choice, terms = self._associate([tubes[i] for i in active], preds, w)
            for i, pred, j, term in zip(active, preds, choice, terms):
                if j >= 0:
                    self._observe(tubes[i], w, int(j), *term)
                else:
                    self._miss(tubes[i], w, pred)
        return [t if t is not None and t.tube.frames[-1].observed else None for t in tubes]

    def _may_step_back(self, world: WorldObservations, cands: np.ndarray, prev: WorldObservations) -> np.ndarray:
        """Cheap pre-check for many starts at once: which observations ``cands`` have
        any observation at t−1 within the footpoint gate of their first backward prediction?

        A fresh filter's predicted footpoint and covariance have a closed form, so the gate
        runs on arrays and most hopeless starts end before any mask is warped. It leaves
        out the velocity covariance's off-diagonal term, so it is a pre-filter: the full
        gate still runs on the starts it keeps.
        """
        usable = np.flatnonzero(prev.usable)
        if usable.size == 0 or cands.size == 0:
            return np.zeros(cands.size, bool)
        kc = self.cfg.kalman
        dt = (prev.frame.t_ns - world.frame.t_ns) / 1e9
        vel = world.velocity[cands][:, GROUND]
        has_vel = np.isfinite(vel).all(axis=1)
        mean = world.footpoint[cands][:, GROUND] + np.where(has_vel[:, None], vel, 0.0) * dt
        vcov = world.velocity_covariance[cands]
        var_v = np.where(has_vel[:, None], np.stack([vcov[:, 0, 0], vcov[:, 2, 2]], axis=1), 0.0)
        q = np.square(np.asarray(kc.process_std_position)[GROUND]) * abs(dt) / kc.process_dt_s
        P = world.covariance[cands][:, GROUND][:, :, GROUND].copy()
        P[:, 0, 0] += var_v[:, 0] * dt * dt + q[0]
        P[:, 1, 1] += var_v[:, 1] * dt * dt + q[1]
        P[~has_vel] += prior_velocity_cov(kc, world.frame.pose[:3, :3]) * dt * dt  # the prior turns with the camera
        S = P[:, None] + prev.covariance[usable][:, GROUND][:, :, GROUND][None]  # (U, M, 2, 2)
        d = prev.footpoint[usable][:, GROUND][None] - mean[:, None]  # (U, M, 2)
        det = S[..., 0, 0] * S[..., 1, 1] - S[..., 0, 1] * S[..., 1, 0]
        m2 = (S[..., 1, 1] * d[..., 0] ** 2 - (S[..., 0, 1] + S[..., 1, 0]) * d[..., 0] * d[..., 1]
              + S[..., 0, 0] * d[..., 1] ** 2) / det
        return (m2 < self.cfg.gate_mahalanobis**2).any(axis=1)

    def _duplicate(self, tube: Tube, others: list[Tube]) -> bool:
        key = set(f.frame for f in tube.frames if f.observed)
        mine = tube.frame_map()
        last = tube.frames[-1]
        # Same inlier frames means an observed end in the same frame, whose boxes must then
        # overlap enough too: cheap first tests, the second on all tubes at once.
        ends = [o for o in others if o.frames[-1].frame == last.frame and o.frames[-1].observed]
        if not ends:
            return False
        close = paired_box_iou(np.array([o.frames[-1].box for o in ends], np.float64), last.box)
        for other in (o for o, ok in zip(ends, close >= self.cfg.duplicate_box_iou) if ok):
            frames = other.frame_map()
            theirs = set(f for f, tf in frames.items() if tf.observed and f >= tube.first_frame)
            if theirs != key:
                continue
            common = sorted(key)
            ious = paired_box_iou(np.array([mine[f].box for f in common], np.float64),
                                  np.array([frames[f].box for f in common], np.float64))
            if (ious >= self.cfg.duplicate_box_iou).all():
                return True
        return False

    # --- joining fragments ----------------------------------------------------------

    def _join(self, tube: LiveTube, w0: WorldObservations) -> bool:
        """Continue a dormant tube (ended by a gap) with a new one, ``tube``, starting at
        ``w0``: True if joined (``tube`` then carries the dormant tube's id and frames).

        A fragment of a far or small object ends when its proposals drop out for a few
        frames; a new tube starts once the object is proposed again. The dormant tube's
        filter, rewound to its last observation, predicts across the gap (the predicted
        frames fill it, as ``_miss`` would have) to ``w0``, and the extension's own gates
        and association rule must pick the new tube's first observation as the dormant
        tube's best one there: the same test as any frame's association, over a longer
        prediction whose covariance has grown with it. The new tube was confirmed by its
        own back-step inliers, so a join never rests on one observation. Of several
        dormant tubes the one whose warped mask agrees best (mask IoU) wins.
        """
        first = tube.tube.frames[0]
        best, best_iou = None, -np.inf
        for k in self._may_join(tube.tube, w0):
            dormant = self.dormant[k]
            last = dormant.tube.last_inlier
            probe = LiveTube(dormant.tube, dormant.kf.copy(), dormant.points, dormant.last_observed_t_ns)
            probe.kf.kf.x, probe.kf.kf.P = (a.copy() for a in dormant.at_last_observation)
            states, t_prev = [], last.t_ns  # the gap's frames and filter means: masks only for the chosen join
            for frame in (f for f in self.recent if last.frame < f.index < first.frame):
                probe.kf.predict((frame.t_ns - t_prev) / 1e9)
                t_prev = frame.t_ns
                states.append((frame, probe.kf.x.copy()))
            probe.kf.predict((first.t_ns - t_prev) / 1e9)
            pred = self._predict(probe, w0.frame)
            if pred is None:
                continue
            choice, terms = self._associate([probe], [pred], w0, self._gap_jitter(probe, w0.frame))
            if choice[0] == first.obs_index and terms[0][0] > best_iou:
                best, best_iou = (k, probe, states, terms[0]), terms[0][0]
        if best is None:
            return False
        k, probe, states, (iou, dens) = best
        gap = []
        for frame, x in states:
            probe.kf.kf.x = x
            pred = self._predict(probe, frame)
            if pred is None:
                return False  # the prediction left the image during the gap: nothing to fill it with
            gap.append(_predicted_frame(x, frame, pred))
        dormant = self.dormant.pop(k)
        dormant.tube.trim()  # its predicted frames after the last observation: the gap replaces them
        joined = dataclasses.replace(first, mask_iou=iou, motion_density=dens)  # scored as an association
        tube.tube.frames = dormant.tube.frames + gap + [joined] + tube.tube.frames[1:]
        tube.tube.tube_id = dormant.tube.tube_id
        return True

    def _may_join(self, tube: Tube, w0: WorldObservations) -> list[int]:
        """Dormant tubes ``tube`` may continue: in its segment, last observed before its
        first frame and at most ``join_max_gap_s`` before, and its first footpoint within
        twice the Mahalanobis gate of their filters predicted in one step (a cheap
        pre-check on arrays: ``_join`` then predicts frame by frame and gates in full)."""
        first = tube.frames[0]
        idx, xs, Ps = [], [], []
        for k, dormant in enumerate(self.dormant):
            last = dormant.tube.last_inlier
            dt = (first.t_ns - last.t_ns) / 1e9
            if dormant.tube.segment == tube.segment and last.frame < first.frame and dt <= self.cfg.join_max_gap_s:
                x, P = predict_states(*(a[None] for a in dormant.at_last_observation), dt, self.cfg.kalman)
                idx.append(k)
                xs.append(x[0])
                Ps.append(P[0])
        if not idx:
            return []
        x, P = np.array(xs), np.array(Ps)
        j = first.obs_index
        m2 = mahalanobis2(np.repeat(w0.footpoint[[j]], len(idx), axis=0), x[:, POS],
                          P[:, POS][:, :, POS] + w0.covariance[j][None])
        return [k for k, d2 in zip(idx, m2) if d2 < 4 * self.cfg.gate_mahalanobis**2]

    def _forget(self, frame: TrackingFrame) -> None:
        """End dormant tubes no longer joinable; keep the frames a join may still fill."""
        horizon = frame.t_ns - self.cfg.join_max_gap_s * 1e9
        keep = []
        for dormant in self.dormant:
            if dormant.tube.last_inlier.t_ns < horizon:
                self._end(dormant)
            else:
                keep.append(dormant)
        self.dormant = keep
        if self.cfg.join_max_gap_s > 0:
            self.recent.append(frame)
        while self.recent and self.recent[0].t_ns < horizon:
            self.recent.popleft()

    # --- end and NMS -----------------------------------------------------------------

    def _pair_ious(self, a: Tube, b: Tube, ma: dict[int, TubeFrame], mb: dict[int, TubeFrame],
                   common: list[int]) -> list[float]:
        """Mask IoU of two live tubes in each common frame. A live tube's frames never change
        once appended, so each frame's IoU is computed once (NMS runs every frame)."""
        key = (min(a.tube_id, b.tube_id), max(a.tube_id, b.tube_id))
        known = self._nms_ious.setdefault(key, {})
        new = [f for f in common if f not in known]
        if new:
            ious = mask_iou([ma[f].rle for f in new], [mb[f].rle for f in new]).diagonal()
            known.update(zip(new, ious.tolist()))
        return [known[f] for f in common]

    def _end(self, live: LiveTube) -> None:
        """The tube ends at its last observation; its tracking state goes."""
        live.tube.trim()
        if live.tube.frames:
            self.ended.append(live.tube)

    def _end_all(self, reason: str) -> None:
        for live in self.dormant + self.live:
            live.tube.end_reason = live.tube.end_reason or reason
            self._end(live)
        self.live, self.dormant = [], []

    def _tube_nms(self) -> None:
        """Suppress the weaker of two old tubes that cover the same masks (REFERENCE.md)."""
        old = [t.tube for t in self.live if len(t.tube.frames) > self.cfg.nms_min_age]
        if len(old) < 2:
            return
        # Pairs that could suppress, on arrays first: lengths in ratio, and enough frames in
        # common (their spans' overlap bounds them) to reach the overlap with IoU ≤ 1 a frame.
        first = np.array([t.first_frame for t in old])
        last = np.array([t.last_frame for t in old])
        inl = np.array([t.n_inliers for t in old], np.float64)
        longer = np.maximum(inl[:, None], inl[None, :])
        span = np.minimum(last[:, None], last[None, :]) - np.maximum(first[:, None], first[None, :]) + 1
        may = ((np.minimum(inl[:, None], inl[None, :]) / longer >= self.cfg.nms_length_ratio)
               & (np.clip(span, 0, None) / longer > self.cfg.nms_overlap))
        np.fill_diagonal(may, False)
        suppressed: set[int] = set()
        if may.any():
            index = {t.tube_id: k for k, t in enumerate(old)}
            scores = {t.tube_id: self.nms_score(t) for t in old}
            maps = {t.tube_id: t.frame_map() for t in old}
            n_common, touch = _common_frames(old, maps, may)
            old.sort(key=lambda t: -scores[t.tube_id])
            for a_i, a in enumerate(old):
                if a.tube_id in suppressed or not may[index[a.tube_id]].any():
                    continue
                for b in old[a_i + 1:]:
                    ia, ib = index[a.tube_id], index[b.tube_id]
                    if b.tube_id in suppressed or not may[ia, ib]:
                        continue
                    longer = max(inl[ia], inl[ib])
                    if n_common[ia, ib] / longer <= self.cfg.nms_overlap or not touch[ia, ib]:
                        continue
                    ma, mb = maps[a.tube_id], maps[b.tube_id]
                    common = sorted(set(ma) & set(mb))
                    if sum(self._pair_ious(a, b, ma, mb, common)) / longer > self.cfg.nms_overlap:
                        suppressed.add(b.tube_id)
        live = {t.tube.tube_id for t in self.live} - suppressed
        self._nms_ious = {k: v for k, v in self._nms_ious.items() if k[0] in live and k[1] in live}
        if suppressed:
            for t in self.live:
                if t.tube.tube_id in suppressed:
                    t.tube.end_reason = "suppressed"
            # Suppressed tubes are dropped, not kept as ended candidates.
            self.live = [t for t in self.live if t.tube.tube_id not in suppressed]


def _common_frames(tubes: list[Tube], maps: dict[int, dict[int, TubeFrame]],
                   may: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For the pairs of ``tubes`` that ``may`` marks: how many frames both tubes have, and whether
    their boxes overlap (box IoU > 0) in any of them, on arrays for all pairs at once (tube NMS
    checks hundreds of pairs a frame at 500 proposals; one pair at a time was most of its cost)."""
    n = len(tubes)
    n_common, touch = np.zeros((n, n), np.int64), np.zeros((n, n), bool)
    a, b = np.nonzero(np.triu(may | may.T, 1))
    if a.size == 0:
        return n_common, touch
    # Every frame any of the tubes has, as a column: each tube's boxes on one dense row (NaN: absent).
    cols = {f: k for k, f in enumerate(sorted(set().union(*(maps[t.tube_id] for t in tubes))))}
    boxes = np.full((n, len(cols), 4), np.nan)
    present = np.zeros((n, len(cols)), bool)
    for i, t in enumerate(tubes):
        m = maps[t.tube_id]
        c = [cols[f] for f in m]
        boxes[i, c] = [tf.box for tf in m.values()]
        present[i, c] = True
    both = present[a] & present[b]
    counts = both.sum(axis=1)
    overlap = (paired_box_iou(boxes[a], boxes[b]) > 0) & both
    n_common[a, b] = n_common[b, a] = counts
    touch[a, b] = touch[b, a] = overlap.any(axis=1)
    return n_common, touch

