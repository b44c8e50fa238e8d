"""The tube descriptor: one fixed-length float32 vector per tube, from what the pipeline already
measured (no weights from outside), for finding similar tubes and grouping the unknown set.

Every component is a physical quantity of the ``tubes`` row or a summary of the tube's observed
``tube_frames`` rows, put on a common scale by a *fixed* transform (a named centre and scale per
component, chosen from the physics of street scenes; never fitted on the data, so a descriptor
does not move when the catalogue grows). The table (``COMPONENTS``, in vector order):

=====================  ========  ==========================================================  ===============
component              family    raw quantity                                                transform
=====================  ========  ==========================================================  ===============
log_width              size      ``size[0]``, m (median over observed frames)                ln(x / 1 m) / ln 10
log_height             size      ``size[1]``, m                                              ln(x / 1 m) / ln 10
log_length             size      ``size[2]``, m                                              ln(x / 1 m) / ln 10
foot_elevation         height    −median camera y of the footpoint, m (y down: a footpoint   (x + 1.65 m) / 2 m
                                 on level ground sits one camera height below the camera)
log_distance           distance  median camera z of the footpoint, m                         ln(x / 10 m) / ln 10
log_speed              motion    ``speed``, m/s (ground-plane line fit)                      ln(1 + x / 1 m/s) / ln 10
log_speed_sigma        motion    ``speed_sigma_mps`` (null: 1 m/s, not measurable)           ln(1 + x / 1 m/s) / ln 10
moving                 motion    1 where ``moving_speed_mps`` is set (speed > 3 σ), else 0   x
log_path               motion    ``path_length``, m                                          ln(1 + x / 1 m) / ln 10
log_duration           motion    ``n_frames``                                                ln(x / 10) / ln 10
box_aspect             shape     median ln(box width / box height) over observed frames      x / ln 4
mask_fill              shape     median mask area / box area (pycocotools area)              (x − 0.5) / 0.5
aspect_spread          shape     σ over frames of ln(box width / box height)                 x / ln 2
fill_spread            shape     σ over frames of mask area / box area                       x / 0.25
area_spread            shape     σ over frames of ln(mask area)                              x / ln 2
class_entropy          class     entropy of ``class_posterior`` (81 classes)                 x / ln 81
p_unknown              class     posterior mass of "unknown" (index 80)                      x
top_known              class     largest posterior mass of the 80 COCO classes               x
object_prob            class     ``object_prob`` of the object gate (null: 0.5, not judged)  x − 0.5
=====================  ========  ==========================================================  ===============

An unclassified tube (no posterior) has class_entropy 1, p_unknown 0, top_known 0: no classifier
looked, so nothing is claimed.

Each family (size, height, distance, motion, shape, class) weighs the same: every component is
multiplied by 1/√(its family's size), so a family of five quantities carries no more of a
vector's length than a family of one. Similarity is cosine distance over these vectors
(``similar.py``).

Left out: colour. It needs the source images, which the catalogue does not hold (``mine export
--format crops`` reads them through the source); a descriptor computable from the catalogue alone
stays cheap to recompute for the whole drive. A later recipe may add it under a new version.

``DESCRIPTOR_VERSION`` names the recipe: ``RECIPE`` (bumped by hand when the code changes what a
component means) and a hash of ``COMPONENTS`` (so a changed centre or scale is a new version by
itself). Stored descriptors of another version are recomputed (``describe.py``).
"""

from __future__ import annotations

import hashlib
import math
from typing import NamedTuple

import duckdb
import numpy as np
import pyarrow as pa

from mining.masks import areas

RECIPE = 1  # ours: bump when the code changes what a component measures
LN10, LN4, LN2 = math.log(10.0), math.log(4.0), math.log(2.0)
CAMERA_HEIGHT_M = 1.65  # physical: a car-roof stereo rig's height above the road (KITTI 1.65 m, RobotCar ~1.5 m)
UNKNOWN_INDEX = 80  # the "unknown" entry of the 81-way class posterior (formats/coco.py: 80 COCO classes, then unknown)
N_CLASSES = 81  # 80 COCO classes + unknown
SIGMA_UNMEASURED_MPS = 1.0  # ours: speed noise taken for a tube under 3 observations (σ null): "not measurable"
OBJECT_PROB_UNJUDGED = 0.5  # ours: P(object) of a tube the object gate did not judge: no claim either way
MIN_POSITIVE = 1e-3  # ours: floor under a logged length, ratio or area (a degenerate box must not give −inf)


