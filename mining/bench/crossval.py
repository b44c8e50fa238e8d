"""``mine bench crossval``: the detections-only settings, chosen by leave-sequences-out cross-validation.

Why: settings fit on all twelve KITTI training sequences at once scored higher on them than on
the validation sequences (issue 9). Here the twelve are split into K folds of whole sequences
(neighbouring frames of one sequence are not independent, so a fold never splits one). For
each fold, a small grid of settings is scored on the other folds (its training folds), the
best is chosen there, and only that one is scored on the held-out fold: what the choice does
on sequences it never saw.

* **Score** of a setting on a set of sequences: the mean of Car and Pedestrian HOTA, each
  combined over the set by the KITTI MOT protocol (``mining.eval.kitti_mot``).
* **Grid**: a few physical parameters (``DEFAULT_GRID``), each axis's first value the REFERENCE
  one; everything else comes from the job config. A ``select.*`` axis only re-judges the same
  tubes, so tubes are generated once per sequence and generation setting, and each sequence's
  detections are read and localised once for all settings.
* **Eligible**: a fold's winner counts only if, on its held-out fold, it beats the 2D-IoU
  baseline in both classes and does not score below the REFERENCE setting (the grid's first
  point, nothing tuned). A setting that wins on the training folds but loses on its held-out
  fold is not taken.
* **Final setting**: the eligible winner chosen by most folds; a tie goes to the one with the
  best mean held-out score over all K folds (the usual K-fold estimate), so that the final
  choice rests on the training-fold selections and, only between equals, on unseen data.
  With no eligible winner the REFERENCE setting stays.
"""

from __future__ import annotations

import argparse
import itertools
import json
import tempfile
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mining.bench.iou_tracker import iou_track, write_iou_tracks
from mining.catalog import safe_files
from mining.checks import count, input_file, output_file
from mining.config import BY_MODE, JobConfig, load_config, parse_override
from mining.eval.kitti_mot import combine_kitti_mot, evaluate_kitti_mot
from mining.formats.kitti_tracking import read_seqmap
from mining.formats.poses import read_poses
from mining.pipeline.arguments import REPO, add_data_option, add_overwrite_option
from mining.pipeline.detections import DETECTIONS, FRAME_INTERVAL_NS, detection_frames, write_detection_tubes
from mining.pipeline.mine import judge, tube_generator
from mining.proposals.precomputed import KittiDetections
from mining.sources.kitti import KittiTrackingSource

CLASSES = ("Car", "Pedestrian")
TARGET_MARGIN = 0.05  # issue 9: held-out HOTA above the 2D-IoU baseline by ≥ 5 (points), both classes

# The four folds of the twelve training sequences (frames; Car / Pedestrian boxes the KITTI
# protocol scores). Of the 15 400 ways to cut them into four folds of three, this one keeps
# each fold's share of frames and of Car boxes nearest 1/4 while every fold has ≥ 150
# Pedestrian boxes; 0019 holds three quarters of all Pedestrian boxes, so its fold's share
# cannot be balanced, and the three long sequences (0009, 0019, 0020) go to different folds.
KITTI_TRAINING_FOLDS = (
    ("0000", "0017", "0020"),  # 1136 frames (23 %), Car 5108 (31 %), Ped 789 (10 %)
    ("0001", "0011", "0012"),  # 898 frames (18 %), Car 5274 (32 %), Ped 365 (5 %)
    ("0003", "0009", "0015"),  # 1323 frames (26 %), Car 3348 (20 %), Ped 747 (10 %)
    ("0004", "0005", "0019"),  # 1670 frames (33 %), Car 2791 (17 %), Ped 5938 (76 %)
)

# KEY → candidate values (TOML literals), the REFERENCE value first. At KITTI's 10 Hz a gap
# of 5 / 10 / 20 frames is 0.5 / 1 / 2 s of missed detections.
DEFAULT_GRID = {
    "tubes.max_gap_frames": ("5", "10", "20"),  # REFERENCE 5; the longest occlusion a tube bridges (frames at 10 Hz)
    "tubes.gap_inlier_factor": ("0.2", "0.5"),  # REFERENCE 0.2; gap allowed per observed frame (gap ≤ factor × inliers)
    "tubes.backward_required": ("3", "1"),  # REFERENCE 3; backward inliers needed to start a tube (confirmation)
    "select.overlap_weight.reference": ("30.0", "2.0"),  # REFERENCE 30; weight of the overlap penalty between co-selected tubes
}

