"""Mined tubes against the synthetic source's exact ground truth, for known and unknown objects.

The synthetic renderer knows every object's visible mask, track id and whether one of the
80 COCO classes covers its category (``ObjectTruth.known``). The miner, however, is
class-agnostic where it matters (the stereo proposer has no classes), so matching is too:
a tube may match any ground-truth object. The protocol, per frame:

1. **Tracker detections.** Each frame of a *selected* tube is a detection with the tube's id
   (observed frames; predicted gap frames too with ``predicted=True``). Similarity is mask
   IoU (``similarity="box"``: box IoU). Tube frames outside the evaluated frames are dropped.
2. **Ignored ground truth.** An object with fewer than ``min_visible_px`` visible pixels (or,
   optionally, a centre deeper than ``max_depth_m``) is *ignored*: never a FN.
3. **Joint matching.** All detections and all ground truth of the frame (ignored included)
   are matched one-to-one by the Hungarian algorithm, maximal total IoU over pairs with
   IoU ≥ ``iou_threshold``. A detection matched to ignored ground truth is removed from
   every evaluation (neither TP nor FP), as KITTI does with DontCare and truncated objects.
4. **A tube's split.** Each tube belongs to the split (known / unknown) of the ground truth
   it was matched to in step 3, weighted by IoU over its frames (ties go to known). A tube
   never matched to evaluated ground truth is *clutter* (background, and duplicates that
   always lost the one-to-one matching to another tube).
5. **Three evaluations.** ``all``: every evaluated object, every detection left after step 3
   (clutter's detections are FPs here, and only here). ``known`` (``unknown``): the objects of
   that split, the detections of the split's tubes, except those matched in step 3 to an
   object of the other split, which are removed (KITTI's neighbour-class rule). Thus a split's
   FPs are the frames where one of its tubes drifted off every object, and its FNs the
   frames where none of its objects is covered.

Each evaluation is scored by ``hota.py`` (HOTA, DetA, AssA over α = 0.05 … 0.95, with its own
matching), ``clear.py`` (MOTA, IDSW, …; a match needs IoU ≥ ``iou_threshold``) and
``identity.py`` (IDF1), with ground-truth ``track_id`` and tube id as the identities.

**Tube recall** (per evaluation): the share of ground-truth tracks, counting only their
evaluated frames, that one single tube covers with IoU ≥ ``iou_threshold`` in at least
``track_cover`` of those frames. **Frame recall**: the share of evaluated ground-truth
detections that some tube detection overlaps with IoU ≥ ``iou_threshold``. Both use that
evaluation's detections (step 5) but not the one-to-one matching: they ask "was this object
mined?", not "how well was it tracked?".

**Discovery** (``discovery.py``): each unknown-split tube's true kind (``tube_kinds``: the
unknown category it collected the most IoU on in step 3) is the truth the descriptors, groups
and propagated labels are scored against.

Run it: ``mine eval synthetic --sequence 0000 --n-frames 500 [--set KEY=VALUE ...]`` (the
driver, which mines the sequence, is ``mining/bench/synthetic.py``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from mining.errors import InputError
from mining.eval.clear import clear_metrics, clear_sums
from mining.eval.hota import hota_metrics, hota_sums
from mining.eval.identity import identity_metrics, identity_sums
from mining.boxes import box_iou
from mining.masks import areas, crop_rle, mask_iou
from mining.types import CALLS, FrameTruth, MinedTube

SPLITS = ("all", "known", "unknown")
_EPS = np.finfo(float).eps


@dataclass(frozen=True)
class SyntheticEvalProtocol:
    """The constants of the synthetic evaluation (see the module docstring)."""

    min_visible_px: int = 100  # ours, after REFERENCE: proposals under 100 px² are dropped, so smaller objects are ignored
    iou_threshold: float = 0.5  # REFERENCE (KITTI MOT): a match needs IoU ≥ 0.5
    similarity: str = "mask"  # ours: "mask" IoU (the tubes are masks) or "box" IoU
    max_depth_m: float | None = None  # ours: ignore objects centred deeper (None: keep all); REFERENCE: proposals need Z < 60 m
    predicted: bool = False  # ours: observed tube frames only, as the tracking export (ExportConfig.observed_only)
    track_cover: float = 0.5  # ours: a track is recalled when one tube covers at least half its evaluated frames


@dataclass
class GtFrame:
    """One frame's ground truth, compact: masks as COCO RLEs (a FrameTruth holds full frames)."""

    track_ids: np.ndarray  # (N,) int64
    known: np.ndarray  # (N,) bool
    categories: list[str]
    rles: list[dict]
    areas: np.ndarray  # (N,) visible pixels
    boxes: np.ndarray  # (N, 4) x1, y1, x2, y2
    depth: np.ndarray  # (N,) z of the object centre, camera metres
    size: tuple[int, int]  # image height, width


