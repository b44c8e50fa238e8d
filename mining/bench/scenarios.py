"""``mine bench scenarios``: mine each staged synthetic scenario with scene flow on and off.

One row per scenario (``mining/sources/synthetic/scenarios.py``) and flow setting. Each
scenario names its targets (role ``moving``) and static references (role ``parked``). It is
mined through the image pipeline (``FrameLoop`` → tube generation → judge, the steps of
``frame_records`` → ``mine_tubes``) with the job config, and again with scene-flow velocities
switched off (``localise.min_flow_samples = 100000``, the issue's switch); geometry and
proposals do not depend on that setting, so the second run reuses the first run's. Scored
against the renderer's truth with ``evaluate_synthetic``:

* **tube recall** of the moving targets and, for reference, of the parked ones (a track is
  recalled when one tube covers it in at least half its evaluated frames), **IDSW per
  track** and **frame recall** of the moving targets, and **HOTA** over every staged object
  (the ``all`` split; tubes on nothing are FPs there);
* **scene flow on the targets** (issue 9, item 2), per evaluated target frame: flow samples
  whose pixel lies on the target's true mask, the share of frames with at least
  ``localise.min_flow_samples`` of them, and the share of those samples the egomotion called
  static inliers (a moving object's should not be);
* **where a target is lost**, per evaluated target frame: a proposal covers it (mask IoU ≥
  0.5), that proposal passed the geometric filter, and it got a velocity (enough flow
  samples in the proposal's own mask, a trusted egomotion; flow on only);
* per target: its first evaluated frame, the first frame a selected tube covers it, how many
  tubes covered it (more than one: fragments or identity switches).

A scenario with a distance band (``far``: 30–60 m) scores its targets only in the frames
where their centre lies inside it (HOTA still counts every object). Resolution: the
source's 1242×375, or with ``half`` 621×188 (fx 360.77: the KITTI camera at half size).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np

from mining.catalog import safe_files
from mining.checks import count, output_file
from mining.config import JobConfig
from mining.eval.synthetic import (
    GtFrame,
    SyntheticEvalProtocol,
    evaluate_synthetic,
    gt_frame,
)
from mining.localise.localise import geometric_filter
from mining.masks import mask_iou, mask_pixels
from mining.pipeline.arguments import SYNTHETIC_JOB, add_job_options, add_overwrite_option, job_config
from mining.pipeline.frames import FrameLoop, FrameRecord, plan_frames
from mining.pipeline.mine import judge, tube_generator
from mining.sources import open_source
from mining.sources.synthetic.scenarios import SCENARIOS, Role, get_scenario
from mining.types import MinedTube, SceneFlow

FLOW_OFF_SAMPLES = 100_000  # the switch: no proposal has this many flow samples
HALF = {"width": 621, "height": 188, "fx": 360.77}  # the KITTI camera at half size
MODES = ("on", "off")
ROLES = ("moving", "parked")


def flow_configs(cfg: JobConfig) -> dict[str, JobConfig]:
    """The job config with scene-flow velocities on (as given) and off."""
    off = dataclasses.replace(cfg, localise=dataclasses.replace(cfg.localise, min_flow_samples=FLOW_OFF_SAMPLES))
    return {"on": cfg, "off": off}


def _flow_counts(flow: SceneFlow | None, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel: flow samples with a finite motion (at the pixel ``localise`` gives them:
    rounded, clipped) and how many of those the egomotion called inliers."""
    if flow is None or len(flow) == 0:
        return np.zeros((h, w), np.int64), np.zeros((h, w), np.int64)
    good = np.isfinite(flow.motion).all(axis=1)
    u = np.clip(np.round(flow.uv[good, 0]).astype(np.int64), 0, w - 1)
    v = np.clip(np.round(flow.uv[good, 1]).astype(np.int64), 0, h - 1)
    key = v * w + u
    counts = np.bincount(key, minlength=h * w).reshape(h, w)
    inliers = np.bincount(key[flow.inlier[good]], minlength=h * w).reshape(h, w)
    return counts, inliers


def _in_band(depth: float, band: tuple[float, float] | None) -> bool:
    return band is None or band[0] <= depth <= band[1]