SequenceSums = dict[str, dict]  # KittiMotResults.sums[seq]: class → summable counts


@dataclass(frozen=True)
class Setting:
    """One grid point: config overrides ``KEY=VALUE``, in the grid's axis order."""

    overrides: tuple[str, ...]

    @property
    def label(self) -> str:
        parts = []
        for o in self.overrides:
            key, value = o.split("=", 1)
            table, _, name = key.rpartition(".")
            if table in BY_MODE:  # "overlap_weight.reference", not a bare "reference"
                name = f"{table.rsplit('.', 1)[-1]}.{name}"
            if name == "max_gap_frames":
                parts.append(f"gap≤{int(value) * FRAME_INTERVAL_NS / 1e9:g}s")
            else:
                parts.append(f"{name}={value}")
        return " ".join(parts) or "(config)"


def grid_settings(grid: Mapping[str, Sequence[str]]) -> list[Setting]:
    """Every combination of the axes, the first axis varying slowest; the first is REFERENCE."""
    keys = list(grid)
    return [Setting(tuple(f"{k}={v}" for k, v in zip(keys, values)))
            for values in itertools.product(*(grid[k] for k in keys))]


def parse_grid(items: Sequence[str]) -> dict[str, tuple[str, ...]]:
    """``KEY=V1,V2,...`` items → {KEY: (V1, V2, ...)}; each value must parse as an override."""
    grid = {}
    for item in items:
        key, _, values = item.partition("=")
        grid[key.strip()] = tuple(v.strip() for v in values.split(",") if v.strip())
        for v in grid[key.strip()]:
            parse_override(f"{key}={v}")
    return grid


def make_folds(frames: Mapping[str, int], k: int) -> list[tuple[str, ...]]:
    """K folds of whole sequences: ``KITTI_TRAINING_FOLDS`` for the twelve, else by length.

    Other sequence sets are dealt longest first in a serpentine (1, 2, …, K, K, …, 1, …), so
    each fold gets long and short ones. Every sequence is in exactly one fold.
    """
    seqs = sorted(frames)
    if k < 2 or k > len(seqs):
        raise ValueError(f"{k} folds of {len(seqs)} sequences")
    if k == len(KITTI_TRAINING_FOLDS) and seqs == sorted(s for f in KITTI_TRAINING_FOLDS for s in f):
        return [tuple(f) for f in KITTI_TRAINING_FOLDS]
    folds: list[list[str]] = [[] for _ in range(k)]
    order = sorted(seqs, key=lambda s: (-frames[s], s))
    for i, seq in enumerate(order):
        lap, pos = divmod(i, k)
        folds[pos if lap % 2 == 0 else k - 1 - pos].append(seq)
    return [tuple(sorted(f)) for f in folds]


def objective(metrics: Mapping[str, Mapping[str, float]]) -> float:
    """The selection score: mean HOTA of Car and Pedestrian."""
    return sum(metrics[c]["HOTA"] for c in CLASSES) / len(CLASSES)


def combined(sums: Mapping[str, SequenceSums], sequences: Sequence[str]) -> dict[str, dict[str, float]]:
    return combine_kitti_mot([sums[s] for s in sequences], CLASSES)


def select_setting(scores: Mapping[Setting, Mapping[str, SequenceSums]], training: Sequence[str]) -> tuple[Setting, float]:
    """The setting with the best score on ``training`` (the first in grid order on a tie).

    Only the training sequences' sums are read: the held-out fold never reaches the choice.
    """
    best, best_score = None, -1.0
    for setting, per_seq in scores.items():
        score = objective(combined(per_seq, training))
        if score > best_score:
            best, best_score = setting, score
    assert best is not None, "an empty grid"
    return best, best_score


@dataclass
class FoldResult:
    held_out: tuple[str, ...]
    training: tuple[str, ...]
    setting: Setting  # chosen on the training folds
    training_score: float
    training_metrics: dict[str, dict[str, float]]
    held_out_metrics: dict[str, dict[str, float]]
    baseline_metrics: dict[str, dict[str, float]]  # 2D-IoU on the held-out fold
    reference_metrics: dict[str, dict[str, float]]  # the REFERENCE setting on the held-out fold
    held_out_rank: int  # 1 = the chosen setting is also the best of the grid on the held-out fold

    def margin(self, cls: str) -> float:
        return self.held_out_metrics[cls]["HOTA"] - self.baseline_metrics[cls]["HOTA"]

    @property
    def classes(self) -> tuple[str, ...]:
        """The classes the held-out fold has ground truth of (a class without any scores 0 for everyone)."""
        return tuple(c for c in CLASSES if self.baseline_metrics[c]["GT_Dets"] > 0)

    @property
    def beats_baseline(self) -> bool:
        return all(self.margin(c) > 0 for c in self.classes)

    @property
    def eligible(self) -> bool:
        return self.beats_baseline and objective(self.held_out_metrics) >= objective(self.reference_metrics)

    @property
    def meets_target(self) -> bool:
        return all(self.margin(c) >= TARGET_MARGIN for c in self.classes)