def gt_frame(truth: FrameTruth | GtFrame) -> GtFrame:
    """Encode a FrameTruth's masks as RLEs; a GtFrame passes through."""
    if isinstance(truth, GtFrame):
        return truth
    objs = truth.objects
    h, w = truth.depth.shape
    rles = []
    for o in objs:
        if o.mask.shape != (h, w):
            raise InputError(f"ground-truth mask of track {o.track_id} is {o.mask.shape}, the frame is {(h, w)}")
        # encode only the box: a full-frame encode per object costs ~25 ms
        x0, y0, x1, y1 = (int(v) for v in o.box)
        rles.append(crop_rle(o.mask[y0:y1, x0:x1], x0, y0, h, w))
    return GtFrame(
        track_ids=np.array([o.track_id for o in objs], np.int64),
        known=np.array([o.known for o in objs], bool),
        categories=[o.category for o in objs],
        rles=rles,
        areas=areas(rles),
        boxes=np.array([o.box for o in objs], np.float64).reshape(-1, 4),
        depth=np.array([o.center_cam[2] for o in objs], np.float64),
        size=(h, w),
    )


@dataclass
class _Frame:
    """One evaluated frame after the joint matching."""

    gt: GtFrame
    evaluated: np.ndarray  # (N,) bool: not ignored
    det_tubes: np.ndarray  # (M,) tube ids
    similarity: np.ndarray  # (N, M) IoU
    det_match: np.ndarray  # (M,) gt row each detection was matched to in step 3, −1 if none


def _detections(tubes: Sequence[MinedTube], frames: set[int], predicted: bool) -> dict[int, list]:
    """frame → [(tube id, rle, box)] of the tubes' frames inside ``frames``."""
    out: dict[int, list] = {}
    for m in tubes:
        seen = set()
        for f in m.tube.frames:
            if f.frame in seen:
                raise InputError(f"tube {m.tube.tube_id} has two entries in one frame", frame=f.frame)
            seen.add(f.frame)
            if f.frame in frames and (f.observed or predicted):
                out.setdefault(f.frame, []).append((m.tube.tube_id, f.rle, np.asarray(f.box, np.float64)))
    return out


def _joint_match(s: np.ndarray, threshold: float) -> np.ndarray:
    """Step 3: for each detection, the gt row it is matched to (−1: none)."""
    match = np.full(s.shape[1], -1)
    if s.size == 0:
        return match
    score = np.where(s >= threshold - _EPS, s, 0.0)
    rows, cols = linear_sum_assignment(score, maximize=True)
    ok = score[rows, cols] > 0
    match[cols[ok]] = rows[ok]
    return match


def _prepare(tubes: Sequence[MinedTube], truths: Mapping[int, FrameTruth | GtFrame],
             p: SyntheticEvalProtocol) -> list[_Frame]:
    dets = _detections(tubes, set(truths), p.predicted)
    out = []
    for t in sorted(truths):
        gt = gt_frame(truths[t])
        d = dets.get(t, [])
        for tid, rle, _ in d:
            if list(rle["size"]) != list(gt.size):
                raise InputError(f"tube {tid} mask is {rle['size']}, the ground truth is {list(gt.size)}", frame=t)
        if p.similarity == "mask":
            s = mask_iou(gt.rles, [x[1] for x in d])
        else:
            s = box_iou(gt.boxes, np.array([x[2] for x in d]).reshape(-1, 4))
        evaluated = gt.areas >= p.min_visible_px
        if p.max_depth_m is not None:
            evaluated &= gt.depth <= p.max_depth_m
        out.append(_Frame(gt, evaluated, np.array([x[0] for x in d], np.int64), s, _joint_match(s, p.iou_threshold)))
    return out