def _target_frames(rec: FrameRecord, roles: dict[int, Role], band, cfg: JobConfig, min_px: int) -> list[dict]:
    """Flow and survival of each evaluated staged object in one frame."""
    truth = rec.frame.truth
    h, w = truth.depth.shape
    counts, inliers = _flow_counts(rec.geometry.flow, h, w)
    props = rec.proposals
    kept = set(geometric_filter(rec.localised, rec.ground, cfg.localise.filters).tolist())
    objs = [o for o in truth.objects if o.track_id in roles and o.mask.sum() >= min_px
            and _in_band(float(o.center_cam[2]), band)]
    if not objs:
        return []
    gt = gt_frame(dataclasses.replace(truth, objects=objs))
    iou = mask_iou(gt.rles, props.rles)
    out = []
    for k, o in enumerate(objs):
        j = int(np.argmax(iou[k])) if iou.shape[1] else -1
        matched = j >= 0 and iou[k, j] >= 0.5
        if matched:
            r, c = mask_pixels(props.rles[j])
            flow_prop = int(counts[r, c].sum())
        n = int(counts[o.mask].sum())
        out.append({
            "track_id": o.track_id, "frame": rec.frame.index, "area": int(gt.areas[k]),
            "depth": float(o.center_cam[2]), "speed": float(np.linalg.norm(o.velocity_world)),
            "flow": n, "flow_inliers": int(inliers[o.mask].sum()),
            "proposal": bool(matched), "kept": bool(matched and j in kept),
            "flow_proposal": flow_prop if matched else 0,
            "velocity": bool(matched and np.isfinite(rec.localised.velocity[j]).all()),
        })
    return out


def _subset(gt: GtFrame, keep: np.ndarray) -> GtFrame:
    idx = np.flatnonzero(keep)
    return GtFrame(gt.track_ids[idx], gt.known[idx], [gt.categories[i] for i in idx], [gt.rles[i] for i in idx],
                   gt.areas[idx], gt.boxes[idx], gt.depth[idx], gt.size)


def _role_truths(truths: dict[int, GtFrame], ids: set[int], band) -> dict[int, GtFrame]:
    out = {}
    for f, gt in truths.items():
        keep = np.array([int(t) in ids for t in gt.track_ids], bool)
        if band is not None:
            keep &= (gt.depth >= band[0]) & (gt.depth <= band[1])
        out[f] = _subset(gt, keep)
    return out


def _coverage(mined: list[MinedTube], truths: dict[int, GtFrame], min_px: int, iou_threshold: float) -> dict:
    """Per ground-truth track: evaluated frames, first one, frames of its best tube, first
    frame any selected tube covers it (IoU ≥ threshold, observed frames), tubes that did."""
    dets: dict[int, list] = {}
    for m in mined:
        if m.selected:
            for f in m.tube.frames:
                if f.observed:
                    dets.setdefault(f.frame, []).append((m.tube.tube_id, f.rle))
    out: dict[int, dict] = {}
    for f in sorted(truths):
        gt = truths[f]
        d = dets.get(f, [])
        iou = mask_iou(gt.rles, [x[1] for x in d])
        for k, tid in enumerate(gt.track_ids.tolist()):
            if gt.areas[k] < min_px:
                continue
            c = out.setdefault(tid, {"frames": 0, "first": f, "first_covered": None, "per_tube": {}})
            c["frames"] += 1
            hits = np.flatnonzero(iou[k] >= iou_threshold - 1e-12) if iou.size else np.zeros(0, np.int64)
            for j in hits:
                tube = d[j][0]
                c["per_tube"][tube] = c["per_tube"].get(tube, 0) + 1
                if c["first_covered"] is None:
                    c["first_covered"] = f
    for c in out.values():
        c["best_tube_frames"] = max(c["per_tube"].values(), default=0)
        c["tubes"] = len(c.pop("per_tube"))
    return out


def _flow_summary(rows: list[dict], min_samples: int) -> dict:
    if not rows:
        return {"frames": 0}
    n = np.array([r["flow"] for r in rows])
    inl = np.array([r["flow_inliers"] for r in rows])
    prop = np.array([r["proposal"] for r in rows])
    return {
        "frames": len(rows),
        "flow_median": float(np.median(n)), "flow_mean": float(n.mean()),
        "flow_enough": float(np.mean(n >= min_samples)),
        "inlier_share": float(inl.sum() / n.sum()) if n.sum() else float("nan"),
        "proposal": float(prop.mean()),
        "kept": float(np.mean([r["kept"] for r in rows])),
        "flow_proposal_median": float(np.median([r["flow_proposal"] for r in rows if r["proposal"]]))
        if prop.any() else float("nan"),
        "velocity": float(np.mean([r["velocity"] for r in rows])),
    }


