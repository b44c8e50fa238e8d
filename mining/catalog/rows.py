"""Mined tubes and observed frames → Arrow tables of catalogue schema v3, and back.

Encoders: ``tube_row`` and ``frame_rows`` fill a window's parts (window-local worlds,
with the part-only columns) and the stitched catalogue (one world per pose segment of
the sequence); ``frames_row`` is a frame's row of a window's ``frames`` part. Decoder:
``part_tube_frame`` reads a part's tube-frame row back (the stitcher's input).

Masks: ``mask_rle`` and ``decode_mask`` are the one reader of a ``tube_frames`` row's mask
for export, render and the viewer. pycocotools trusts an RLE's runs, so they are checked
first (non-negative, covering exactly H × W pixels) and, given the frame the mask is drawn
on, its size against the frame's; a mask over ``MAX_MASK_PIXELS`` is malformed whatever the
frame. A bad row is a ``BadMask`` naming the tube, the frame and the table, never a crash
inside the decoder, a mask of garbage or gigabytes allocated.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence, Sized
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import pyarrow as pa
from pycocotools import mask as mask_utils

from mining.catalog.schema import SCHEMA_VERSION, THETA_COLUMNS, hive_file_schema, part_schema
from mining.errors import InputError
from mining.masks import rle_problem
from mining.types import MinedTube, TubeFrame

MASK_TABLE = "tube_frames"  # the table whose rows carry the masks
MAX_MASK_PIXELS = 7680 * 4320  # ours: an 8K UHD frame (KITTI's is 0.47 MP); a larger mask is never decoded


@dataclass(frozen=True)
class RunInfo:
    """What every tube row records about the run that made it."""

    dataset: str
    sequence: str
    run_id: str
    params_hash: str
    bf: float | None = None  # stereo baseline × focal (m·px): the depth-noise floor of motion σ


def _vec(v: np.ndarray) -> list[float]:
    return [float(x) for x in np.asarray(v, np.float64).ravel()]


def _opt(x: float) -> float | None:
    return None if x is None or not np.isfinite(x) else float(x)


def compressed_counts(rle: dict) -> str:
    """The COCO compressed counts string of an RLE (plain run lists are compressed)."""
    counts = rle["counts"]
    if isinstance(counts, list):
        h, w = rle["size"]
        counts = mask_utils.frPyObjects({"size": [h, w], "counts": counts}, h, w)["counts"]
    return counts.decode("ascii") if isinstance(counts, bytes) else counts


DISPARITY_SIGMA_PX = 0.3  # REFERENCE: sub-pixel SGM disparity noise on KITTI is ~0.2-0.5 px (Hirschmüller 2008; KITTI stereo 2012 end-point errors)
MOTION_K_SIGMA = 3.0  # ours: a speed is reported only when the fit's slope is 3 σ from zero (~0.3 % false "moving" per static tube under Gaussian noise)


def motion_fit(t_s: np.ndarray, foot: np.ndarray, depth_sigma: np.ndarray | None = None) -> tuple[float, float, float, float]:
    """Ground speed from a least-squares line through the observed footpoints over time.

    Summing frame-to-frame steps integrates every frame's stereo depth noise into the path
    (a static barrier "travels" metres); the slope of a line fitted to all positions
    averages it out. Returns (speed m/s, speed σ m/s, net path m, path σ m); σ comes from the
    fit's residuals (the positions' own scatter, i.e. the stereo noise at that depth), NaN
    when fewer than three observations make the scatter unmeasurable.
    """
    n = len(t_s)
    if n < 2:
        return 0.0, float("nan"), 0.0, float("nan")
    tc = t_s - t_s.mean()
    sxx = float(np.sum(tc * tc))
    if sxx <= 0:
        return 0.0, float("nan"), 0.0, float("nan")
    xz = foot[:, [0, 2]]  # ground plane: x right, z forward (y is height)
    slope = (tc[:, None] * (xz - xz.mean(axis=0))).sum(axis=0) / sxx
    speed = float(np.linalg.norm(slope))
    if n < 3:
        return speed, float("nan"), speed * float(t_s[-1] - t_s[0]), float("nan")
    resid = xz - xz.mean(axis=0) - tc[:, None] * slope
    sigma_pos = float(np.sqrt(np.sum(resid ** 2) / (2 * (n - 2))))  # per-axis position σ
    if depth_sigma is not None and len(depth_sigma):
        # filtered footpoints are smoother than their stereo noise: the residuals alone
        # under-state it, so the stereo depth σ (Z²/(f·B)·σ_d) is a floor
        sigma_pos = max(sigma_pos, float(np.sqrt(np.mean(np.square(depth_sigma)))))
    speed_sigma = sigma_pos / np.sqrt(sxx)
    duration = float(t_s[-1] - t_s[0])
    return speed, float(speed_sigma), speed * duration, float(speed_sigma * duration)


def tube_summary(mt: MinedTube, bf: float | None = None) -> dict:
    """The 3D summary of a tube: mean footpoint, median size, path length and speed (a line
    fitted to the observed footpoints over time) with their σ; ``moving_speed_mps`` is the
    speed where it exceeds ``MOTION_K_SIGMA`` σ, else null (static or not measurable)."""
    frames = mt.tube.frames
    obs = [f for f in frames if f.observed] or frames
    foot = np.array([f.footpoint_world for f in obs], np.float64)
    t_s = np.array([f.t_ns for f in obs], np.float64) / 1e9
    ok = np.isfinite(foot).all(axis=1)
    z = np.array([f.position_cam[2] for f in obs], np.float64)[ok]
    depth_sigma = None if bf is None else z ** 2 / bf * DISPARITY_SIGMA_PX
    speed, speed_sigma, path, path_sigma = motion_fit(t_s[ok], foot[ok], depth_sigma)
    moving = speed if np.isfinite(speed_sigma) and speed > MOTION_K_SIGMA * speed_sigma else None
    return {
        "mean_position": _vec(np.mean([f.footpoint_world for f in obs], axis=0)),
        "size": _vec(np.median([f.size for f in obs], axis=0)),
        "path_length": float(path),
        "speed": float(speed),
        "speed_sigma_mps": _opt(speed_sigma), "path_sigma_m": _opt(path_sigma),
        "moving_speed_mps": moving,
    }


THETA_GROUPS = tuple(c.removeprefix("theta_") for c in THETA_COLUMNS)  # score/calibrated.GROUPS (tests check)


def tube_row(mt: MinedTube, tube_id: str, run: RunInfo, n_windows: int = 1) -> dict:
    t = mt.tube
    c = mt.category
    return {
        "tube_id": tube_id,
        "t_start": int(t.frames[0].t_ns), "t_end": int(t.frames[-1].t_ns),
        "frame_start": int(t.first_frame), "frame_end": int(t.last_frame),
        "n_frames": len(t.frames), "n_observed": t.n_inliers,
        "score": float(mt.score.total), "score_model": mt.score.model,
        "score_version": mt.score.version or None,
        **{f"theta_{g}": (None if mt.score.terms is None else float(mt.score.terms[g])) for g in THETA_GROUPS},
        "score_motion": float(mt.score.motion),
        "score_mask": float(mt.score.mask), "score_objectness": float(mt.score.objectness),
        "selected": bool(mt.selected), "call": c.call, "object_prob": _opt(c.object_prob),
        "known": None if c.known is None else bool(c.known), "category": c.category,
        "category_prob": _opt(c.probability), "best_known": c.best_known,
        "class_posterior": None if c.posterior is None else _vec(c.posterior),
        "classified_frames": int(c.classified_frames), "class_evidence": float(c.evidence),
        "segment": int(t.segment),
        **tube_summary(mt, run.bf),
        "n_windows": n_windows,
        "run_id": run.run_id, "params_hash": run.params_hash, "schema_version": SCHEMA_VERSION,
    }


def frame_rows(mt: MinedTube, tube_id: str, cam_from_world: Callable[[int], np.ndarray] | None = None,
               core: Callable[[int], bool] | None = None, window: str | None = None) -> list[dict]:
    """One row per tube frame. With ``window`` set, the rows are a part's (extra columns).

    ``cam_from_world(frame)`` gives the (4, 4) world-to-camera transform of a frame; parts
    need it to store the footpoint and velocity in camera coordinates.
    """
    rows = []
    for f in mt.tube.frames:
        h, w = f.rle["size"]
        row = {
            "tube_id": tube_id, "frame": int(f.frame), "t_ns": int(f.t_ns), "bbox": _vec(f.box),
            "rle_counts": compressed_counts(f.rle), "rle_h": int(h), "rle_w": int(w),
            "observed": bool(f.observed), "obs_index": int(f.obs_index),
            "objectness": _opt(f.objectness), "position_cam": _vec(f.position_cam),
            "position_world": _vec(f.footpoint_world), "velocity_world": _vec(f.velocity_world),
            "size": _vec(f.size), "mask_iou": _opt(f.mask_iou), "motion_density": _opt(f.motion_density),
        }
        if window is not None:
            T = cam_from_world(f.frame)
            row["window"] = window
            row["core"] = bool(core(f.frame))
            row["posterior"] = None if f.posterior is None else _vec(f.posterior)
            row["class_weight"] = float(f.class_weight)
            row["footpoint_cam"] = _vec(T[:3, :3] @ f.footpoint_world + T[:3, 3])
            row["velocity_cam"] = _vec(T[:3, :3] @ f.velocity_world)
        rows.append(row)
    return rows


def part_tube_frame(r: dict, pose: np.ndarray) -> TubeFrame:
    """A part's tube-frame row (``frame_rows`` with ``window``) as a tube frame in the world
    whose (4, 4) camera-to-world transform of that frame is ``pose``."""
    R, t = pose[:3, :3], pose[:3, 3]
    nan = float("nan")
    return TubeFrame(
        frame=r["frame"], t_ns=r["t_ns"], observed=r["observed"], obs_index=r["obs_index"],
        rle={"size": [r["rle_h"], r["rle_w"]], "counts": r["rle_counts"].encode("ascii")},
        box=np.asarray(r["bbox"], np.float64),
        footpoint_world=R @ np.asarray(r["footpoint_cam"], np.float64) + t,
        velocity_world=R @ np.asarray(r["velocity_cam"], np.float64),
        size=np.asarray(r["size"], np.float64), position_cam=np.asarray(r["position_cam"], np.float64),
        objectness=nan if r["objectness"] is None else r["objectness"],
        mask_iou=nan if r["mask_iou"] is None else r["mask_iou"],
        motion_density=nan if r["motion_density"] is None else r["motion_density"],
        posterior=None if r["posterior"] is None else np.asarray(r["posterior"], np.float64),
        class_weight=float(r["class_weight"]),
    )


class BadMask(InputError):
    """A ``tube_frames`` row whose mask cannot be drawn: malformed (``problem`` says how) or,
    with ``mismatch``, of another size than the frame it belongs to."""

    def __init__(self, reason: str, row: dict, problem: str, mismatch: bool = False, path: str | None = None):
        self.problem, self.mismatch = problem, mismatch
        super().__init__(reason, path, row.get("frame"))


def mask_problem(row: dict) -> str | None:
    """Why a ``tube_frames`` row's RLE (``rle_h``, ``rle_w``, ``rle_counts``) is malformed, or
    None: its size at most MAX_MASK_PIXELS, then ``mining.masks.rle_problem`` (its size positive, its runs
    covering exactly H × W pixels)."""
    h, w = row["rle_h"], row["rle_w"]
    if isinstance(h, int) and isinstance(w, int) and h > 0 and w > 0 and h * w > MAX_MASK_PIXELS:
        return f"its size {w}x{h} ({h * w / 1e6:.0f} MP) is over the {MAX_MASK_PIXELS / 1e6:.1f} MP of an 8K frame"
    return rle_problem(h, w, row["rle_counts"])


def mask_rle(row: dict, shape: tuple[int, int] | None = None, path: str | None = None) -> dict:
    """The checked COCO RLE (``size`` [h, w], ``counts`` bytes) of a ``tube_frames`` row;
    BadMask (naming ``path`` and the row's frame) when it is malformed or, given the
    ``shape`` (height, width) of the frame it belongs to, of another size."""
    tube = row.get("tube_id")
    if shape is not None and (row["rle_h"], row["rle_w"]) != tuple(shape):
        size = f"{row['rle_h']}×{row['rle_w']}"
        raise BadMask(f"mask size {size} of tube {tube} differs from the image's {shape[0]}×{shape[1]}", row,
                      f"{size} is not {shape[0]}×{shape[1]}", mismatch=True, path=path)
    problem = mask_problem(row)
    if problem is not None:
        raise BadMask(f"the {MASK_TABLE} row of tube {tube!r} has a malformed mask ({problem})", row, problem,
                      path=path)
    return {"size": [row["rle_h"], row["rle_w"]], "counts": row["rle_counts"].encode()}


def decode_mask(row: dict, shape: tuple[int, int] | None = None, path: str | None = None) -> np.ndarray:
    """The (H, W) uint8 0/1 mask of a ``tube_frames`` row, checked as ``mask_rle`` checks it."""
    return mask_utils.decode(mask_rle(row, shape, path))


class ObservedFrameLike(Protocol):
    """What a ``frames`` row records of an observed frame (``mining.pipeline.window.ObservedFrame``)."""

    position: int
    index: int
    t_ns: int
    T_cur_prev: np.ndarray | None
    egomotion_ok: bool | None
    egomotion_inliers: int
    egomotion_rmse_px: float
    ground_ok: bool
    ground_age: int | None
    n_proposals: int
    observations: Sized


def frames_row(f: ObservedFrameLike, pose: np.ndarray, segment: int) -> dict:
    """A frame's row of a window's ``frames`` part: its (4, 4) chained ``pose`` and pose
    ``segment`` in the window, its egomotion and ground quality and its counts."""
    return {"frame": f.index, "position": f.position, "t_ns": f.t_ns, "segment": segment,
            "pose": pose.ravel().tolist(), "egomotion_ok": f.egomotion_ok,
            "egomotion_inliers": f.egomotion_inliers,
            "egomotion_rmse_px": None if not np.isfinite(f.egomotion_rmse_px) else f.egomotion_rmse_px,
            "ground_ok": f.ground_ok, "ground_age": f.ground_age, "n_proposals": f.n_proposals,
            "n_observations": len(f.observations),
            "T_cur_prev": None if f.T_cur_prev is None else f.T_cur_prev.ravel().tolist()}


def to_table(rows: Sequence[dict], table: str, part: bool = False) -> pa.Table:
    """``rows`` of ``table`` without ``dataset`` / ``sequence`` (their folder names say them): a
    manifest row, a window's part (``part``), or one sequence's rows, which ``store.write_sequence``
    completes with both."""
    schema = part_schema(table) if part else hive_file_schema(table)
    return pa.Table.from_pylist(list(rows), schema=schema)
