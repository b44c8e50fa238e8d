"""The recall funnel: at which stage of the pipeline each ground-truth object is lost.

Every evaluated ground-truth detection is followed through the pipeline's stages, each a
set of masks in its frame; a stage *covers* the detection when one of its masks overlaps it
with IoU ≥ ``iou_threshold`` (mask IoU; ``similarity="box"``: box IoU). The stages, in
pipeline order:

1. **Proposal stages**, given per frame by the caller (``stages``). ``mine eval synthetic``
   gives two: ``proposed``, the proposer's output, and ``observed``, the observations that
   passed localisation and the geometric filter (the tube generator's input).
2. **candidate**: the observed frames of every candidate tube the generator kept (after tube
   NMS), selected or not. Predicted gap frames do not count: they are not proposals.
3. **selected**: the observed frames of the tubes co-selection chose.

No stage is matched one-to-one: the funnel asks "was there a mask on this object?", not "how
well was it tracked?". The stages nest in the pipeline (a tube's observed mask is an
observation's, an observation is a proposal), so recall can only fall along the funnel: a
drop between ``observed`` and ``candidate`` is tracking and association (a tube never formed,
or tube NMS dropped it), between ``candidate`` and ``selected`` scoring and co-selection.

**Ignored ground truth** follows the synthetic protocol (``synthetic.py``): an object with
fewer than ``min_visible_px`` visible pixels, or centred deeper than ``max_depth_m``, is not
evaluated. Evaluated detections are counted per split (``all``, ``known``, ``unknown``), per
distance bin (z of the object centre, camera metres) and per height bin (the visible box's
height, pixels), and in the cross of both bins.

**Track level.** A ground-truth track counts its evaluated frames only. A proposal stage
covers it when it covers at least ``track_cover`` of those frames (proposals have no
identity); the tube stages when *one* tube covers at least that share, the synthetic
protocol's tube-recall rule.

**Carried by.** Each selected tube that never covers an evaluated object (IoU ≥
``iou_threshold`` in none of its observed, evaluated frames) is explained frame by frame:
*on an ignored object* (IoU ≥ ``iou_threshold`` with an ignored one), else *part* of a
ground-truth object (intersection over the tube mask's own area, IoA, ≥ ``part_ioa``; the
object with the largest IoA), else part of another selected tube (IoA ≥ ``part_ioa`` with its
mask), else *clutter*. The tube takes its most frequent explanation. For each part and
clutter tube the report gives its unary score's three terms as weighted into the total
(``mining/score/unary.py``: β·α·motion, β·(1−α)·mask, (1−β)·objectness, with the run's α
and β) and the term that contributed most (*carried by*): the evidence co-selection
believed.

**Calls** (with the synthetic protocol's tube split). Each selected tube on a known object is
placed in the distance and height bins of the evaluated known objects it covers (the median
over its frames) and counted by the miner's call: known, unknown (a *known object called
unknown*), clutter or unclassified. Of the part and clutter tubes above, those called unknown are
counted by the term that carried them: the evidence that put them into the unknown set.

Run it: ``mine eval synthetic …`` prints it after the synthetic metrics (masks; driver
``mining/bench/synthetic.py``); ``mine eval recall --sequence S --funnel`` on KITTI labels
(boxes, a label's depth the z of its 3D location; driver ``mining/bench/funnel.py``).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from mining.boxes import box_ioa, box_iou
from mining.errors import InputError
from mining.eval.synthetic import GtFrame, SyntheticEvalProtocol
from mining.masks import mask_ioa, mask_iou
from mining.types import CALLS, MinedTube

SPLITS = ("all", "known", "unknown")
TUBE_STAGES = ("candidate", "selected")
TERMS = ("motion", "mask", "objectness")
_EPS = np.finfo(float).eps


@dataclass(frozen=True)
class FunnelProtocol:
    """The constants of the recall funnel (see the module docstring)."""

    iou_threshold: float = SyntheticEvalProtocol.iou_threshold  # issue 18: covered = a mask with IoU ≥ 0.5
    similarity: str = SyntheticEvalProtocol.similarity  # "mask" IoU, or "box" (labels without masks)
    min_visible_px: int = SyntheticEvalProtocol.min_visible_px  # the synthetic protocol's ignore rule: same objects
    max_depth_m: float | None = SyntheticEvalProtocol.max_depth_m  # likewise
    track_cover: float = SyntheticEvalProtocol.track_cover  # the synthetic protocol's tube-recall rule
    part_ioa: float = 0.5  # issue 18: a part lies at least half inside the object (IoA over the tube's own mask)
    distance_edges_m: tuple[float, ...] = (0.0, 20.0, 40.0, 60.0, float("inf"))  # issue 18: 0–20–40–60 m, beyond
    # ours: 25 px is KITTI's smallest evaluated box height, then octaves (a 1.5 m tall car: 25 / 50 / 100 px at
    # ≈ 43 / 22 / 11 m, f = 721 px)
    height_edges_px: tuple[float, ...] = (0.0, 25.0, 50.0, 100.0, float("inf"))


@dataclass
class StageFrame:
    """One frame's masks at one proposal stage, compact: a Proposals' RLEs and boxes."""

    rles: list[dict]
    boxes: np.ndarray  # (N, 4) x1, y1, x2, y2


def stage_frame(proposals) -> StageFrame:
    """The RLEs and boxes of anything that has them (Proposals, an Observations' proposals)."""
    return StageFrame(list(proposals.rles), np.asarray(proposals.boxes, np.float64).reshape(-1, 4))


def bin_names(edges: Sequence[float], unit: str) -> list[str]:
    """"0–20 m", …, ">60 m" for edges (0, 20, …, 60, inf)."""
    def num(x: float) -> str:
        return f"{x:g}"
    names = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        names.append(f">{num(lo)} {unit}" if np.isinf(hi) else f"{num(lo)}–{num(hi)} {unit}")
    return names


def _bin(values: np.ndarray, edges: Sequence[float]) -> np.ndarray:
    """Bin index of each value in [edges[k], edges[k+1]); values outside go to the end bins."""
    k = np.searchsorted(np.asarray(edges, np.float64), values, side="right") - 1
    return np.clip(k, 0, len(edges) - 2)


def _similarity(p: FunnelProtocol, gt_rles, gt_boxes, rles, boxes, ioa: bool = False) -> np.ndarray:
    """(len(a), len(b)) IoU, or intersection over each row's own area when ``ioa``."""
    if p.similarity == "mask":
        return (mask_ioa if ioa else mask_iou)(list(gt_rles), list(rles))
    a, b = np.asarray(gt_boxes, np.float64).reshape(-1, 4), np.asarray(boxes, np.float64).reshape(-1, 4)
    return box_ioa(a, b) if ioa else box_iou(a, b)


def _rates(row: np.ndarray, stages: Sequence[str]) -> dict:
    """{"gt": n, stage: covered, …, "recall": {stage: share}} from a (1 + stages) count row."""
    n = int(row[0])
    out: dict = {"gt": n}
    out |= {s: int(row[1 + i]) for i, s in enumerate(stages)}
    out["recall"] = {s: (float(row[1 + i]) / n if n else float("nan")) for i, s in enumerate(stages)}
    return out


def weighted_terms(m: MinedTube, alpha: float, beta: float, groups: Sequence[str] | None = None) -> dict[str, float]:
    """The score's terms as they enter the total (``mining/score/unary.py``); with ``groups`` (the
    calibrated unary's groups of terms, ``mining.score.calibrated.GROUPS``), the split of its total
    the score recorded (``TubeScore.terms``)."""
    if groups is not None:
        if m.score.terms is None:
            raise InputError(f"tube {m.tube.tube_id}: its score has no groups of terms (not the calibrated unary's)")
        return {g: float(m.score.terms[g]) for g in groups}
    return {"motion": float(beta * alpha * m.score.motion), "mask": float(beta * (1 - alpha) * m.score.mask),
            "objectness": float((1 - beta) * m.score.objectness)}


def carried_by(terms: Mapping[str, float]) -> str:
    """The term that contributed most to the total; "none" when no term is positive."""
    best = max(terms, key=lambda k: terms[k])
    return best if terms[best] > 0 else "none"


def evaluate_funnel(truths: Mapping[int, GtFrame], mined: Sequence[MinedTube],
                    stages: Mapping[str, Mapping[int, StageFrame]] | None = None, *, alpha: float, beta: float,
                    groups: Sequence[str] | None = None,
                    iou_threshold: float = FunnelProtocol.iou_threshold,
                    similarity: str = FunnelProtocol.similarity,
                    min_visible_px: int = FunnelProtocol.min_visible_px,
                    max_depth_m: float | None = FunnelProtocol.max_depth_m,
                    track_cover: float = FunnelProtocol.track_cover,
                    part_ioa: float = FunnelProtocol.part_ioa,
                    tube_split: Mapping[int, str] | None = None) -> dict:
    """The funnel over the frames in ``truths`` (frame index → GtFrame).

    ``stages`` maps a proposal stage's name to its masks per frame (a frame it lacks has no
    masks), in pipeline order; ``mined`` holds every candidate tube, ``selected`` set on the
    chosen ones; ``alpha`` and ``beta`` are the run's score weights (ScoreConfig), ``groups`` the
    calibrated unary's groups of terms when the run used it (``mining.score.calibrated.GROUPS``;
    the caller knows the unary, the funnel only reads each score's split). Returns a
    plain-JSON dict: ``stages``, ``bins``, ``protocol``, ``frames`` (per split: ``total``,
    ``distance``, ``height`` and ``cells`` ``"<distance> | <height>"``, each ``{"gt": n,
    <stage>: covered, "recall": {<stage>: share}}``), ``tracks`` (per split, the same shape)
    and ``carried`` (``summary`` and ``tubes``, the part and clutter tubes, highest score first;
    ``called_unknown_by``: the part and clutter tubes called unknown, per kind and carrying term).
    With ``tube_split`` (tube id → "known" / "unknown", the synthetic protocol's
    ``results["tube_split"]``; others are clutter), also ``calls``: the selected tubes on known
    objects per distance and height bin and what the miner called them (see "Calls" above).
    """
    if similarity not in ("mask", "box"):
        raise InputError(f"similarity must be 'mask' or 'box', got {similarity!r}")
    if not truths:
        raise InputError("no ground-truth frames to evaluate")
    p = FunnelProtocol(iou_threshold, similarity, min_visible_px, max_depth_m, track_cover, part_ioa)
    stages = dict(stages or {})
    if clash := set(stages) & set(TUBE_STAGES):
        raise InputError(f"proposal stage names must differ from the tube stages: {sorted(clash)}")
    names = list(stages) + list(TUBE_STAGES)
    nd, nh = len(p.distance_edges_m) - 1, len(p.height_edges_px) - 1
    counts = np.zeros((len(SPLITS), nd, nh, 1 + len(names)), np.int64)
    thr = p.iou_threshold - _EPS
    tube_dets = _observed_by_frame(mined, truths)  # frame → (tube, rle, box) of its observed tube frames

    visible: dict[int, int] = {}  # gt track → evaluated frames
    track_known: dict[int, bool] = {}
    stage_hits: dict[tuple[int, str], int] = {}  # (gt track, proposal stage) → frames covered
    tube_hits: dict[tuple[int, int], int] = {}  # (gt track, tube id) → frames covered
    explain: dict[int, list] = {}  # selected tube id → per-frame explanation
    where: dict[int, list] = {}  # tube id → (known, depth m, box height px) of the evaluated objects it covers
    covers_object: set[int] = set()  # selected tubes that cover an evaluated object somewhere

    for t in sorted(truths):
        gt = truths[t]
        if gt is None:
            raise InputError("frame has no ground truth", frame=t)
        evaluated = gt.areas >= p.min_visible_px
        if p.max_depth_m is not None:
            evaluated &= gt.depth <= p.max_depth_m
        heights = gt.boxes[:, 3] - gt.boxes[:, 1] if len(gt.boxes) else np.zeros(0)
        d_bin, h_bin = _bin(gt.depth, p.distance_edges_m), _bin(heights, p.height_edges_px)
        hit = np.zeros((len(gt.track_ids), len(names)), bool)
        for i, s in enumerate(stages):
            sf = stages[s].get(t)
            if sf is not None and len(sf.rles):
                hit[:, i] = (_similarity(p, gt.rles, gt.boxes, sf.rles, sf.boxes) >= thr).any(axis=1)
        dets = tube_dets.get(t, [])
        for m, rle, _ in dets:
            if list(rle["size"]) != list(gt.size):
                raise InputError(f"tube {m.tube.tube_id} mask is {rle['size']}, the ground truth is {list(gt.size)}",
                                 frame=t)
        iou = _similarity(p, gt.rles, gt.boxes, [d[1] for d in dets], [d[2] for d in dets])
        sel = np.array([d[0].selected for d in dets], bool)
        ok = iou >= thr
        hit[:, len(stages)] = ok.any(axis=1)
        hit[:, len(stages) + 1] = ok[:, sel].any(axis=1)
        for g in np.flatnonzero(evaluated):
            for k, split in enumerate(SPLITS):
                if split == "all" or gt.known[g] == (split == "known"):
                    counts[k, d_bin[g], h_bin[g], 0] += 1
                    counts[k, d_bin[g], h_bin[g], 1:] += hit[g]
            tid = int(gt.track_ids[g])
            visible[tid] = visible.get(tid, 0) + 1
            track_known[tid] = bool(gt.known[g])
            for i, s in enumerate(stages):
                stage_hits[(tid, s)] = stage_hits.get((tid, s), 0) + int(hit[g, i])
            for j in np.flatnonzero(ok[g]):
                key = (tid, dets[j][0].tube.tube_id)
                tube_hits[key] = tube_hits.get(key, 0) + 1
                where.setdefault(dets[j][0].tube.tube_id, []).append((bool(gt.known[g]), gt.depth[g], heights[g]))
        _explain_frame(p, gt, evaluated, dets, iou, sel, explain, covers_object)

    dist_names, height_names = bin_names(p.distance_edges_m, "m"), bin_names(p.height_edges_px, "px")
    return {
        "stages": names,
        "bins": {"distance_m": {"edges": list(p.distance_edges_m), "names": dist_names},
                 "height_px": {"edges": list(p.height_edges_px), "names": height_names}},
        "protocol": asdict(p) | {"distance_edges_m": list(p.distance_edges_m),
                                 "height_edges_px": list(p.height_edges_px)},
        "frames": _frame_rates(counts, names, dist_names, height_names),
        "tracks": _tracks(p, names, stages, visible, track_known, stage_hits, tube_hits, mined),
        "carried": _carried(mined, explain, covers_object, alpha, beta, groups),
    } | ({} if tube_split is None else {"calls": _calls(p, mined, tube_split, where)})


def _observed_by_frame(mined: Sequence[MinedTube], truths: Mapping[int, GtFrame]) -> dict[int, list]:
    """Frame → the observed tube frames on it with ground truth: (mined tube, rle, box)."""
    tube_dets: dict[int, list] = {}
    for m in mined:
        for f in m.tube.frames:
            if f.observed and f.frame in truths:
                tube_dets.setdefault(f.frame, []).append((m, f.rle, np.asarray(f.box, np.float64)))
    return tube_dets


def _frame_rates(counts: np.ndarray, names: list[str], dist_names: list[str], height_names: list[str]) -> dict:
    """Per split: the frame counts and recall in total, per distance bin, per height bin and per cell."""
    frames: dict = {}
    for k, split in enumerate(SPLITS):
        c = counts[k]
        frames[split] = {
            "total": _rates(c.sum(axis=(0, 1)), names),
            "distance": {dn: _rates(c[i].sum(axis=0), names) for i, dn in enumerate(dist_names)},
            "height": {hn: _rates(c[:, j].sum(axis=0), names) for j, hn in enumerate(height_names)},
            "cells": {f"{dn} | {hn}": _rates(c[i, j], names) for i, dn in enumerate(dist_names)
                      for j, hn in enumerate(height_names)},
        }
    return frames


def _calls(p: FunnelProtocol, mined: Sequence[MinedTube], tube_split: Mapping[int, str],
           where: dict[int, list]) -> dict:
    """The selected tubes on known objects per bin of the objects they cover, by the miner's call."""
    dist_names, height_names = bin_names(p.distance_edges_m, "m"), bin_names(p.height_edges_px, "px")
    out = {"distance": {n: dict.fromkeys(("tubes", *CALLS), 0) for n in dist_names},
           "height": {n: dict.fromkeys(("tubes", *CALLS), 0) for n in height_names},
           "total": dict.fromkeys(("tubes", *CALLS), 0)}
    for m in mined:
        tid = m.tube.tube_id
        on = [(z, h) for known, z, h in where.get(tid, []) if known]
        if not m.selected or tube_split.get(tid) != "known" or not on:
            continue
        z, h = np.median(np.array(on, np.float64), axis=0)
        call = m.category.call
        for axis, names, edges, v in (("distance", dist_names, p.distance_edges_m, z),
                                      ("height", height_names, p.height_edges_px, h)):
            cell = out[axis][names[int(_bin(np.array([v]), edges)[0])]]
            cell["tubes"] += 1
            cell[call] += 1
        out["total"]["tubes"] += 1
        out["total"][call] += 1
    return out


def _explain_frame(p: FunnelProtocol, gt: GtFrame, evaluated: np.ndarray, dets: list, iou: np.ndarray,
                   sel: np.ndarray, explain: dict[int, list], covers_object: set[int]) -> None:
    """Each selected tube's explanation in this frame (see "Carried by" in the module docstring)."""
    cols = np.flatnonzero(sel)
    if not len(cols):
        return
    thr = p.iou_threshold - _EPS
    rles, boxes = [dets[j][1] for j in cols], [dets[j][2] for j in cols]
    # intersection over the tube mask's own area: tubes are the rows
    in_gt = _similarity(p, rles, boxes, gt.rles, gt.boxes, ioa=True)  # (tubes, gt)
    in_tube = _similarity(p, rles, boxes, rles, boxes, ioa=True)  # (tubes, tubes)
    np.fill_diagonal(in_tube, 0.0)
    for r, j in enumerate(cols):
        m = dets[j][0]
        tid = m.tube.tube_id
        on = iou[:, j] >= thr
        if (on & evaluated).any():
            covers_object.add(tid)
            why = ("object", None)
        elif (on & ~evaluated).any():
            g = int(np.argmax(np.where(~evaluated, iou[:, j], -1.0)))
            why = ("ignored object", _gt_ref(gt, g, bool(evaluated[g])))
        elif in_gt.shape[1] and in_gt[r].max() >= p.part_ioa - _EPS:
            g = int(np.argmax(in_gt[r]))
            why = ("part", _gt_ref(gt, g, bool(evaluated[g])))
        elif in_tube.shape[1] > 1 and in_tube[r].max() >= p.part_ioa - _EPS:
            why = ("part", {"tube_id": int(dets[cols[int(np.argmax(in_tube[r]))]][0].tube.tube_id)})
        else:
            why = ("clutter", None)
        explain.setdefault(tid, []).append(why)


def _gt_ref(gt: GtFrame, g: int, evaluated: bool) -> dict:
    return {"track_id": int(gt.track_ids[g]), "category": str(gt.categories[g]), "known": bool(gt.known[g]),
            "evaluated": evaluated}


def _tracks(p: FunnelProtocol, names: list[str], stages: Mapping, visible: dict[int, int], known: dict[int, bool],
            stage_hits: dict, tube_hits: dict, mined: Sequence[MinedTube]) -> dict:
    """Track-level funnel per split (see "Track level" in the module docstring)."""
    selected = {m.tube.tube_id for m in mined if m.selected}
    best_any: dict[int, int] = {}
    best_sel: dict[int, int] = {}
    for (gid, tube), n in tube_hits.items():
        best_any[gid] = max(best_any.get(gid, 0), n)
        if tube in selected:
            best_sel[gid] = max(best_sel.get(gid, 0), n)
    counts = np.zeros((len(SPLITS), 1 + len(names)), np.int64)
    for gid, n in visible.items():
        need = p.track_cover * n - 1e-9
        row = [1] + [stage_hits.get((gid, s), 0) >= need for s in stages] + \
              [best_any.get(gid, 0) >= need, best_sel.get(gid, 0) >= need]
        for k, split in enumerate(SPLITS):
            if split == "all" or known[gid] == (split == "known"):
                counts[k] += np.array(row, np.int64)
    return {split: _rates(counts[k], names) for k, split in enumerate(SPLITS)}


def _carried(mined: Sequence[MinedTube], explain: dict[int, list], covers_object: set[int],
             alpha: float, beta: float, groups: Sequence[str] | None) -> dict:
    """The part and clutter tubes among the selected ones, with the score term that carried each."""
    summary = {"selected": 0, "on objects": 0, "on ignored objects": 0, "part": 0, "clutter": 0,
               "outside the evaluated frames": 0}
    by_term = {k: 0 for k in (*(TERMS if groups is None else groups), "none")}
    called_unknown = {kind: dict.fromkeys(by_term, 0) for kind in ("part", "clutter")}
    tubes = []
    for m in mined:
        if not m.selected:
            continue
        summary["selected"] += 1
        tid = m.tube.tube_id
        why = explain.get(tid)
        if tid in covers_object:
            summary["on objects"] += 1
            continue
        if not why:
            summary["outside the evaluated frames"] += 1
            continue
        # the most frequent explanation; ties go to the first seen
        key = Counter(_key(w) for w in why).most_common(1)[0][0]
        kind, of = next(w for w in why if _key(w) == key)
        if kind == "ignored object":
            summary["on ignored objects"] += 1
            continue
        summary[kind] += 1
        terms = weighted_terms(m, alpha, beta, groups)
        by = carried_by(terms)
        by_term[by] += 1
        if m.category.call == "unknown":
            called_unknown[kind][by] += 1
        tubes.append({
            "tube_id": int(tid), "frames": len(why), "observed_frames": m.tube.n_inliers, "kind": kind, "of": of,
            "label": _label(kind, of), "share": sum(1 for w in why if _key(w) == key) / len(why),
            "terms": terms, "total": float(m.score.total), "carried_by": by,
            "category": m.category.category,
            "known_call": None if m.category.known is None else bool(m.category.known), "call": m.category.call,
        })
    tubes.sort(key=lambda x: (-x["total"], x["tube_id"]))
    return {"summary": summary, "carried_by": by_term, "called_unknown_by": called_unknown, "tubes": tubes}


def _key(why: tuple) -> tuple:
    kind, of = why
    if of is None:
        return (kind,)
    return (kind, of.get("track_id"), of.get("tube_id"))


def _label(kind: str, of: dict | None) -> str:
    if kind != "part":
        return kind
    if "tube_id" in of:
        return f"part of tube {of['tube_id']}"
    ignored = "" if of["evaluated"] else ", ignored"
    return f"part of track {of['track_id']} ({of['category']}{ignored})"


def _pct(x: float) -> str:
    return "—" if x != x else f"{100 * x:.0f} %"


def _table(head: list[str], rows: list[list[str]]) -> list[str]:
    widths = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]
    return ["  ".join(x.ljust(w) if i < 2 else x.rjust(w) for i, (x, w) in enumerate(zip(r, widths)))
            for r in [head] + rows]