def run_scenario(name: str, cfg: JobConfig, n_frames: int | None = None, sequence: str = "0000",
                 half: bool = False, min_visible_px: int = SyntheticEvalProtocol.min_visible_px) -> dict:
    """Mine one scenario with flow on and off and score it (see the module docstring)."""
    spec = get_scenario(name)
    n = int(n_frames or spec.n_frames)
    options = {k: v for k, v in cfg.source.options.items() if k not in ("n_frames", "scenario", "sequences")}
    if half:
        options |= HALF
    src = open_source("synthetic", None, n_frames=n, scenario=name, **options)
    plan = src.plan(sequence)
    roles = src.scene(sequence).roles
    cfgs = flow_configs(cfg)
    loops = {m: FrameLoop(c) for m, c in cfgs.items()}
    gens = {m: tube_generator(c) for m, c in cfgs.items()}
    truths: dict[int, GtFrame] = {}
    rows: list[dict] = []
    ego_failures = 0
    t0 = time.perf_counter()
    for position, frame, after_gap in plan_frames(src, plan, 0, len(plan)):
        if after_gap:
            for loop in loops.values():
                loop.recording_gap()
        rec = loops["on"].step(frame, position=position)
        rec_off = loops["off"].step(frame, geometry=rec.geometry, proposals=rec.proposals, position=position)
        gens["on"].step(rec.tracking)
        gens["off"].step(rec_off.tracking)
        truths[frame.index] = gt_frame(frame.truth)
        rows += _target_frames(rec, roles, spec.band_m, cfg, min_visible_px)
        ego_failures += int(position > 0 and rec.egomotion_T is None)
    mined = {m: judge(g.finish(), cfgs[m]) for m, g in gens.items()}
    t1 = time.perf_counter()
    ids = {role: {t for t, r in roles.items() if r.role == role} for role in ROLES}
    role_truths = {role: _role_truths(truths, ids[role], spec.band_m) for role in ROLES}
    threshold = SyntheticEvalProtocol.iou_threshold
    modes = {}
    for m in MODES:
        full = evaluate_synthetic(mined[m], truths, min_visible_px=min_visible_px)
        res = {"HOTA": full["all"]["HOTA"], "tubes": full["tubes"]["evaluated"], "clutter": full["tubes"]["clutter"],
               "roles": {}, "targets": {}}
        for role in ROLES:
            if not ids[role]:
                continue
            r = evaluate_synthetic(mined[m], role_truths[role], min_visible_px=min_visible_px)["all"]
            res["roles"][role] = {"tracks": r["tracks"], "covered": r["tracks_covered"], "tube_recall": r["tube_recall"],
                                  "IDSW": r["IDSW"], "IDSW_per_track": r["IDSW"] / r["tracks"] if r["tracks"] else float("nan"),
                                  "frame_recall": r["frame_recall"], "HOTA": r["HOTA"]}
            res["targets"].update(_coverage(mined[m], role_truths[role], min_visible_px, threshold))
        modes[m] = res
    min_samples = cfg.localise.min_flow_samples
    targets = {}
    for tid, role in roles.items():
        own = [r for r in rows if r["track_id"] == tid]
        if not own:
            continue
        targets[tid] = {"role": role.role, "note": role.note, "textureless": role.textureless,
                        "depth": (min(r["depth"] for r in own), max(r["depth"] for r in own)),
                        "speed": float(np.median([r["speed"] for r in own]))} | _flow_summary(own, min_samples)
    return {
        "scenario": name, "summary": spec.summary, "sequence": sequence, "frames": n,
        "resolution": f"{plan.calib.width}x{plan.calib.height}", "band_m": spec.band_m,
        "egomotion_failures": ego_failures,
        "flow": {role: _flow_summary([r for r in rows if roles[r["track_id"]].role == role], min_samples)
                 for role in ROLES},
        "modes": modes, "targets": targets,
        "seconds": {"mine": t1 - t0, "eval": time.perf_counter() - t1},
    }


def _f(x: float, fmt: str = "{:.2f}") -> str:
    return "—" if x is None or (isinstance(x, float) and not np.isfinite(x)) else fmt.format(x)


