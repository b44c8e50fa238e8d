"""The few data types every stage shares.

Conventions used throughout the code base:

* Images are rectified, RGB, ``uint8``, shape ``(H, W, 3)``; the left camera is the
  reference camera.
* Camera coordinates: x right, y down, z forward, metres (the KITTI convention).
* A *pose* is a 4×4 camera-to-world transform; the world is the first frame's camera.
* An *egomotion* ``T_cur_prev`` is the 4×4 transform that maps a point given in the
  previous frame's camera coordinates into the current frame's camera coordinates:
  ``X_cur = T_cur_prev @ X_prev``. Hence ``pose_cur = pose_prev @ inv(T_cur_prev)``.
* Disparity is in pixels, ``x_left − x_right`` (positive); invalid pixels are NaN.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class StereoCalib:
    """Pinhole intrinsics of the rectified left camera plus the stereo baseline."""

    fx: float
    fy: float
    cx: float
    cy: float
    baseline_m: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        """3×3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def bf(self) -> float:
        """Baseline × focal length: depth = bf / disparity."""
        return self.baseline_m * self.fx

    def depth_from_disparity(self, disparity: np.ndarray) -> np.ndarray:
        """Depth in metres; NaN where the disparity is invalid (NaN or ≤ 0)."""
        d = np.asarray(disparity, dtype=np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.float32(self.bf) / d
        z[~(d > 0)] = np.nan
        return z

    def backproject(self, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Pixel coordinates and depth → (N, 3) camera points."""
        x = (np.asarray(u, np.float64) - self.cx) * z / self.fx
        y = (np.asarray(v, np.float64) - self.cy) * z / self.fy
        return np.stack([x, y, np.asarray(z, np.float64)], axis=-1)

    def project(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) camera points → (N, 2) pixel coordinates (no visibility check)."""
        p = np.asarray(points, np.float64)
        return np.stack([self.fx * p[:, 0] / p[:, 2] + self.cx, self.fy * p[:, 1] / p[:, 2] + self.cy], axis=-1)


@dataclass
class ObjectTruth:
    """Ground truth of one object instance in one frame (synthetic source only)."""

    track_id: int
    category: str  # e.g. "car", "person", "bicycle", "cone", "tyre", "tortoise" (synthetic: scene.KNOWN lists them)
    known: bool  # True when one of the 80 COCO classes covers the category
    mask: np.ndarray  # (H, W) bool, visible pixels in the left image
    box: tuple[float, float, float, float]  # x1, y1, x2, y2 of the visible mask, pixels
    center_cam: np.ndarray  # (3,) object centre in the left camera frame, metres
    size: np.ndarray  # (3,) width, height, length, metres
    velocity_world: np.ndarray  # (3,) metres per second in the world frame


@dataclass
class FrameTruth:
    """Exact ground truth of one frame, where the source knows it (synthetic)."""

    depth: np.ndarray  # (H, W) float32 metres, NaN where nothing was hit (sky)
    pose: np.ndarray  # (4, 4) camera-to-world
    objects: list[ObjectTruth] = field(default_factory=list)


@dataclass
class StereoFrame:
    """One rectified stereo pair with its calibration and time."""

    dataset: str
    sequence: str
    index: int  # frame index within the sequence (0-based, as the source numbers it)
    t_ns: int  # capture time, nanoseconds
    left: np.ndarray  # (H, W, 3) uint8 RGB, rectified
    right: np.ndarray  # (H, W, 3) uint8 RGB, rectified
    calib: StereoCalib
    truth: FrameTruth | None = None


@dataclass(frozen=True)
class SequencePlan:
    """What a source knows about a sequence before decoding any image.

    ``frames`` lists the frame indices that exist, in time order; ``t_ns`` holds their
    timestamps. A recording gap (e.g. a missing RobotCar chunk) shows as a jump in
    ``t_ns``; ``gaps`` lists the positions ``i`` in ``frames`` where a gap lies between
    ``frames[i-1]`` and ``frames[i]``.

    ``problems`` are frames the listing shows cannot be read (one image of the pair
    missing), as (position, message naming the file and frame): they keep their place,
    so positions do not shift when a file goes missing, and only a job whose frame range
    holds one of them is refused (``Source.plan``).
    """

    dataset: str
    sequence: str
    calib: StereoCalib
    frames: tuple[int, ...]
    t_ns: tuple[int, ...]
    gaps: tuple[int, ...] = ()
    problems: tuple[tuple[int, str], ...] = ()
    note: str = ""  # how the source sampled the recording, for the run summary ("stride 4: …"); "" = every frame

    def problem_in(self, start: int = 0, stop: int | None = None) -> str | None:
        """The first problem at a position in ``[start, stop)``, or None."""
        stop = len(self.frames) if stop is None else stop
        return next((msg for pos, msg in self.problems if start <= pos < stop), None)

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def duration_s(self) -> float:
        return (self.t_ns[-1] - self.t_ns[0]) / 1e9 if self.frames else 0.0


@dataclass(frozen=True)
class Window:
    """The unit of scheduling, retry and output: a core frame range plus its context.

    Ranges are half-open positions into ``SequencePlan.frames``.
    """

    dataset: str
    sequence: str
    core: tuple[int, int]
    context: tuple[int, int]

    @property
    def name(self) -> str:
        """Deterministic name used for output files and the manifest."""
        return f"{self.sequence}-{self.core[0]:07d}-{self.core[1]:07d}"


def plan_windows(plan: SequencePlan, core: int = 100, before: int = 0, after: int = 0,
                 start: int = 0, stop: int | None = None) -> list[Window]:
    """Cut plan positions [start, stop) into windows of ``core`` frames, each with its context margins."""
    if core <= 0:
        raise ValueError("window core length must be positive")
    n = len(plan) if stop is None else min(stop, len(plan))
    start = max(0, start)
    out = []
    for s in range(start, n, core):
        e = min(s + core, n)
        out.append(Window(plan.dataset, plan.sequence, (s, e), (max(start, s - before), min(n, e + after))))
    return out


@dataclass
class Egomotion:
    """Camera motion from the previous frame to this one.

    ``ok`` is False when the estimate failed (too few inliers, no convergence, degenerate
    geometry); ``T_cur_prev`` is then None. A failure is never replaced by the identity.
    """

    T_cur_prev: np.ndarray | None  # (4, 4), see the module docstring
    inliers: int
    matches: int  # cycle-consistent matches the estimate started from
    rmse_px: float  # reprojection RMSE over the inliers (NaN when failed)
    ok: bool
    reason: str = ""  # why it failed, empty when ok


@dataclass
class SceneFlow:
    """Sparse scene flow: cycle-consistent features triangulated at t−1 and t.

    All arrays have N rows. ``motion`` is each point's own 3D motion between the two
    frames in the current camera frame after removing the egomotion (zero for static
    points, up to noise); ``NaN`` rows when the egomotion failed.
    """

    uv_prev: np.ndarray  # (N, 2) left-image pixels at t−1
    uv: np.ndarray  # (N, 2) left-image pixels at t
    disparity_prev: np.ndarray  # (N,)
    disparity: np.ndarray  # (N,)
    points_prev: np.ndarray  # (N, 3) camera t−1
    points: np.ndarray  # (N, 3) camera t
    motion: np.ndarray  # (N, 3) metres, current camera frame
    inlier: np.ndarray  # (N,) bool, consistent with the egomotion (static scene)

    def __len__(self) -> int:
        return len(self.uv)


@dataclass
class GroundPlane:
    """Plane n·X + d = 0 in camera coordinates, n unit length and pointing up (−y)."""

    normal: np.ndarray | None  # (3,)
    d: float
    inliers: int
    ok: bool
    reason: str = ""

    def height(self, points: np.ndarray) -> np.ndarray:
        """Signed height of points above the plane (positive above), metres."""
        if not self.ok:
            raise ValueError("no ground plane: " + self.reason)
        return np.asarray(points) @ self.normal + self.d


@dataclass
class FrameGeometry:
    """Everything the geometry stage computes for one frame."""

    index: int
    t_ns: int
    disparity: np.ndarray  # (H, W) float32 pixels, NaN = invalid
    depth: np.ndarray  # (H, W) float32 metres, NaN = invalid
    flow: SceneFlow | None  # None on the first frame of a run
    egomotion: Egomotion | None  # None on the first frame of a run
    ground: GroundPlane
    timings_ms: dict[str, float] = field(default_factory=dict)


N_CLASSES = 81  # the 80 COCO classes + "unknown" (the paper's category vector c ∈ R^81)
UNKNOWN_CLASS = 80  # index of "unknown" in a class posterior


def max_class_score(posterior: np.ndarray) -> float:
    """The classifier's max class score p* recovered from its row's posterior: the row is
    [p_1..p_80, 1 − p*] / Z (``mining.proposals.yolo_seg.class_posterior``), so
    P[k*] / P[unknown] = p* / (1 − p*). 0 for a class-agnostic row (all "unknown")."""
    pk, pu = float(np.max(posterior[:UNKNOWN_CLASS])), float(posterior[UNKNOWN_CLASS])
    if pk <= 0:
        return 0.0
    return 1.0 if pu <= 0 else pk / (pk + pu)


@dataclass
class Proposals:
    """One frame's image-level mask proposals, as a struct of arrays (N proposals).

    Masks are COCO compressed RLEs (``{"size": [h, w], "counts": bytes}``, as
    ``pycocotools.mask.encode`` makes them) so that no stage holds full-frame arrays per
    proposal. ``posterior`` is an (N, 81) distribution over the 80 COCO classes plus
    unknown (rows sum to 1), or None when the proposer has no classes; in a union of
    proposers, the rows of a proposer without classes are NaN.
    """

    frame: int
    rles: list[dict]
    boxes: np.ndarray  # (N, 4) float32 x1, y1, x2, y2 pixels
    objectness: np.ndarray  # (N,) float32 in [0, 1]
    posterior: np.ndarray | None = None  # (N, 81) float32
    proposer: list[str] = field(default_factory=list)  # which proposer made each row
    position: np.ndarray | None = None  # (N, 3) camera metres where the proposer measures 3D (e.g. LiDAR boxes), NaN rows otherwise
    size: np.ndarray | None = None  # (N, 3) width, height, length metres where known, NaN rows otherwise
    class_weight: np.ndarray | None = None  # (N,) how much a row's posterior counts toward its tube's class; None = 1 per classified row

    def class_weights(self) -> np.ndarray:
        """(N,) evidence weight of each row's posterior: 0 where no classifier looked (no or NaN
        posterior), else ``class_weight`` (1 when unset: the classifier's own rows)."""
        if self.posterior is None:
            return np.zeros(len(self), np.float32)
        looked = np.isfinite(self.posterior).all(axis=1)
        w = np.ones(len(self), np.float32) if self.class_weight is None else np.asarray(self.class_weight, np.float32)
        return np.where(looked, w, 0.0).astype(np.float32)

    def __len__(self) -> int:
        return len(self.rles)

    def take(self, idx: np.ndarray) -> Proposals:
        """The proposals at ``idx`` (indices or a boolean mask), in that order."""
        idx = np.flatnonzero(idx) if np.asarray(idx).dtype == bool else np.asarray(idx, np.int64)

        def rows(a):
            return None if a is None else a[idx]

        return Proposals(
            frame=self.frame,
            rles=[self.rles[i] for i in idx],
            boxes=self.boxes[idx],
            objectness=self.objectness[idx],
            posterior=rows(self.posterior),
            proposer=[self.proposer[i] for i in idx] if self.proposer else [],
            position=rows(self.position),
            size=rows(self.size),
            class_weight=rows(self.class_weight),
        )

    @staticmethod
    def cat(parts: Sequence[Proposals]) -> Proposals:
        """The rows of several proposal sets of one frame, one set after the other.

        An optional field (posterior, position, size) that some sets lack becomes NaN rows
        for them ("not known"); None when every set lacks it. Proposer names are kept when
        every set has them.
        """
        if not parts:
            raise ValueError("concatenation of no proposal sets")
        frame = parts[0].frame
        if any(p.frame != frame for p in parts):
            raise ValueError(f"cannot concatenate proposals of frames {sorted({p.frame for p in parts})}")
        named = [len(p.proposer) == len(p) for p in parts]
        if any(named) and not all(named):
            raise ValueError("cannot concatenate proposal sets with and without proposer names")
        n = [len(p) for p in parts]
        return Proposals(
            frame=frame,
            rles=[r for p in parts for r in p.rles],
            boxes=np.concatenate([p.boxes.reshape(-1, 4) for p in parts]).astype(np.float32),
            objectness=np.concatenate([p.objectness for p in parts]).astype(np.float32),
            posterior=_stack_rows([p.posterior for p in parts], n, N_CLASSES),
            proposer=[name for p in parts for name in p.proposer],
            position=_stack_rows([p.position for p in parts], n, 3),
            size=_stack_rows([p.size for p in parts], n, 3),
            class_weight=None if all(p.class_weight is None for p in parts)
            else np.concatenate([p.class_weights() for p in parts]).astype(np.float32),
        )

    @staticmethod
    def empty(frame: int) -> Proposals:
        return Proposals(frame, [], np.zeros((0, 4), np.float32), np.zeros(0, np.float32))


def _stack_rows(parts: list[np.ndarray | None], n: list[int], width: int) -> np.ndarray | None:
    """Row-stack optional float32 arrays of ``n[i]`` rows each; a missing one becomes NaN
    rows (None if all are missing)."""
    if all(a is None for a in parts):
        return None
    rows = [np.full((k, width), np.nan, np.float32) if a is None else np.asarray(a, np.float32).reshape(k, width)
            for a, k in zip(parts, n)]
    return np.concatenate(rows)


@dataclass
class Observations:
    """One frame's proposals localised in 3D: the paper's position p, velocity v and size s.

    Row i belongs to ``proposals`` row i. Positions are in the current camera frame;
    NaN rows where the mask holds too few valid depth points to localise.
    """

    proposals: Proposals
    t_ns: int
    position: np.ndarray  # (N, 3) median of the mask's 3D points, camera metres
    covariance: np.ndarray  # (N, 3, 3) triangulation covariance (+ prior), m²
    footpoint: np.ndarray  # (N, 3) position projected onto the ground plane
    velocity: np.ndarray  # (N, 3) m/s in the camera frame, NaN without enough flow samples
    velocity_covariance: np.ndarray  # (N, 3, 3)
    size: np.ndarray  # (N, 3) width, height, length metres
    n_points: np.ndarray  # (N,) valid depth points inside the mask
    # The mask's 3D points (camera frame) on a regular pixel grid, kept for mask warping so
    # no later stage decodes the mask again; ``grid[i]`` is the grid's spacing in pixels.
    points: list[np.ndarray] | None = None
    grid: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.proposals)

    def take(self, idx: np.ndarray) -> Observations:
        """The observations at ``idx`` (indices or a boolean mask), in that order."""
        idx = np.flatnonzero(idx) if np.asarray(idx).dtype == bool else np.asarray(idx, np.int64)
        return Observations(
            self.proposals.take(idx), self.t_ns, self.position[idx], self.covariance[idx], self.footpoint[idx],
            self.velocity[idx], self.velocity_covariance[idx], self.size[idx], self.n_points[idx],
            None if self.points is None else [self.points[i] for i in idx],
            None if self.grid is None else self.grid[idx],
        )


@dataclass
class TrackingFrame:
    """Everything the tube stage needs about one frame.

    ``pose`` is camera-to-world for the current *segment*: a failed egomotion starts a new
    segment (``segment`` increments) because nothing links the two sides; tubes never
    cross a segment border. ``depth`` is None in detections-only mode (no images).
    """

    index: int
    t_ns: int
    calib: StereoCalib
    pose: np.ndarray  # (4, 4) camera-to-world within the segment
    segment: int
    observations: Observations
    depth: np.ndarray | None = None  # (H, W) float32 metres, NaN invalid


@dataclass
class TubeFrame:
    """One frame of a tube: an observation (inlier) or the tube's prediction in a gap.

    World coordinates are those of the tube's pose segment (``TrackingFrame.pose``).
    """

    frame: int
    t_ns: int
    observed: bool
    obs_index: int  # row in that frame's Observations; −1 when predicted
    rle: dict  # observed mask, or the predicted mask in a gap
    box: np.ndarray  # (4,) x1, y1, x2, y2
    footpoint_world: np.ndarray  # (3,) filtered footpoint, world (segment) frame
    velocity_world: np.ndarray  # (3,) filtered velocity on the ground plane, m/s
    size: np.ndarray  # (3,) filtered width, height, length
    position_cam: np.ndarray  # (3,) observed 3D position in this frame's camera (predicted in a gap)
    objectness: float  # the proposal's score; NaN when predicted
    mask_iou: float  # IoU(predicted mask, observed mask); NaN for a tube's first inlier and in gaps
    motion_density: float  # Gaussian density of the observed footpoint under the prediction; NaN likewise
    posterior: np.ndarray | None = None  # the observation's 81-way class posterior; None where no classifier looked
    class_weight: float = 1.0  # how much ``posterior`` counts (Proposals.class_weights); ignored without a posterior


@dataclass
class Tube:
    """A video object tube (the paper's hypothesis): the frames it spans, in time order.

    The tracking state a tube has while it is being extended (filter, mask points, gap)
    is the tube generator's, not the tube's: a tube read back from the catalogue is the
    same object as one just made.
    """

    tube_id: int
    segment: int
    frames: list[TubeFrame] = field(default_factory=list)
    end_reason: str = ""

    @property
    def n_inliers(self) -> int:
        return sum(1 for f in self.frames if f.observed)

    @property
    def first_frame(self) -> int:
        return self.frames[0].frame

    @property
    def last_frame(self) -> int:
        return self.frames[-1].frame

    @property
    def last_inlier(self) -> TubeFrame:
        """The last observed frame (every tube has one: a tube starts at an observation)."""
        return next(f for f in reversed(self.frames) if f.observed)

    def frame_map(self) -> dict[int, TubeFrame]:
        return {f.frame: f for f in self.frames}

    def inlier_key(self) -> tuple[tuple[int, int], ...]:
        """(frame, observation) of every inlier: two tubes with the same key explain the same data."""
        return tuple((f.frame, f.obs_index) for f in self.frames if f.observed)

    def trim(self) -> None:
        """Drop trailing predicted frames: a tube ends at its last observation."""
        while self.frames and not self.frames[-1].observed:
            self.frames.pop()


@dataclass
class TubeScore:
    """The tube's unary score (paper Eq. 2–8): its three log-likelihood ratios and the total the
    run's unary gives: REFERENCE's weighted sum of them (``model`` "reference"), or the
    calibrated log-odds (``model`` "calibrated"), whose groups of terms (``terms``,
    ``mining.score.calibrated.GROUPS``) add up to it; two totals compare only where ``version`` agrees."""

    motion: float
    mask: float
    objectness: float
    total: float
    model: str = "reference"
    terms: dict[str, float] | None = None
    version: str = ""  # the model and a hash of every parameter of its total (``score.unary.unary_version``)


# A tube's call (the rule: ``mining.score.call``): known (one of the 80 COCO classes wins its posterior),
# unknown (unknown wins and its object evidence says object), clutter (unknown wins, but the object gate
# says P(object) below ``score.unknown_min_object``), unclassified (no classifier looked).
CALLS = ("known", "unknown", "clutter", "unclassified")


@dataclass
class TubeCategory:
    """What the tube is, from the frames where a classifier looked (``mining.score.category``)
    and the object gate (``mining.score.call``).

    ``known`` is True (one of the 80 COCO classes wins the posterior), False (unknown wins) or
    None (*unclassified*: no classifier looked, ``classified_frames`` 0); ``category`` is the
    winning COCO class, "unknown", or None when unclassified. ``clutter``: unknown, but the
    object gate judged it not an object (``object_prob`` below the gate's threshold); ``call``
    says which of ``CALLS`` the tube is.
    """

    posterior: np.ndarray | None  # (81,) evidence-weighted mean over the classified frames, or None
    category: str | None  # COCO class name, "unknown", or None (unclassified)
    probability: float  # posterior mass of ``category`` (NaN when unclassified)
    known: bool | None
    best_known: str | None  # the most probable of the 80 classes, even when the tube is unknown (None when unclassified)
    classified_frames: int = 0  # observed frames whose posterior counted (weight > 0)
    evidence: float = 0.0  # the sum of those frames' weights (frame-equivalents of a classifier's own rows)
    object_prob: float = float("nan")  # P(object) of the object gate for a tube unknown wins (NaN: not judged)
    clutter: bool = False  # unknown wins and the object gate said not an object

    @property
    def call(self) -> str:
        """One of ``CALLS``."""
        if self.known is None:
            return "unclassified"
        if self.known:
            return "known"
        return "clutter" if self.clutter else "unknown"


@dataclass
class MinedTube:
    """A tube as the miner judged it: score, category and whether co-selection chose it."""

    tube: Tube
    score: TubeScore
    category: TubeCategory
    selected: bool