def format_funnel(funnel: dict, max_tubes: int = 20) -> str:
    """The funnel as text: recall per split × distance bin, per split × height bin, tracks,
    then the part and clutter tubes (at most ``max_tubes`` lines, then a count of the rest)."""
    stages = funnel["stages"]
    p = funnel["protocol"]
    head = ["split", "bin", "gt dets"] + stages
    lines = [f"recall funnel: share of evaluated ground-truth detections covered (a {p['similarity']} IoU ≥ "
             f"{p['iou_threshold']:g}) at each stage"]
    for axis, title in (("distance", "distance (object centre)"), ("height", "height (visible box)")):
        rows = []
        for split in SPLITS:
            s = funnel["frames"][split]
            bins = list(s[axis].items()) if s["total"]["gt"] else []  # a split without objects: one row
            for name, r in [("all", s["total"])] + bins:
                rows.append([split, name, str(r["gt"])] + [_pct(r["recall"][x]) for x in stages])
        lines.append(f"by {title}:")
        lines += ["  " + x for x in _table(head, rows)]
    rows = [[split, "", str(r["gt"])] + [_pct(r["recall"][x]) for x in stages]
            for split, r in funnel["tracks"].items()]
    lines.append(f"ground-truth tracks covered in ≥ {100 * p['track_cover']:.0f} % of their evaluated frames "
                 f"(tube stages: by one tube):")
    lines += ["  " + x for x in _table(["split", "", "tracks"] + stages, rows)]
    c = funnel["carried"]
    s = c["summary"]
    lines.append(f"selected tubes: {s['selected']}; {s['on objects']} on objects, {s['on ignored objects']} on ignored "
                 f"objects, {s['part']} on parts, {s['clutter']} clutter, {s['outside the evaluated frames']} outside "
                 f"the evaluated frames; parts and clutter carried by "
                 + ", ".join(f"{k} {v}" for k, v in c["carried_by"].items() if v))
    cu = c.get("called_unknown_by")
    if cu:
        lines.append("parts and clutter called unknown, by the term that carried them: " + "; ".join(
            f"{kind} {sum(v.values())}" + (" (" + ", ".join(f"{k} {n}" for k, n in v.items() if n) + ")"
                                            if sum(v.values()) else "") for kind, v in cu.items()))
    if "calls" in funnel:
        lines.append(f"selected tubes on known objects by the miner's call ({' / '.join(CALLS)}):")
        cells = [("", "all", funnel["calls"]["total"])]
        cells += [(axis, name, r) for axis in ("distance", "height") for name, r in funnel["calls"][axis].items()]
        rows = [[axis, name, str(r["tubes"]), *(str(r.get(c, 0)) for c in CALLS),
                 _pct(r.get("unknown", 0) / r["tubes"] if r["tubes"] else float("nan"))] for axis, name, r in cells]
        lines += ["  " + x for x in _table(["by", "bin", "tubes", *CALLS, "called unknown"], rows)]
    if c["tubes"]:
        names = list(c["tubes"][0]["terms"])  # the REFERENCE's three terms, or the calibrated model's groups
        head = ["tube", "kind", "frames", *names, "total", "carried by", "call"]
        rows = []
        for x in c["tubes"][:max_tubes]:
            t = x["terms"]
            call = x["call"]
            if x["category"] not in (None, "unknown"):
                call += f" ({x['category']})"
            rows.append([str(x["tube_id"]), x["label"], str(x["frames"])] +
                        [f"{t[k]:.1f}" for k in names] + [f"{x['total']:.1f}", x["carried_by"], call])
        lines += ["  " + x for x in _table(head, rows)]
        rest = len(c["tubes"]) - max_tubes
        if rest > 0:
            lines.append(f"  … and {rest} more (in the JSON)")
    return "\n".join(lines)