def format_scenarios(results: list[dict]) -> str:
    """The tables: tubes per scenario × flow, flow on the targets, and per target."""
    head = ["scenario", "flow", "moving tubeR", "IDSW/trk", "frameR", "parked tubeR", "HOTA", "tubes", "clutter"]
    rows = [head]
    for r in results:
        for m in MODES:
            x = r["modes"][m]
            mv, pk = x["roles"].get("moving", {}), x["roles"].get("parked", {})
            rows.append([r["scenario"], m,
                         f"{_f(mv.get('tube_recall'))} ({mv.get('covered', 0)}/{mv.get('tracks', 0)})",
                         _f(mv.get("IDSW_per_track")), _f(mv.get("frame_recall")),
                         f"{_f(pk.get('tube_recall'))} ({pk.get('covered', 0)}/{pk.get('tracks', 0)})" if pk else "—",
                         _f(x["HOTA"], "{:.3f}"), str(x["tubes"]), str(x["clutter"])])
    lines = [_table(rows), ""]
    head = ["scenario", "role", "frames", "flow/mask med", "mean", "≥min", "inlier", "proposal", "kept",
            "flow/prop med", "velocity"]
    rows = [head]
    for r in results:
        for role in ROLES:
            s = r["flow"][role]
            if not s["frames"]:
                continue
            rows.append([r["scenario"], role, str(s["frames"]), _f(s["flow_median"], "{:.0f}"), _f(s["flow_mean"], "{:.1f}"),
                         _f(s["flow_enough"]), _f(s["inlier_share"]), _f(s["proposal"]), _f(s["kept"]),
                         _f(s["flow_proposal_median"], "{:.0f}"), _f(s["velocity"])])
    lines += ["Scene flow on the staged objects (evaluated frames; velocity: flow on):", _table(rows), ""]
    head = ["scenario", "id", "role", "depth m", "speed", "flow med", "≥min", "prop", "kept", "vel", "frames",
            "first", "on: 1st cover/tubes/best", "off: 1st cover/tubes/best", "note"]
    rows = [head]
    for r in results:
        for tid, t in sorted(r["targets"].items()):
            if t["role"] != "moving":
                continue
            cov = []
            for m in MODES:
                c = r["modes"][m]["targets"].get(tid)
                first = "never" if c is None or c["first_covered"] is None else c["first_covered"]
                cov.append("—" if c is None else f"{first}/{c['tubes']}/{c['best_tube_frames']}")
            c = r["modes"]["on"]["targets"].get(tid, {"frames": 0, "first": None})
            rows.append([r["scenario"], str(tid), t["role"] + (" (flat)" if t["textureless"] else ""),
                         f"{t['depth'][0]:.0f}–{t['depth'][1]:.0f}", f"{t['speed']:.1f}", _f(t["flow_median"], "{:.0f}"),
                         _f(t["flow_enough"]), _f(t["proposal"]), _f(t["kept"]), _f(t["velocity"]), str(c["frames"]),
                         str(c["first"]), cov[0], cov[1], t["note"]])
    lines += [("Moving targets (frames: evaluated; cover: first frame a selected tube covers it / tubes that did / "
               "frames of the best one):"), _table(rows)]
    return "\n".join(lines)


def _table(rows: list[list[str]]) -> str:
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(x.ljust(w) if i in (0, 1) or i == len(row) - 1 else x.rjust(w)
                               for i, (x, w) in enumerate(zip(row, widths))).rstrip() for row in rows)


def run_scenarios_bench(cfg: JobConfig, names: list[str] | None = None, n_frames: int | None = None,
                        sequence: str = "0000", half: bool = False, json_out: str | None = None,
                        overwrite: bool = False) -> int:
    """`mine bench scenarios`: every (or the named) scenario, flow on and off; prints the tables."""
    names = list(names or SCENARIOS)
    for name in names:
        get_scenario(name)  # unknown names fail before any work
    results = []
    t0 = time.perf_counter()
    for name in names:
        r = run_scenario(name, cfg, n_frames, sequence, half)
        results.append(r)
        print(f"{name}: {r['frames']} frames at {r['resolution']}, mined (flow on and off) in "
              f"{r['seconds']['mine']:.0f} s, {r['egomotion_failures']} egomotion failures", flush=True)
    res = sorted({r["resolution"] for r in results})
    print(f"\nScenarios, sequence {sequence} (seed), {', '.join(res)}, proposer {cfg.proposals.proposer}, "
          f"flow off = localise.min_flow_samples={FLOW_OFF_SAMPLES} (on: {cfg.localise.min_flow_samples}); "
          f"{time.perf_counter() - t0:.0f} s in all\n")
    print(format_scenarios(results))
    if json_out:
        safe_files.write_file(json_out, json.dumps(results, indent=1, default=_json_default).encode(), overwrite)
    return 0


def _json_default(x):
    if isinstance(x, np.generic):
        return x.item()
    raise TypeError(type(x).__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine bench scenarios``'s options."""
    add_job_options(p)
    if SYNTHETIC_JOB.is_file():
        p.set_defaults(config=str(SYNTHETIC_JOB))
    p.add_argument("--scenarios", nargs="+", default=None, help="default: all (mining/sources/synthetic/scenarios.py)")
    p.add_argument("--frames", type=count(), default=None, help="frames per scenario (default: the scenario's, 80)")
    p.add_argument("--sequence", default="0000", help="seeds the world around the staged objects")
    p.add_argument("--half", action="store_true", help="render at 621x188 (fx 360.77) instead of 1242x375")
    p.add_argument("--json", type=output_file, help="also write the results as JSON here")
    add_overwrite_option(p, "the --json file")


def run(args: argparse.Namespace) -> int:
    """``mine bench scenarios``."""
    return run_scenarios_bench(job_config(args), args.scenarios, args.frames, args.sequence, args.half, args.json,
                               overwrite=args.overwrite)
