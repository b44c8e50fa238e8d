"""``mine bench crossval-scenarios``: the image pipeline's new settings, by leave-seeds-out cross-validation.

Why: the image pipeline has labelled video only for KITTI 0005 frames 0–15 (one clip, mostly
parked cars), so its settings cannot be cross-validated over the KITTI training sequences as
the detections-only ones are (``mining.bench.crossval``). The synthetic scenarios
(``mining.sources.synthetic.scenarios``) are ground truth for the failure modes the settings
exist for (moving objects without flow, far objects), and each seed (``--sequence``) stages
them in another world: other clutter, other parked cars, other speeds and distances. Each seed
is one fold.

* **Score** of a setting on a set of seeds: the mean, over seeds × scenarios × scene flow on
  and off, of HOTA over every staged object (``mining.bench.scenarios``: it counts missed
  targets and clutter tubes alike, so a setting cannot win by starting tubes on everything).
* **Grid**: the settings the image pipeline added to REFERENCE.md's (``DEFAULT_GRID``), each
  axis's first value the REFERENCE behaviour (the setting off).
* **Eligible**: a fold's winner counts only if it does not score below the REFERENCE setting
  on its held-out seed. **Final**: the eligible winner most folds chose; a tie goes to the best
  mean held-out score. With none eligible the REFERENCE setting stays.
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from mining.bench.crossval import Setting, grid_settings, parse_grid
from mining.bench.scenarios import MODES, run_scenario
from mining.catalog import safe_files
from mining.checks import count, input_file, output_file
from mining.config import load_config
from mining.pipeline.arguments import SYNTHETIC_JOB, add_overwrite_option
from mining.sources.synthetic.scenarios import SCENARIOS

DEFAULT_GRID = {
    "tubes.start_hypotheses": ("0", "3"),  # REFERENCE: none (own-motion start only); ours: 3 displacement hypotheses
    "localise.filters.noise_sigmas": ("0", "2"),  # REFERENCE: limits on the point estimate; ours: allow 2σ stereo noise
}
DEFAULT_SEEDS = ("0000", "0001", "0002", "0003")

Scores = dict[Setting, dict[str, list[dict]]]  # setting → seed → run_scenario results


def scenario_score(results: Sequence[dict]) -> float:
    """Mean HOTA over the scenarios and the two flow modes."""
    return float(np.mean([r["modes"][m]["HOTA"] for r in results for m in MODES]))


def moving_recall(results: Sequence[dict]) -> float:
    """Mean tube recall of the moving targets over scenarios × flow modes (reported, not selected on)."""
    vals = [r["modes"][m]["roles"]["moving"]["tube_recall"] for r in results for m in MODES
            if "moving" in r["modes"][m]["roles"]]
    return float(np.mean(vals)) if vals else float("nan")


def _over(scores: Scores, setting: Setting, seeds: Sequence[str], fn=scenario_score) -> float:
    return fn([r for s in seeds for r in scores[setting][s]])


def cross_validate_seeds(scores: Scores, seeds: Sequence[str]) -> dict:
    """Per held-out seed: the setting best on the others, its held-out score, and the final choice."""
    settings = list(scores)
    reference = settings[0]
    folds = []
    for held in seeds:
        training = [s for s in seeds if s != held]
        chosen = max(settings, key=lambda st: (_over(scores, st, training), -settings.index(st)))
        held_scores = {st: _over(scores, st, [held]) for st in settings}
        folds.append({"held_out": held, "setting": chosen, "training": _over(scores, chosen, training),
                      "held_out_score": held_scores[chosen], "reference": held_scores[reference],
                      "recall": _over(scores, chosen, [held], moving_recall),
                      "reference_recall": _over(scores, reference, [held], moving_recall),
                      "rank": 1 + sum(v > held_scores[chosen] for v in held_scores.values()),
                      "eligible": held_scores[chosen] >= held_scores[reference]})
    cv = {st: float(np.mean([_over(scores, st, [s]) for s in seeds])) for st in settings}
    votes = Counter(f["setting"] for f in folds if f["eligible"])
    if votes:
        top = max(votes.values())
        tied = [st for st in settings if votes.get(st) == top]
        final = max(tied, key=lambda st: (cv[st], -settings.index(st)))
        rule = f"chosen by {top} of {len(seeds)} folds" + ("" if len(tied) == 1 else ", tie broken by mean held-out score")
    else:
        final, rule = reference, "no fold's choice was eligible: the REFERENCE setting stays"
    return {"folds": folds, "final": final, "rule": rule, "cv": cv}


def run_crossval_scenarios(config: str | Path | None, overrides: Sequence[str] = (),
                           grid: Mapping[str, Sequence[str]] | None = None, seeds: Sequence[str] = DEFAULT_SEEDS,
                           names: Sequence[str] | None = None, n_frames: int | None = 60, half: bool = True,
                           json_out: str | Path | None = None, overwrite: bool = False) -> int:
    """Score every (setting, seed), cross-validate over the seeds and print every fold."""
    settings = grid_settings(grid or DEFAULT_GRID)
    names = list(names or SCENARIOS)
    print(f"Leave-one-seed-out cross-validation over synthetic seeds {', '.join(seeds)}: {len(settings)} settings, "
          f"scenarios {', '.join(names)}, {n_frames or 'default'} frames{', half size' if half else ''}", flush=True)
    t0 = time.perf_counter()
    scores: Scores = {st: {} for st in settings}
    for st in settings:
        cfg = load_config(config, [*overrides, *st.overrides])
        for seed in seeds:
            scores[st][seed] = [run_scenario(n, cfg, n_frames, seed, half) for n in names]
            print(f"  {st.label:<40} seed {seed}: HOTA {scenario_score(scores[st][seed]):.3f}, moving tube recall "
                  f"{moving_recall(scores[st][seed]):.3f} ({time.perf_counter() - t0:.0f} s)", flush=True)
    res = cross_validate_seeds(scores, seeds)
    print("\nPer fold (held-out seed): chosen on the other seeds by mean HOTA; HOTA and moving tube recall on the "
          "held-out seed, the chosen setting vs REFERENCE (the grid's first)")
    for f in res["folds"]:
        print(f"  seed {f['held_out']}: {f['setting'].label:<40} train {f['training']:.3f} | held-out HOTA "
              f"{f['held_out_score']:.3f} (REF {f['reference']:.3f}), moving recall {f['recall']:.3f} "
              f"(REF {f['reference_recall']:.3f}), rank {f['rank']}/{len(settings)}, "
              f"{'eligible' if f['eligible'] else 'not eligible'}")
    print(f"Final setting: {res['final'].label} ({res['rule']})")
    print("Mean held-out HOTA per setting: " + "; ".join(f"{st.label} {v:.3f}" for st, v in res["cv"].items()))
    print(f"  ({time.perf_counter() - t0:.0f} s)")
    if json_out:
        doc = {"seeds": list(seeds), "scenarios": names, "frames": n_frames, "half": half,
               "per_seed": {" ".join(st.overrides): {s: {"HOTA": scenario_score(r), "moving_tube_recall": moving_recall(r)}
                                                    for s, r in per.items()} for st, per in scores.items()},
               "folds": [f | {"setting": list(f["setting"].overrides)} for f in res["folds"]],
               "final": list(res["final"].overrides), "rule": res["rule"],
               "cv": {" ".join(st.overrides): v for st, v in res["cv"].items()}}
        safe_files.write_file(json_out, json.dumps(doc, indent=1).encode(), overwrite)
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine bench crossval-scenarios``'s options (a config and overrides of its own: the grid overrides them)."""
    p.add_argument("--config", type=input_file, default=None,
                   help="job config TOML the grid overrides (default: jobs/synthetic.toml)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config value")
    p.add_argument("--grid", action="append", default=[], metavar="KEY=V1,V2,...",
                   help="a grid axis, REFERENCE value first (default: mining/bench/crossval_scenarios.py DEFAULT_GRID)")
    p.add_argument("--seeds", nargs="+", default=["0000", "0001", "0002", "0003"], help="synthetic seeds, one fold each")
    p.add_argument("--scenarios", nargs="+", default=None, help="default: all")
    p.add_argument("--frames", type=count(), default=60, help="frames per scenario (default 60)")
    p.add_argument("--full", action="store_true", help="render at 1242x375 instead of half size")
    p.add_argument("--json", type=output_file, help="also write the results as JSON here")
    add_overwrite_option(p, "the --json file")
    if SYNTHETIC_JOB.is_file():
        p.set_defaults(config=str(SYNTHETIC_JOB))


def run(args: argparse.Namespace) -> int:
    """``mine bench crossval-scenarios``."""
    return run_crossval_scenarios(args.config, args.set, grid=parse_grid(args.grid) if args.grid else None,
                                  seeds=args.seeds, names=args.scenarios, n_frames=args.frames, half=not args.full,
                                  json_out=args.json, overwrite=args.overwrite)