@dataclass
class CrossvalResult:
    folds: list[FoldResult]
    final: Setting
    final_rule: str  # how the final setting was reached, in words
    cv_score: dict[Setting, float]  # mean held-out score over the folds, per setting
    pooled_held_out: dict[str, dict[str, float]]  # every sequence scored under its own fold's choice
    final_held_out: list[dict[str, dict[str, float]]] = field(default_factory=list)  # the final setting, per fold


def cross_validate(scores: Mapping[Setting, Mapping[str, SequenceSums]], baseline: Mapping[str, SequenceSums],
                   folds: Sequence[Sequence[str]]) -> CrossvalResult:
    """Choose per fold on its training folds, score on its held-out fold, then the final setting."""
    settings = list(scores)
    reference = settings[0]
    all_seqs = [s for f in folds for s in f]
    results = []
    for held in folds:
        training = tuple(s for s in all_seqs if s not in held)
        setting, train_score = select_setting(scores, training)
        held_scores = {s: objective(combined(scores[s], held)) for s in settings}
        mine = held_scores[setting]
        results.append(FoldResult(
            held_out=tuple(held), training=training, setting=setting, training_score=train_score,
            training_metrics=combined(scores[setting], training),
            held_out_metrics=combined(scores[setting], held),
            baseline_metrics=combined(baseline, held),
            reference_metrics=combined(scores[reference], held),
            held_out_rank=1 + sum(v > mine for v in held_scores.values())))
    cv_score = {s: sum(objective(combined(scores[s], f)) for f in folds) / len(folds) for s in settings}
    votes = Counter(r.setting for r in results if r.eligible)
    if votes:
        top = max(votes.values())
        tied = [s for s in settings if votes.get(s) == top]
        final = max(tied, key=lambda s: (cv_score[s], -settings.index(s)))
        rule = (f"chosen by {top} of {len(folds)} folds" if len(tied) == 1 else
                f"tied at {top} of {len(folds)} folds with {len(tied) - 1} other(s); best mean held-out score")
    else:
        final, rule = reference, "no fold's choice was eligible: the REFERENCE setting stays"
    pooled = combine_kitti_mot([scores[r.setting][s] for r in results for s in r.held_out], CLASSES)
    final_held = [combined(scores[final], f) for f in folds]
    return CrossvalResult(results, final, rule, cv_score, pooled, final_held)


def score_grid(data: Path, config: str | Path | None, overrides: Sequence[str], sequences: Sequence[str],
               settings: Sequence[Setting], log=print) -> tuple[dict[Setting, dict[str, SequenceSums]], dict[str, SequenceSums]]:
    """Every setting's and the 2D-IoU baseline's KITTI MOT sums, per sequence.

    Each sequence's detections are read and localised once per distinct (proposals, localise)
    config, its tubes generated once per distinct generation config (tubes, score), and judged
    (score, select) and written per setting: exactly what ``track_detections`` writes.
    """
    root = data / "kitti_tracking"
    train = root / "training"
    seqmap = train / "seqmaps" / "train.seqmap"
    source = KittiTrackingSource(str(root))
    cfgs = {s: load_config(config, [*overrides, *s.overrides]) for s in settings}
    base = load_config(config, list(overrides))

    def key(cfg: JobConfig, *sections: str) -> str:
        d = cfg.to_dict()
        return json.dumps({k: d[k] for k in sections}, sort_keys=True, default=str)

    scores: dict[Setting, dict[str, SequenceSums]] = {s: {} for s in settings}
    baseline: dict[str, SequenceSums] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for seq in sequences:
            t0 = time.perf_counter()
            poses = train / "egoposes_orbslam3" / f"{seq}.txt"
            frames_cache: dict[str, list] = {}
            tubes_cache: dict[str, list] = {}
            for i, (setting, cfg) in enumerate(cfgs.items()):
                fkey = key(cfg, "proposals", "localise")
                if fkey not in frames_cache:
                    frames_cache[fkey] = list(detection_frames(root, seq, train / "det_pointrcnn", poses, cfg))
                gkey = fkey + key(cfg, "tubes", "score")
                if gkey not in tubes_cache:
                    gen = tube_generator(cfg, proposer=DETECTIONS)
                    for frame in frames_cache[fkey]:
                        gen.step(frame)
                    tubes_cache[gkey] = gen.finish()
                out = Path(tmp) / str(i)
                write_detection_tubes(root, seq, judge(tubes_cache[gkey], cfg, DETECTIONS), cfg, out / f"{seq}.txt")
                scores[setting][seq] = evaluate_kitti_mot(train / "label_02", out, [seq], CLASSES, seqmap).sums[seq]
            calib = source.calib(seq)
            dets = KittiDetections(train / "det_pointrcnn", seq, source.kitti_calib(seq), (calib.width, calib.height),
                                   base.proposals.kitti_detections)
            write_iou_tracks(Path(tmp) / "iou" / f"{seq}.txt", iou_track(dets, len(read_poses(poses))))
            baseline[seq] = evaluate_kitti_mot(train / "label_02", Path(tmp) / "iou", [seq], CLASSES, seqmap).sums[seq]
            log(f"  {seq}: {len(tubes_cache)} tube generations, {len(settings)} settings, "
                f"{time.perf_counter() - t0:.0f} s")
    return scores, baseline


