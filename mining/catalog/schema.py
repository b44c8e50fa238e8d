"""Catalogue schema v3: the Arrow schemas of the four tables (DESIGN.md "Catalogue").

The catalogue is Parquet, one folder per ``dataset`` and ``sequence``
(``catalog/<table>/<dataset>/<sequence>/part-<k>.parquet``, ``layout.py``). From v3 the
compacted files hold every column of their table, ``dataset`` and ``sequence`` included,
as strings, and the folders have plain names: any Parquet reader's default read (pandas,
pyarrow, polars, DuckDB) gives ``sequence`` as the string "0005". ``file_schema`` is that
file's schema. Before v3 the folders were hive-named (``dataset=D/sequence=S``) and the files
left those two columns out, so a default read inferred ``sequence=0005`` as the integer 5;
such a catalogue is still read (``views.py``), its files by ``hive_file_schema``.

The working files stay hive-named without the two columns (``hive_file_schema``): the
manifest rows, and the per-window *parts* (written by each window before stitching), which
use the same tables plus the columns in ``PART_EXTRA``: the stitcher needs each tube
piece's frames in the window's context, and each observation's class posterior to
re-average it. ``schemas/v3/`` holds the same schemas as JSON and the DuckDB views over them.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pyarrow as pa

SCHEMA_VERSION = 3  # v3: dataset / sequence inside the compacted files, plain folder names (v2: hive folders)
# v2: known / category nullable (unclassified), classified_frames, class_evidence
# Nullable columns added since v2: files written before them read them as null (catalog/views.py),
# so an older catalogue (of v2 or v3) stays readable.
THETA_COLUMNS = ("theta_prior", "theta_motion", "theta_mask", "theta_objectness", "theta_shape", "theta_class")
ADDED_COLUMNS = {"tubes": frozenset({"speed_sigma_mps", "path_sigma_m", "moving_speed_mps", "score_model", "score_version",
                                  *THETA_COLUMNS, "call", "object_prob"})}
PARTITION = ("dataset", "sequence")  # the folder levels of every table (hive-named before v3 and in the working files)

vec3 = pa.list_(pa.float32(), 3)
box4 = pa.list_(pa.float32(), 4)

TUBES = pa.schema([
    pa.field("tube_id", pa.string(), False),  # stable: "<dataset>/<sequence>/<first frame>.<observation>"
    pa.field("dataset", pa.string(), False),
    pa.field("sequence", pa.string(), False),
    pa.field("t_start", pa.int64(), False),  # ns, first frame
    pa.field("t_end", pa.int64(), False),  # ns, last frame
    pa.field("frame_start", pa.int32(), False),  # the source's index of the first frame
    pa.field("frame_end", pa.int32(), False),  # index of the last frame (inclusive)
    pa.field("n_frames", pa.int32(), False),
    pa.field("n_observed", pa.int32(), False),
    pa.field("score", pa.float64(), False),  # the unary score_model names: calibrated = natural-log odds that the tube is an object (the theta_* add up to it); reference = β·(α·score_motion + (1−α)·score_mask) + (1−β)·score_objectness
    pa.field("score_model", pa.string()),  # calibrated | reference: which unary made score (null: written before it was stored)
    pa.field("score_version", pa.string()),  # <score_model>-<12 hex>: a hash of every parameter of score (weights, or K, α, β); scores compare only where it agrees (null: written before it was stored)
    # Under the calibrated unary, score's terms by group (mining/score/calibrated.py GROUPS): null under reference.
    pa.field("theta_prior", pa.float64()),  # log-odds from the tube's constant and its length (bias, frame)
    pa.field("theta_motion", pa.float64()),  # log-odds from the footpoints' motion density
    pa.field("theta_mask", pa.float64()),  # log-odds from the warped masks' IoU
    pa.field("theta_objectness", pa.float64()),  # log-odds from the proposals' objectness
    pa.field("theta_shape", pa.float64()),  # log-odds from the 3D extent (objects are compact and of bounded size)
    pa.field("theta_class", pa.float64()),  # log-odds from the classifier's mass on the 80 known classes
    pa.field("score_motion", pa.float64(), False),  # REFERENCE's motion LLR Σ ln(x·score.motion_k): part of score only under reference
    pa.field("score_mask", pa.float64(), False),  # REFERENCE's mask LLR Σ ln(IoU·score.mask_k): part of score only under reference
    pa.field("score_objectness", pa.float64(), False),  # REFERENCE's objectness LLR Σ ln(o·score.objectness_k): part of score only under reference
    pa.field("selected", pa.bool_(), False),  # chosen by co-selection
    # The call (mining/score/call.py, one rule): known, unknown, clutter (unknown wins but the object gate says not an
    # object) or unclassified (no classifier looked: classified_frames = 0). Rows written before issue 39 have no
    # call (null); their known was also null where classifier evidence was below score.min_class_evidence or the gate
    # withdrew the call.
    pa.field("call", pa.string()),  # known | unknown | clutter | unclassified (null: written before the column)
    pa.field("object_prob", pa.float32()),  # P(object) of the object gate for a tube unknown wins; below score.unknown_min_object it is clutter (null: not judged)
    pa.field("known", pa.bool_()),  # true: a COCO class wins the posterior; false: unknown wins (call unknown or clutter); null: unclassified
    pa.field("category", pa.string()),  # COCO class, "unknown", or null (unclassified)
    pa.field("category_prob", pa.float32()),  # posterior mass of category; null when unclassified
    pa.field("best_known", pa.string()),  # most probable of the 80 classes, even when unknown; null when unclassified
    pa.field("class_posterior", pa.list_(pa.float32())),  # 81 floats (80 COCO + unknown), evidence-weighted mean; null when unclassified
    pa.field("classified_frames", pa.int32(), False),  # observed frames where a classifier looked
    pa.field("class_evidence", pa.float32(), False),  # Σ of those frames' evidence weights (frame-equivalents)
    pa.field("segment", pa.int32(), False),  # egomotion segment: world coordinates are per segment
    pa.field("mean_position", vec3, False),  # world metres, mean footpoint
    pa.field("size", vec3, False),  # metres (width, height, length), median over observed frames
    pa.field("path_length", pa.float32(), False),  # metres, net ground displacement of a line fitted to the observed footpoints over time
    pa.field("speed", pa.float32(), False),  # m/s, slope of that line (ground plane); noise-level for static objects: read moving_speed_mps
    pa.field("speed_sigma_mps", pa.float32()),  # m/s, σ of speed: the fit residuals, floored by stereo depth noise Z²/(f·B)·σ_d (rows.DISPARITY_SIGMA_PX); null under 3 observations
    pa.field("path_sigma_m", pa.float32()),  # metres, σ of path_length (speed_sigma_mps × duration); null under 3 observations
    pa.field("moving_speed_mps", pa.float32()),  # m/s, speed where it exceeds 3 σ (rows.MOTION_K_SIGMA); null: static or not measurable
    pa.field("n_windows", pa.int16(), False),  # how many window pieces were stitched into it
    pa.field("run_id", pa.string(), False),
    pa.field("params_hash", pa.string(), False),
    pa.field("schema_version", pa.int16(), False),
])

TUBE_FRAMES = pa.schema([
    pa.field("tube_id", pa.string(), False),
    pa.field("dataset", pa.string(), False),
    pa.field("sequence", pa.string(), False),
    pa.field("frame", pa.int32(), False),  # the source's frame index
    pa.field("t_ns", pa.int64(), False),
    pa.field("bbox", box4, False),  # x1, y1, x2, y2 pixels
    pa.field("rle_counts", pa.string(), False),  # COCO compressed RLE
    pa.field("rle_h", pa.int32(), False),
    pa.field("rle_w", pa.int32(), False),
    pa.field("observed", pa.bool_(), False),  # an observation, or the tube's prediction in a gap
    pa.field("obs_index", pa.int32(), False),  # row in the frame's proposals; -1 when predicted
    pa.field("objectness", pa.float32()),  # null when predicted
    pa.field("position_cam", vec3, False),  # camera metres (x right, y down, z forward)
    pa.field("position_world", vec3, False),  # filtered footpoint, world metres of the tube's segment
    pa.field("velocity_world", vec3, False),  # m/s, world frame
    pa.field("size", vec3, False),  # filtered width, height, length
    pa.field("mask_iou", pa.float32()),  # IoU(predicted mask, observed mask); null for the first inlier and gaps
    pa.field("motion_density", pa.float32()),  # density of the observed footpoint under the prediction
])

FRAMES = pa.schema([
    pa.field("dataset", pa.string(), False),
    pa.field("sequence", pa.string(), False),
    pa.field("frame", pa.int32(), False),  # the source's frame index
    pa.field("position", pa.int32(), False),  # position in the sequence plan (windows count positions)
    pa.field("t_ns", pa.int64(), False),
    pa.field("segment", pa.int32(), False),  # increments after every failed egomotion
    pa.field("pose", pa.list_(pa.float64(), 16), False),  # camera-to-world of the segment, row-major 4×4
    pa.field("egomotion_ok", pa.bool_()),  # null for a sequence's first frame (no previous frame)
    pa.field("egomotion_inliers", pa.int32(), False),
    pa.field("egomotion_rmse_px", pa.float32()),
    pa.field("ground_ok", pa.bool_(), False),  # measured in this frame
    pa.field("ground_age", pa.int32()),  # frames since the plane used was measured; null: none
    pa.field("n_proposals", pa.int32(), False),
    pa.field("n_observations", pa.int32(), False),  # after localisation and the geometric filter
])

WINDOWS = pa.schema([
    pa.field("run_id", pa.string(), False),
    pa.field("dataset", pa.string(), False),
    pa.field("sequence", pa.string(), False),
    pa.field("window", pa.string(), False),  # Window.name
    pa.field("core_start", pa.int32(), False),
    pa.field("core_end", pa.int32(), False),
    pa.field("context_start", pa.int32(), False),
    pa.field("context_end", pa.int32(), False),
    pa.field("status", pa.string(), False),  # done | failed
    pa.field("attempts", pa.int32(), False),
    pa.field("started", pa.timestamp("ms", tz="UTC")),
    pa.field("finished", pa.timestamp("ms", tz="UTC")),
    pa.field("seconds_observe", pa.float32()),  # geometry + proposals + localise
    pa.field("seconds_tubes", pa.float32()),  # tubes + score + select
    pa.field("n_pieces", pa.int32()),  # tube pieces the window wrote
    pa.field("context_complete", pa.bool_()),  # every neighbour's frames were there when it was tracked
    pa.field("error", pa.string()),  # the InputError text for a failed window
    pa.field("params_hash", pa.string(), False),
])

SCHEMAS = {"tubes": TUBES, "tube_frames": TUBE_FRAMES, "frames": FRAMES, "windows": WINDOWS}

# Columns only the per-window parts carry (dropped when a sequence is stitched).
PART_EXTRA = {
    "tubes": [pa.field("window", pa.string(), False)],
    "tube_frames": [
        pa.field("window", pa.string(), False),
        pa.field("core", pa.bool_(), False),  # the frame is in the window's core (the window owns it)
        pa.field("posterior", pa.list_(pa.float32())),  # the observation's 81-way posterior
        pa.field("class_weight", pa.float32(), False),  # how much it counts (Proposals.class_weights)
        pa.field("footpoint_cam", vec3, False),  # filtered footpoint in this frame's camera (worlds differ per window)
        pa.field("velocity_cam", vec3, False),  # filtered velocity in this frame's camera
    ],
    "frames": [
        pa.field("T_cur_prev", pa.list_(pa.float64())),  # 16 floats (variable-size: null fixed-size lists do not round-trip Parquet); egomotion from the previous frame; null when failed or absent
    ],
    "windows": [],
}


# Units of the columns that have one, by column name, in every table (a new column with a unit: one entry).
UNITS = {
    "t_start": "ns", "t_end": "ns", "t_ns": "ns",
    "mean_position": "m", "size": "m", "path_length": "m", "speed": "m/s",
    "position_cam": "m", "position_world": "m", "velocity_world": "m/s",
    "footpoint_cam": "m", "velocity_cam": "m/s",
    "bbox": "px", "rle_h": "px", "rle_w": "px", "egomotion_rmse_px": "px",
    "class_evidence": "frame-equivalents", "seconds_observe": "s", "seconds_tubes": "s",
}
DESCRIPTION_KEY, UNIT_KEY = b"description", b"unit"  # ours: the Parquet / Arrow field metadata keys
_VARS = {"tubes": "TUBES", "tube_frames": "TUBE_FRAMES", "frames": "FRAMES", "windows": "WINDOWS"}


@functools.cache
def field_comments() -> dict[str, dict[str, str]]:
    """``{schema variable: {field name: trailing comment}}`` read from this file's source: the
    comments are the columns' descriptions (one source for schemas/, Parquet and DuckDB)."""
    source = Path(__file__).read_text()
    lines = source.splitlines()
    out: dict[str, dict[str, str]] = {}
    for node in ast.walk(ast.parse(source)):
        if not (isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name)):
            continue
        for call in ast.walk(node.value):
            if (isinstance(call, ast.Call) and getattr(call.func, "attr", "") == "field" and call.args
                    and isinstance(call.args[0], ast.Constant)):
                line = lines[call.end_lineno - 1]
                out.setdefault(node.targets[0].id, {})[call.args[0].value] = line.split("#", 1)[1].strip() if "#" in line else ""
    return out