def _of_match(values: np.ndarray, match: np.ndarray) -> np.ndarray:
    """``values`` of each detection's matched gt row; unmatched rows (−1) get any value, so
    callers mask with ``match >= 0`` (a frame without ground truth has no row to index)."""
    if len(values) == 0:
        return np.zeros(len(match), values.dtype)
    return values[np.maximum(match, 0)]


def _tube_splits(frames: list[_Frame]) -> dict[int, str]:
    """Step 4: each matched tube's split, by the IoU it collected on known / unknown objects."""
    weight: dict[int, np.ndarray] = {}
    for f in frames:
        for j, g in enumerate(f.det_match):
            if g >= 0 and f.evaluated[g]:
                w = weight.setdefault(int(f.det_tubes[j]), np.zeros(2))
                w[0 if f.gt.known[g] else 1] += f.similarity[g, j]
    return {tid: ("known" if w[0] >= w[1] else "unknown") for tid, w in weight.items()}


def tube_kinds(frames: list[_Frame], tube_split: Mapping[int, str]) -> dict[int, str]:
    """Each unknown-split tube's true kind: the category of the evaluated unknown objects it was
    matched to in step 3, the one it collected the most IoU on (ties: the first name in sort order)."""
    weight: dict[int, dict[str, float]] = {}
    for f in frames:
        for j, g in enumerate(f.det_match):
            tid = int(f.det_tubes[j])
            if g >= 0 and f.evaluated[g] and not f.gt.known[g] and tube_split.get(tid) == "unknown":
                w = weight.setdefault(tid, {})
                w[f.gt.categories[g]] = w.get(f.gt.categories[g], 0.0) + float(f.similarity[g, j])
    return {tid: min(w, key=lambda k: (-w[k], k)) for tid, w in weight.items()}


def _contiguous(ids: list[np.ndarray]) -> list[np.ndarray]:
    """Arbitrary ids → 0-based contiguous ids, the same mapping over all frames."""
    uniq = np.unique(np.concatenate(ids)) if ids else np.zeros(0, np.int64)
    return [np.searchsorted(uniq, x).astype(np.int64) for x in ids]


def _split_inputs(frames: list[_Frame], split: str, tube_split: dict[int, str]):
    """Per-frame gt ids, tracker ids and similarity of one evaluation (step 5)."""
    gt_ids, tr_ids, sims = [], [], []
    for f in frames:
        g_keep = f.evaluated.copy()
        if split != "all":
            g_keep &= f.gt.known == (split == "known")
        matched = f.det_match >= 0
        # rule 3: detections matched to ignored gt are removed everywhere
        d_keep = ~(matched & ~_of_match(f.evaluated, f.det_match))
        if split != "all":
            own = np.array([tube_split.get(int(t)) == split for t in f.det_tubes], bool)
            other = matched & (_of_match(f.gt.known, f.det_match) != (split == "known"))
            d_keep &= own & ~other
        gt_ids.append(f.gt.track_ids[g_keep])
        tr_ids.append(f.det_tubes[d_keep])
        sims.append(f.similarity[np.ix_(g_keep, d_keep)])
    return gt_ids, tr_ids, sims


def _recall(gt_ids: list[np.ndarray], tr_ids: list[np.ndarray], sims: list[np.ndarray],
            threshold: float, cover: float) -> dict:
    """Tube recall and frame recall (see the module docstring)."""
    hits: dict[tuple[int, int], int] = {}
    visible: dict[int, int] = {}
    n_det = n_hit = 0
    for g, p, s in zip(gt_ids, tr_ids, sims):
        ok = s >= threshold - _EPS
        n_det += len(g)
        n_hit += int(ok.any(axis=1).sum()) if s.size else 0
        for gid in g:
            visible[int(gid)] = visible.get(int(gid), 0) + 1
        for r, c in zip(*np.nonzero(ok)):
            key = (int(g[r]), int(p[c]))
            hits[key] = hits.get(key, 0) + 1
    best: dict[int, int] = {}
    for (gid, _), n in hits.items():
        best[gid] = max(best.get(gid, 0), n)
    covered = sum(1 for gid, n in visible.items() if best.get(gid, 0) >= cover * n - 1e-9)
    return {
        "tube_recall": covered / len(visible) if visible else float("nan"),
        "tracks": len(visible),
        "tracks_covered": covered,
        "frame_recall": n_hit / n_det if n_det else float("nan"),
    }