def _pct(x: float) -> str:
    return f"{100 * x:5.1f}"


def format_report(result: CrossvalResult, settings: Sequence[Setting]) -> list[str]:
    lines = ["Per fold: chosen on the training folds (mean of Car and Pedestrian HOTA), scored on the held-out fold",
             (f"  {'fold':<4} {'held out':<15} {'chosen setting':<62} {'train':>5} | "
              f"{'HOTA C':>6} {'HOTA P':>6} {'MOTA C':>6} {'MOTA P':>6} {'IDSW C':>6} {'IDSW P':>6} | "
              f"{'IoU C':>5} {'IoU P':>5} {'marg C':>6} {'marg P':>6} | {'REF':>5} {'rank':>4} {'elig':>4}")]
    for n, r in enumerate(result.folds, start=1):
        h, b = r.held_out_metrics, r.baseline_metrics
        lines.append(
            f"  {n:<4} {','.join(r.held_out):<15} {r.setting.label:<62} {_pct(r.training_score)} | "
            f"{_pct(h['Car']['HOTA']):>6} {_pct(h['Pedestrian']['HOTA']):>6} "
            f"{_pct(h['Car']['MOTA']):>6} {_pct(h['Pedestrian']['MOTA']):>6} "
            f"{h['Car']['IDSW']:6d} {h['Pedestrian']['IDSW']:6d} | "
            f"{_pct(b['Car']['HOTA'])} {_pct(b['Pedestrian']['HOTA'])} "
            f"{100 * r.margin('Car'):+6.1f} {100 * r.margin('Pedestrian'):+6.1f} | "
            f"{_pct(objective(r.reference_metrics))} {r.held_out_rank:4d}/{len(settings)} {'yes' if r.eligible else 'no':>4}")
    p = result.pooled_held_out
    lines.append(f"  pooled held-out (each sequence under its own fold's choice): HOTA Car {_pct(p['Car']['HOTA'])}, "
                 f"Pedestrian {_pct(p['Pedestrian']['HOTA'])}; MOTA Car {_pct(p['Car']['MOTA'])}, "
                 f"Pedestrian {_pct(p['Pedestrian']['MOTA'])}")
    lines.append("  (train, REF: mean of the two HOTAs; REF = the REFERENCE setting on the held-out fold; rank of the "
                 "chosen setting among the grid on the held-out fold; elig: beats 2D-IoU in both classes and not below REF)")
    lines.append(f"Final setting: {result.final.label}  ({result.final_rule})")
    lines.append("  " + "  ".join(result.final.overrides))
    for n, (fold, m) in enumerate(zip(result.folds, result.final_held_out), start=1):
        lines.append(f"  fold {n} held out {','.join(fold.held_out)}: HOTA Car {_pct(m['Car']['HOTA'])}, "
                     f"Pedestrian {_pct(m['Pedestrian']['HOTA'])}; MOTA Car {_pct(m['Car']['MOTA'])}, "
                     f"Pedestrian {_pct(m['Pedestrian']['MOTA'])}; IDSW {m['Car']['IDSW']}/{m['Pedestrian']['IDSW']}")
    best = sorted(result.cv_score.items(), key=lambda kv: -kv[1])[:5]
    lines.append("Mean held-out score over the folds, best five: " +
                 "; ".join(f"{s.label} {_pct(v).strip()}" for s, v in best))
    return lines