def column_doc(table: str, name: str) -> tuple[str, str]:
    """A column's description and unit ("" where none)."""
    c = field_comments()
    desc = c.get(_VARS[table], {}).get(name) or c.get("PART_EXTRA", {}).get(name, "")
    return desc, UNITS.get(name, "")


def documented(table: str, f: pa.Field) -> pa.Field:
    """``f`` with its description and unit as field metadata (written into every Parquet file)."""
    desc, unit = column_doc(table, f.name)
    md = {k: v.encode() for k, v in ((DESCRIPTION_KEY, desc), (UNIT_KEY, unit)) if v}
    return f.with_metadata(md) if md else f


def file_schema(table: str) -> pa.Schema:
    """The schema of a compacted catalogue file (v3): every column of the table, ``dataset`` and
    ``sequence`` included, so a reader needs no folder name to know them."""
    return pa.schema([documented(table, f) for f in SCHEMAS[table]])


def hive_file_schema(table: str) -> pa.Schema:
    """The schema of a file whose hive folder names hold ``dataset`` / ``sequence`` (left out of
    the file): a manifest row, and a compacted file of a catalogue before v3."""
    return pa.schema([documented(table, f) for f in SCHEMAS[table] if f.name not in PARTITION])


def part_schema(table: str) -> pa.Schema:
    """The schema of a per-window part (hive folders: partition columns left out, part-only columns added)."""
    return pa.schema(list(hive_file_schema(table)) + [documented(table, f) for f in PART_EXTRA[table]])


def partitioning() -> "pyarrow.dataset.Partitioning":  # noqa: F821
    """The hive partitioning of the working folders (manifest, parts) and of a catalogue before v3,
    with ``dataset`` / ``sequence`` as strings: without it pandas, pyarrow and polars infer
    ``sequence=0005`` as the integer 5 (pass it as ``partitioning=``). A v3 catalogue's tables need
    none: their files hold both columns, as strings."""
    import pyarrow.dataset as ds

    return ds.partitioning(pa.schema([pa.field(n, pa.string()) for n in PARTITION]), flavor="hive")