def _score(gt_ids, tr_ids, sims, threshold: float) -> dict:
    g, p = _contiguous(gt_ids), _contiguous(tr_ids)
    out = {}
    out.update(hota_metrics(hota_sums(g, p, sims)))
    out.update(clear_metrics(clear_sums(g, p, sims, threshold)))
    out.update(identity_metrics(identity_sums(g, p, sims, threshold)))
    out["gt_dets"] = int(sum(len(x) for x in gt_ids))
    out["tracker_dets"] = int(sum(len(x) for x in tr_ids))
    out["tracker_ids"] = int(len(np.unique(np.concatenate(tr_ids)))) if tr_ids else 0
    return out


def evaluate_synthetic(mined: Sequence[MinedTube], truths: Mapping[int, FrameTruth | GtFrame],
                       min_visible_px: int = SyntheticEvalProtocol.min_visible_px,
                       iou_threshold: float = SyntheticEvalProtocol.iou_threshold,
                       similarity: str = SyntheticEvalProtocol.similarity,
                       max_depth_m: float | None = SyntheticEvalProtocol.max_depth_m,
                       predicted: bool = SyntheticEvalProtocol.predicted,
                       track_cover: float = SyntheticEvalProtocol.track_cover,
                       selected_only: bool = True) -> dict:
    """Metrics of the selected tubes over the frames in ``truths`` (frame index → truth).

    Returns ``{"all" | "known" | "unknown": {metric: value}, "tubes": {...}, "frames": n,
    "protocol": {...}}``; each split holds HOTA, DetA, AssA, MOTA, IDSW, IDF1, TP, FP, FN
    (and the rest of the three metric families), tube and frame recall. ``selected_only=False``
    scores every candidate tube (diagnostic: what selection loses).
    """
    if similarity not in ("mask", "box"):
        raise InputError(f"similarity must be 'mask' or 'box', got {similarity!r}")
    if not truths:
        raise InputError("no ground-truth frames to evaluate")
    missing = [t for t, x in truths.items() if x is None]
    if missing:
        raise InputError("frame has no ground truth (not a synthetic source?)", frame=missing[0])
    p = SyntheticEvalProtocol(min_visible_px, iou_threshold, similarity, max_depth_m, predicted, track_cover)
    tubes = [m for m in mined if m.selected or not selected_only]
    ids = [m.tube.tube_id for m in tubes]
    if len(set(ids)) != len(ids):
        raise InputError("tube ids must be unique: they are the tracker identities")
    frames = _prepare(tubes, truths, p)
    tube_split = _tube_splits(frames)
    results: dict = {"frames": len(frames), "protocol": asdict(p) | {"selected_only": selected_only}}
    for split in SPLITS:
        gt_ids, tr_ids, sims = _split_inputs(frames, split, tube_split)
        results[split] = _score(gt_ids, tr_ids, sims, iou_threshold) | _recall(gt_ids, tr_ids, sims, iou_threshold,
                                                                             track_cover)
    ignored = sum(int(np.sum((f.det_match >= 0) & ~_of_match(f.evaluated, f.det_match))) for f in frames)
    results["tubes"] = {
        "evaluated": len(tubes),
        "known": sum(1 for s in tube_split.values() if s == "known"),
        "unknown": sum(1 for s in tube_split.values() if s == "unknown"),
        "clutter": len({m.tube.tube_id for m in tubes} - set(tube_split)),
        "ignored_dets": ignored,
    }
    results["tube_split"] = {m.tube.tube_id: tube_split.get(m.tube.tube_id, "clutter") for m in tubes}
    results["tube_kind"] = tube_kinds(frames, tube_split)  # the unknown tubes' true kinds (discovery's truth)
    # how the miner's own call (TubeCategory.call, one of CALLS: mining.score.call) agrees with the split
    t = results["tubes"]
    for split in ("known", "unknown"):
        on = [m for m in tubes if tube_split.get(m.tube.tube_id) == split]
        for call in CALLS:
            t[f"{split}_called_{call}"] = sum(1 for m in on if m.category.call == call)
        t[f"{split}_called_{split}_share"] = t[f"{split}_called_{split}"] / len(on) if on else float("nan")
    t["clutter_share"] = t["clutter"] / len(tubes) if tubes else float("nan")
    t["clutter_called"] = {call: sum(1 for m in tubes if m.tube.tube_id not in tube_split and m.category.call == call)
                           for call in CALLS}
    # the unknown set (issue 29): what a researcher who exports the tubes called unknown finds in them
    t |= unknown_set(tubes, tube_split)
    return results