def _metrics_json(m: Mapping[str, Mapping[str, float]]) -> dict[str, dict[str, float]]:
    keep = ("HOTA", "DetA", "AssA", "MOTA", "IDF1", "IDSW", "FP", "FN")
    return {c: {k: m[c][k] for k in keep} for c in CLASSES}


def run_crossval_bench(data: Path, config: str | Path | None, overrides: Sequence[str] = (), k: int = 4,
                       grid: Mapping[str, Sequence[str]] | None = None, sequences: Sequence[str] | None = None,
                       json_out: str | Path | None = None, overwrite: bool = False) -> int:
    """Run the cross-validation and print every fold; 0 when every held-out fold meets the target."""
    seqmap = data / "kitti_tracking" / "training" / "seqmaps" / "train.seqmap"
    frames = read_seqmap(seqmap)
    sequences = list(sequences or frames)
    folds = make_folds({s: frames[s] for s in sequences}, k)
    settings = grid_settings(grid or DEFAULT_GRID)
    print(f"Cross-validation, {k} folds of the {len(sequences)} KITTI training sequences, {len(settings)} settings "
          f"(config {config or 'defaults'}{' ' + ' '.join(overrides) if overrides else ''})")
    for n, f in enumerate(folds, start=1):
        print(f"  fold {n}: {', '.join(f)} ({sum(frames[s] for s in f)} frames)")
    t0 = time.perf_counter()
    scores, baseline = score_grid(data, config, overrides, sequences, settings)
    result = cross_validate(scores, baseline, folds)
    for line in format_report(result, settings):
        print(line)
    misses = [n for n, r in enumerate(result.folds, start=1) if not r.meets_target]
    print(f"Target (held-out HOTA ≥ 2D-IoU + {100 * TARGET_MARGIN:.0f} for Car and Pedestrian): "
          f"{'met on every fold' if not misses else 'missed on fold(s) ' + ', '.join(map(str, misses))}")
    print(f"  ({time.perf_counter() - t0:.0f} s)")
    if json_out:
        doc: dict[str, Any] = {
            "folds": [{"held_out": r.held_out, "setting": list(r.setting.overrides), "training_score": r.training_score,
                       "training": _metrics_json(r.training_metrics), "held_out_metrics": _metrics_json(r.held_out_metrics),
                       "baseline": _metrics_json(r.baseline_metrics), "reference": _metrics_json(r.reference_metrics),
                       "held_out_rank": r.held_out_rank, "eligible": r.eligible, "meets_target": r.meets_target}
                      for r in result.folds],
            "final": list(result.final.overrides), "final_rule": result.final_rule,
            "final_held_out": [_metrics_json(m) for m in result.final_held_out],
            "pooled_held_out": _metrics_json(result.pooled_held_out),
            "cv_score": {" ".join(s.overrides): v for s, v in result.cv_score.items()},
        }
        safe_files.write_file(json_out, json.dumps(doc, indent=1).encode(), overwrite)
    return 0 if not misses else 1


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine bench crossval``'s options (a config and overrides of its own: the grid overrides them)."""
    p.add_argument("--config", type=input_file, default=str(REPO / "jobs" / "kitti-detections.toml"),
                   help="job config TOML the grid overrides (default: jobs/kitti-detections.toml)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config value")
    add_data_option(p)
    p.add_argument("--folds", type=count(2, 100), default=4, help="number of folds (default 4)")
    p.add_argument("--grid", action="append", default=[], metavar="KEY=V1,V2,...",
                   help="a grid axis, REFERENCE value first; repeat for more (default: mining/bench/crossval.py "
                        "DEFAULT_GRID)")
    p.add_argument("--sequences", nargs="+", default=None, help="default: the twelve training sequences")
    p.add_argument("--json", type=output_file, help="also write the results as JSON here")
    add_overwrite_option(p, "the --json file")


def run(args: argparse.Namespace) -> int:
    """``mine bench crossval``."""
    return run_crossval_bench(Path(args.data), args.config, args.set, k=args.folds,
                              grid=parse_grid(args.grid) if args.grid else None, sequences=args.sequences,
                              json_out=args.json, overwrite=args.overwrite)