class Component(NamedTuple):
    """One entry of the vector: ``value = transform(raw)``; see the module docstring's table."""

    name: str
    family: str
    transform: str  # log: ln(x / centre) / scale · log1p: ln(1 + x / centre) / scale · lin: (x − centre) / scale
    centre: float
    scale: float


COMPONENTS = (
    Component("log_width", "size", "log", 1.0, LN10),  # a decade of size is one unit
    Component("log_height", "size", "log", 1.0, LN10),
    Component("log_length", "size", "log", 1.0, LN10),
    Component("foot_elevation", "height", "lin", -CAMERA_HEIGHT_M, 2.0),  # 2 m: a person's height
    Component("log_distance", "distance", "log", 10.0, LN10),  # 10 m: the middle of a stereo rig's useful range
    Component("log_speed", "motion", "log1p", 1.0, LN10),  # 1 m/s: a slow walk
    Component("log_speed_sigma", "motion", "log1p", 1.0, LN10),
    Component("moving", "motion", "lin", 0.0, 1.0),
    Component("log_path", "motion", "log1p", 1.0, LN10),  # 1 m: a step
    Component("log_duration", "motion", "log", 10.0, LN10),  # 10 frames: a second of video
    Component("box_aspect", "shape", "lin", 0.0, LN4),  # a box four times wider than high is one unit
    Component("mask_fill", "shape", "lin", 0.5, 0.5),  # 0 … 1 onto −1 … 1
    Component("aspect_spread", "shape", "lin", 0.0, LN2),  # the aspect doubling is one unit
    Component("fill_spread", "shape", "lin", 0.0, 0.25),
    Component("area_spread", "shape", "lin", 0.0, LN2),  # the mask area doubling is one unit
    Component("class_entropy", "class", "lin", 0.0, math.log(N_CLASSES)),  # 0 … 1 (uniform posterior)
    Component("p_unknown", "class", "lin", 0.0, 1.0),
    Component("top_known", "class", "lin", 0.0, 1.0),
    Component("object_prob", "class", "lin", OBJECT_PROB_UNJUDGED, 1.0),
)
NAMES = tuple(c.name for c in COMPONENTS)
DIM = len(COMPONENTS)


def _recipe_hash() -> str:
    text = repr((RECIPE, COMPONENTS, CAMERA_HEIGHT_M, SIGMA_UNMEASURED_MPS, OBJECT_PROB_UNJUDGED, MIN_POSITIVE))
    return hashlib.sha256(text.encode()).hexdigest()[:8]


DESCRIPTOR_VERSION = f"d{RECIPE}-{_recipe_hash()}"  # stored beside every vector; another version is recomputed


def family_weights() -> np.ndarray:
    """1/√(family size) per component: every family carries the same weight."""
    fams = [c.family for c in COMPONENTS]
    return np.array([1.0 / math.sqrt(fams.count(f)) for f in fams], np.float64)


def normalise(raw: np.ndarray) -> np.ndarray:
    """(n, DIM) raw quantities (columns in ``NAMES`` order, physical units) → float32 descriptors."""
    raw = np.asarray(raw, np.float64)
    if raw.ndim != 2 or raw.shape[1] != DIM:
        raise ValueError(f"raw descriptor quantities must be (n, {DIM}), got {raw.shape}")
    out = np.empty_like(raw)
    for k, c in enumerate(COMPONENTS):
        x = raw[:, k]
        if c.transform == "log":
            out[:, k] = np.log(np.maximum(x, MIN_POSITIVE) / c.centre) / c.scale
        elif c.transform == "log1p":
            out[:, k] = np.log1p(np.maximum(x, 0.0) / c.centre) / c.scale
        else:
            out[:, k] = (x - c.centre) / c.scale
    return (out * family_weights()).astype(np.float32)


# Per observed frame: the box's log aspect, the mask's fill of its box and log area, the footpoint.
_FRAME_SQL = """
SELECT tube_id,
       median(log_aspect) AS box_aspect, median(fill) AS mask_fill,
       coalesce(stddev_pop(log_aspect), 0) AS aspect_spread, coalesce(stddev_pop(fill), 0) AS fill_spread,
       coalesce(stddev_pop(log_area), 0) AS area_spread,
       -median(cam_y) AS foot_elevation, median(cam_z) AS distance
FROM per_frame GROUP BY tube_id
"""