def unknown_set(tubes: Sequence[MinedTube], tube_split: Mapping[int, str]) -> dict:
    """The selected tubes called unknown by what they are: ``called_unknown`` (n),
    ``called_unknown_on`` ({"unknown", "known", "clutter"}: n; clutter = not matched to an
    evaluated object) and ``unknown_set_precision`` (the share on unknown objects; NaN when
    none is called unknown)."""
    on = {"unknown": 0, "known": 0, "clutter": 0}
    for m in tubes:
        if m.category.call == "unknown":
            on[tube_split.get(m.tube.tube_id, "clutter")] += 1
    n = sum(on.values())
    return {"called_unknown": n, "called_unknown_on": on,
            "unknown_set_precision": on["unknown"] / n if n else float("nan")}


def format_synthetic(results: dict) -> str:
    """A small text table: one row per evaluation, then the tube counts."""
    cols = [("HOTA", "HOTA", "{:.3f}"), ("DetA", "DetA", "{:.3f}"), ("AssA", "AssA", "{:.3f}"),
            ("MOTA", "MOTA", "{:.3f}"), ("IDSW", "IDSW", "{:d}"), ("IDF1", "IDF1", "{:.3f}"), ("TP", "TP", "{:d}"),
            ("FP", "FP", "{:d}"), ("FN", "FN", "{:d}"), ("frame_recall", "frameR", "{:.3f}"),
            ("tube_recall", "tubeR", "{:.3f}"), ("tracks", "tracks", "{:d}")]
    head = ["split"] + [label for _, label, _ in cols]
    rows = [head] + [[split] + [fmt.format(results[split][key]) for key, _, fmt in cols] for split in SPLITS]
    widths = [max(len(row[i]) for row in rows) for i in range(len(head))]
    lines = ["  ".join(x.rjust(w) for x, w in zip(row, widths)) for row in rows]
    t = results.get("tubes", {})
    lines.append(f"{results['frames']} frames; tubes: {t.get('evaluated')} evaluated, {t.get('known')} on known objects "
                 f"({t.get('known_called_known')} called known), {t.get('unknown')} on unknown objects "
                 f"({t.get('unknown_called_unknown')} called unknown), {t.get('clutter')} clutter; "
                 f"{t.get('ignored_dets')} detections on ignored objects")

    def pct(x):
        return "—" if x != x else f"{100 * x:.0f} %"
    if "known_called_unclassified" in t:
        lines.append(f"the miner's call per object kind ({' / '.join(CALLS)}):")
        for kind, n in (("known", t["known"]), ("unknown", t["unknown"]), ("clutter", t["clutter"])):
            c = t["clutter_called"] if kind == "clutter" else {k: t[f"{kind}_called_{k}"] for k in CALLS}
            share = t["clutter_share"] if kind == "clutter" else t[f"{kind}_called_{kind}_share"]
            what = "of the evaluated tubes" if kind == "clutter" else f"called {kind}"
            lines.append(f"  on {kind + ' objects' if kind != 'clutter' else 'nothing (clutter)'}: {n} tubes → "
                         f"{' / '.join(str(c[k]) for k in CALLS)}; {pct(share)} {what}")
    if "called_unknown_on" in t:
        on = t["called_unknown_on"]
        lines.append(f"the unknown set: {t['called_unknown']} tubes called unknown, {on['unknown']} on unknown objects "
                     f"(precision {pct(t['unknown_set_precision'])}), {on['known']} on known objects, "
                     f"{on['clutter']} clutter")
    return "\n".join(lines)