def frame_summaries(tube_frames: pa.Table) -> dict[str, np.ndarray]:
    """Per tube (``tube_id`` → row), the shape and position summaries of its observed frames:
    (box_aspect, mask_fill, aspect_spread, fill_spread, area_spread, foot_elevation, distance)."""
    tf = tube_frames.filter(tube_frames.column("observed"))
    if not len(tf):
        return {}
    box = np.asarray(tf.column("bbox").combine_chunks().flatten().to_numpy(zero_copy_only=False), np.float64).reshape(-1, 4)
    bw = np.maximum(box[:, 2] - box[:, 0], MIN_POSITIVE)
    bh = np.maximum(box[:, 3] - box[:, 1], MIN_POSITIVE)
    rles = [{"size": [int(h), int(w)], "counts": c.encode()} for c, h, w in
            zip(tf.column("rle_counts").to_pylist(), tf.column("rle_h").to_pylist(), tf.column("rle_w").to_pylist())]
    area = areas(rles).astype(np.float64)
    cam = np.asarray(tf.column("position_cam").combine_chunks().flatten().to_numpy(zero_copy_only=False),
                     np.float64).reshape(-1, 3)
    per_frame = pa.table({
        "tube_id": tf.column("tube_id"), "log_aspect": np.log(bw / bh), "fill": np.clip(area / (bw * bh), 0.0, 1.0),
        "log_area": np.log(np.maximum(area, 1.0)), "cam_y": cam[:, 1], "cam_z": cam[:, 2]})
    con = duckdb.connect(":memory:")
    try:
        con.register("per_frame", per_frame)
        rows = con.execute(_FRAME_SQL).fetchall()
    finally:
        con.close()
    return {r[0]: np.array(r[1:], np.float64) for r in rows}


def class_summaries(posteriors: list[list[float] | None]) -> np.ndarray:
    """(n, 3) class_entropy, p_unknown, top_known from each tube's posterior (None: unclassified)."""
    out = np.tile([math.log(N_CLASSES), 0.0, 0.0], (len(posteriors), 1))
    for k, p in enumerate(posteriors):
        if p is None or len(p) != N_CLASSES:
            continue
        q = np.clip(np.asarray(p, np.float64), 0.0, None)
        q = q / q.sum() if q.sum() > 0 else np.full(N_CLASSES, 1.0 / N_CLASSES)
        nz = q[q > 0]
        out[k] = (-(nz * np.log(nz)).sum(), q[UNKNOWN_INDEX], q[:UNKNOWN_INDEX].max())
    return out


TUBE_COLUMNS = ["tube_id", "dataset", "sequence", "size", "speed", "speed_sigma_mps", "moving_speed_mps",
                "path_length", "n_frames", "class_posterior", "object_prob"]
FRAME_COLUMNS = ["tube_id", "bbox", "rle_counts", "rle_h", "rle_w", "observed", "position_cam"]


def raw_quantities(tubes: pa.Table, tube_frames: pa.Table) -> np.ndarray:
    """(n, DIM) raw quantities of ``tubes`` (``TUBE_COLUMNS``) from them and their frames
    (``FRAME_COLUMNS``), rows in ``tubes``' order. A tube without an observed frame takes the
    shape summaries of a plain box (aspect 0, fill 0.5, no spread) and its mean position's distance."""
    n = len(tubes)
    frames = frame_summaries(tube_frames)
    size = np.asarray(tubes.column("size").combine_chunks().flatten().to_numpy(zero_copy_only=False),
                      np.float64).reshape(n, 3)

    def col(name: str, null: float) -> np.ndarray:
        return np.asarray(tubes.column(name).fill_null(null).to_numpy(zero_copy_only=False), np.float64)

    shape = np.array([frames.get(t, np.array([0.0, 0.5, 0.0, 0.0, 0.0, -CAMERA_HEIGHT_M, 10.0]))
                      for t in tubes.column("tube_id").to_pylist()], np.float64).reshape(n, 7)
    moving = (~np.asarray(tubes.column("moving_speed_mps").is_null().to_numpy(zero_copy_only=False))).astype(np.float64)
    cls = class_summaries(tubes.column("class_posterior").to_pylist())
    raw = np.column_stack([
        size, shape[:, 5], shape[:, 6],
        col("speed", 0.0), col("speed_sigma_mps", SIGMA_UNMEASURED_MPS), moving, col("path_length", 0.0),
        col("n_frames", 1.0), shape[:, :5], cls, col("object_prob", OBJECT_PROB_UNJUDGED)])
    return np.nan_to_num(raw, nan=0.0, posinf=0.0, neginf=0.0)


def descriptors(tubes: pa.Table, tube_frames: pa.Table) -> np.ndarray:
    """(n, DIM) float32 descriptors of ``tubes``, every value finite."""
    return normalise(raw_quantities(tubes, tube_frames))
