"""``mine bench calibrate``: fit the calibrated unary on synthetic truth, leave-one-seed-out.

Issue 18 (scope 4): clutter is to be rejected on evidence, with the scoring calibrated as a
likelihood ratio on synthetic truth and chosen by leave-seeds-out cross-validation.

1. **Tubes.** Each training seed is mined with the job's config (its proposer, its tube
   generation); every candidate tube is kept, with the frame truths.
2. **Labels** (``mining.eval.tube_labels``): object (IoU ≥ 0.5 with an evaluated object in
   most of its frames) against part or clutter; tubes on ignored objects (too small or too
   far for the protocol) and outside the truth are left out of the fit.
3. **Fit** (``fit_log_odds``): the calibrated unary θ = w₀ + Σ_t w·φ_t
   (``mining.score.calibrated``) is linear in the tube's summed evidence, so a logistic
   regression on (1, Σ_t φ_t) is its maximum-likelihood fit: θ is then the log-odds of
   "object" among the candidates, a likelihood ratio times the candidates' prior odds. A
   weak L2 penalty on the standardised evidence (not on w₀) keeps collinear terms (a
   log-size and its square) finite. Object tubes on unknown objects are weighted so that
   they count as much in total as those on known ones (``balance_weights``): the training
   seeds' objects are mostly COCO classes, and a fit on them as they come learns that an
   object is what the classifier recognises (leave-one-seed-out, unbalanced: unknown frame
   recall 0.25 → 0.06).
4. **Leave one seed out.** For each training seed, the weights are fit on the others and the
   held-out seed's tubes are judged again (co-selection with ε1 = ``epsilon1``, 0 by default:
   selected alone when more likely an object than not, and overlap weight ε2 = ``epsilon2``,
   3 by default: ``select.overlap_weight.calibrated``), then scored by the synthetic
   protocol beside the job's own judgement of the same tubes: HOTA, frame recall (known /
   unknown), clutter share of the selected tubes, and the ranking quality of the unary on
   all candidates (ROC AUC of object vs the rest) for both.
5. **Weights** fit on all training seeds, printed as the TOML table for
   ``score.calibrated."<proposer>"``; the held-out seeds of ``mine eval synthetic`` are the test.
   ``--write`` records them, with how they were made (``unary_fit``), as the proposer's default:
   the ``[unary]`` table of ``mining/score/fits/<proposer>.toml`` (``mining.score.fits``).

The tubes come from the job's tube generation with REFERENCE's unary ranking tube NMS
(``score.model`` is set to "reference" for it, so a fit never depends on the weights it is to
replace); judging them again with the calibrated unary leaves tube NMS as it was (a ``mine
eval synthetic`` run with the calibrated model ranks with it too). "job" in the report is
REFERENCE's judgement of the same tubes.
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from mining.bench.calling import run_calling_bench
from mining.bench.fit import (L2, balance_weights, check_seeds, command_line, fit_log_odds, provenance, roc_auc,
                              write_fit)
from mining.bench.synthetic import run_synthetic
from mining.catalog import safe_files
from mining.checks import count, finite_float, output_file, output_folder, positive_float, real, worker_count
from mining.config import JobConfig, validate
from mining.errors import MiningError
from mining.eval.synthetic import evaluate_synthetic
from mining.eval.tube_labels import label_tubes
from mining.pipeline.arguments import add_job_options, add_overwrite_option, job_config
from mining.pipeline.mine import judge, unary
from mining.score.calibrated import TERMS, tube_evidence
from mining.score.fits import FITS_DIR, UNARY_FIT
from mining.types import Tube

EPSILON1 = 0.0  # ours: log-odds 0 — a tube alone is selected when it is more likely an object than not
EPSILON2 = 3.0  # ours: the calibrated unary's overlap weight (select.overlap_weight.calibrated)


def _mine_seed(args) -> tuple[str, list[Tube], dict, float]:
    seed, n_frames, cfg = args
    mined, results = run_synthetic(seed, n_frames, cfg)
    return seed, [m.tube for m in mined], results["truths"], results["seconds"]["mine"]


def _summary(res: dict) -> dict:
    a, k, u, t = res["all"], res["known"], res["unknown"], res["tubes"]
    return {"HOTA": a["HOTA"], "MOTA": a["MOTA"], "frame_recall": a["frame_recall"],
            "known_frame_recall": k["frame_recall"], "unknown_frame_recall": u["frame_recall"],
            "unknown_tube_recall": u["tube_recall"], "clutter_share": t["clutter_share"], "selected": t["evaluated"],
            "known_called_known": t.get("known_called_known_share"),
            "unknown_called_unknown": t.get("unknown_called_unknown_share")}


def calibrated_config(cfg: JobConfig, weights: dict[str, float], epsilon1: float = EPSILON1,
                      epsilon2: float = EPSILON2) -> JobConfig:
    """``cfg`` with the calibrated unary for its proposer, co-selection price ``epsilon1`` and overlap weight ``epsilon2``."""
    out = copy.deepcopy(cfg)
    out.score.model = "calibrated"
    out.score.calibrated = {**out.score.calibrated, cfg.proposals.proposer: weights}
    out.select.price.calibrated = float(epsilon1)
    out.select.overlap_weight.calibrated = float(epsilon2)
    validate(out, "calibrated config")
    return out


def check_fit_data(data: dict[str, dict], train: Sequence[str], n_frames: int, held_out: str | None = None) -> None:
    """MiningError naming what is missing when the tubes of the seeds ``train`` cannot be fit:
    a logistic fit needs object tubes and part or clutter tubes (few frames give neither)."""
    n_object = sum(int(data[s]["y"].sum()) for s in train)
    n_other = sum(int((~data[s]["y"]).sum()) for s in train)
    if n_object and n_other:
        return
    missing = " and no ".join(k for k, n in (("object tube", n_object), ("part or clutter tube", n_other)) if not n)
    fold = f" (the fold holding out {held_out})" if held_out is not None else ""
    raise MiningError(f"too few frames to fit: seeds {', '.join(train)}{fold} gave no {missing} in {n_frames} "
                      f"frames each ({n_object} object, {n_other} part or clutter tubes); the fit needs both: raise "
                      "--frames or add --seeds")


def run_calibrate_bench(cfg: JobConfig, seeds: Sequence[str], n_frames: int, workers: int = 1,
                        l2: float = L2, epsilon1: float = EPSILON1, epsilon2: float = EPSILON2, balance: bool = True,
                        json_out: str | None = None, overwrite: bool = False, write: str | Path | None = None,
                        command: str = "") -> int:
    """Mine, fit and report (module docstring); ``write``: the folder of fit files whose
    ``<proposer>.toml`` takes the weights fit on all seeds (``command``: what was run, recorded with them)."""
    check_seeds(seeds)
    t0 = time.perf_counter()
    print(f"calibrate: mining {len(seeds)} seed(s) × {n_frames} frames, proposer {cfg.proposals.proposer}, "
          f"{workers} worker(s)")
    # the tubes come from REFERENCE's unary (it ranks tube NMS), so the fit never depends on the weights it replaces
    cfg = copy.deepcopy(cfg)
    cfg.score.model = "reference"
    jobs = [(s, n_frames, cfg) for s in seeds]
    if workers > 1:
        with ProcessPoolExecutor(workers) as pool:
            mined = list(pool.map(_mine_seed, jobs))
    else:
        mined = [_mine_seed(j) for j in jobs]
    data = {}
    for seed, tubes, truths, secs in mined:
        labels = label_tubes(tubes, truths)
        keep = [t for t in tubes if labels[t.tube_id].label in ("object", "part", "clutter")]
        x = np.array([tube_evidence(t, cfg.score.floor) for t in keep]).reshape(-1, len(TERMS))
        y = np.array([labels[t.tube_id].label == "object" for t in keep], bool)
        unknown = np.array([labels[t.tube_id].object_known is False for t in keep], bool)
        data[seed] = {"tubes": tubes, "truths": truths, "keep": keep, "x": x, "y": y, "unknown": unknown,
                      "labels": labels}
        counts = {k: sum(1 for v in labels.values() if v.label == k) for k in ("object", "part", "clutter", "ignored")}
        print(f"  seed {seed}: {len(tubes)} candidate tubes ({counts}), mined in {secs:.0f} s")

    for held in seeds:  # before any fit: every fold, and the final fit on all seeds, has both kinds of tube
        check_fit_data(data, [s for s in seeds if s != held], n_frames, held)
    own = unary(cfg)
    rows = []
    for held in seeds:
        train = [s for s in seeds if s != held]
        x = np.concatenate([data[s]["x"] for s in train])
        y = np.concatenate([data[s]["y"] for s in train])
        sw = balance_weights(y, np.concatenate([data[s]["unknown"] for s in train])) if balance else None
        w = fit_log_odds(x, y, l2, sw)
        weights = dict(zip(TERMS, map(float, w)))
        d = data[held]
        auc_cal = roc_auc(d["x"] @ w, d["y"])
        auc_own = roc_auc(np.array([own(t).total for t in d["keep"]]), d["y"])
        res_own = evaluate_synthetic(judge(d["tubes"], cfg), d["truths"])
        res_cal = evaluate_synthetic(judge(d["tubes"], calibrated_config(cfg, weights, epsilon1, epsilon2)), d["truths"])
        rows.append({"held_out": held, "auc": {"job": auc_own, "calibrated": auc_cal},
                     "job": _summary(res_own), "calibrated": _summary(res_cal), "weights": weights})

    x = np.concatenate([data[s]["x"] for s in seeds])
    y = np.concatenate([data[s]["y"] for s in seeds])
    sw = balance_weights(y, np.concatenate([data[s]["unknown"] for s in seeds])) if balance else None
    final = dict(zip(TERMS, map(float, fit_log_odds(x, y, l2, sw))))
    _print(rows, final, cfg, seeds, int(y.sum()), int((~y).sum()), epsilon1, epsilon2)
    print(f"calibrate: {time.perf_counter() - t0:.0f} s")
    if json_out:
        doc = {"proposer": cfg.proposals.proposer, "seeds": list(seeds), "n_frames": n_frames, "l2": l2,
               "epsilon1": epsilon1, "epsilon2": epsilon2, "balance": balance, "folds": rows, "weights": final,
               "tubes": {"object": int(y.sum()), "part_or_clutter": int((~y).sum())}}
        safe_files.write_file(json_out, json.dumps(doc, indent=1).encode(), overwrite)
    if write is not None:
        table = unary_fit(final, rows, y, np.concatenate([data[s]["unknown"] for s in seeds]), cfg.proposals.proposer,
                          seeds, n_frames, command, l2, balance, epsilon1, epsilon2)
        print(f"calibrate: wrote {write_fit(cfg.proposals.proposer, UNARY_FIT, table, write)}")
    return 0


def unary_fit(final: dict[str, float], rows: Sequence[dict], y: np.ndarray, unknown: np.ndarray, proposer: str,
              seeds: Sequence[str], n_frames: int, command: str, l2: float = L2, balance: bool = True,
              epsilon1: float = EPSILON1, epsilon2: float = EPSILON2) -> dict:
    """The ``[unary]`` fit table ``--write`` records: provenance, the tubes it was fit on (``y``:
    object or not; ``unknown``: on an unknown object), the folds' mean AUC (calibrated and the job's
    REFERENCE unary on the same tubes) and the weights fit on all seeds."""
    y = np.asarray(y, bool)
    note = (f"l2 {l2:g}; unknown objects' tubes {'weighted up to the known ones' if balance else 'as they come'}; "
            f"folds judged at ε1 {epsilon1:g}, ε2 {epsilon2:g}")
    return {**provenance(command, proposer, seeds, n_frames, note),
            "samples": {"object": int(y.sum()), "object_on_unknown": int((y & np.asarray(unknown, bool)).sum()),
                        "part_or_clutter": int((~y).sum())},
            "auc": {"mean": round(float(np.nanmean([r["auc"]["calibrated"] for r in rows])), 3),
                    "reference_mean": round(float(np.nanmean([r["auc"]["job"] for r in rows])), 3)},
            "weights": {k: float(final[k]) for k in TERMS}}


def _print(rows: list[dict], final: dict, cfg: JobConfig, seeds: Sequence[str], n_pos: int, n_neg: int,
           epsilon1: float, epsilon2: float) -> None:
    keys = ("HOTA", "frame_recall", "known_frame_recall", "unknown_frame_recall", "clutter_share", "selected",
            "known_called_known")
    head = ("AUC",) + keys
    print(f"\nLeave one seed out (job = REFERENCE's unary and co-selection on the same tubes; calibrated with ε1 = {epsilon1:g}, "
          f"ε2 = {epsilon2:g}):")
    print(f"  {'held out':8} {'unary':10} " + " ".join(f"{h[:12]:>12}" for h in head))

    def fmt(v):
        return f"{v:12.3f}" if isinstance(v, float) and np.isfinite(v) else f"{str(v):>12}"

    for r in rows:
        for which in ("job", "calibrated"):
            vals = [r["auc"][which]] + [r[which][k] for k in keys]
            print(f"  {r['held_out']:8} {which:10} " + " ".join(fmt(v) for v in vals))
    for which in ("job", "calibrated"):
        mean = [float(np.nanmean([r["auc"][which] for r in rows]))]
        mean += [float(np.nanmean([np.nan if r[which][k] is None else r[which][k] for r in rows])) for k in keys]
        print(f"  {'mean':8} {which:10} " + " ".join(fmt(v) for v in mean))
    print(f"\nWeights fit on all {len(seeds)} seeds ({n_pos} object tubes, {n_neg} part or clutter):")
    print(f'[score.calibrated."{cfg.proposals.proposer}"]  # mine bench calibrate --seeds {" ".join(seeds)}')
    for k, v in final.items():
        print(f"{k} = {v:.6g}")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``mine bench calibrate``'s options."""
    add_job_options(p)
    p.add_argument("--seeds", nargs="+", default=["0000", "0001", "0002", "0003", "0004", "0005", "0006"],
                   help="synthetic training seeds, one fold each (default 0000–0006; 0007–0009 are held out)")
    p.add_argument("--frames", type=count(), default=100, help="frames per seed (default 100)")
    p.add_argument("--workers", type=worker_count, default=1, help="seeds mined in parallel processes (default 1)")
    p.add_argument("--l2", type=positive_float(1e6), default=L2,
                   help="L2 penalty on the standardised evidence, > 0 (default 1)")
    p.add_argument("--epsilon1", type=finite_float(1e3), default=EPSILON1,
                   help="co-selection price for the calibrated unary in the folds (default 0: log-odds 0)")
    p.add_argument("--epsilon2", type=real(0.0, 1e3), default=EPSILON2,
                   help="overlap weight for the calibrated unary in the folds (default 3)")
    p.add_argument("--no-balance", action="store_true",
                   help="do not weigh unknown objects' tubes up to the known ones' total")
    p.add_argument("--calling", action="store_true",
                   help="fit what calls a tube unknown instead (issue 29: the classifier rows' calibrated confidence "
                        "and the object evidence, mining/bench/calling.py), leave-one-seed-out")
    p.add_argument("--cache", type=output_folder, metavar="DIR", default=None,
                   help="with --calling: keep each mined seed here as NPZ and read it back on the next run with the "
                        "same proposer, seed and frames (delete it after changing the pipeline)")
    p.add_argument("--write", type=output_folder, nargs="?", const=FITS_DIR, default=None, metavar="DIR",
                   help="record the weights fit on all seeds, with how they were made, as the proposer's defaults: "
                        "mining/score/fits/<proposer>.toml (with --calling: its object evidence, and rows.toml), "
                        "or the fit files in DIR")
    p.add_argument("--json", type=output_file, help="also write the results as JSON here")
    add_overwrite_option(p, "the --json file")


def run(args: argparse.Namespace) -> int:
    """``mine bench calibrate``."""
    if args.calling:
        check_seeds(args.seeds)
        return run_calling_bench(job_config(args), args.seeds, args.frames, cache=args.cache, l2=args.l2,
                                 json_out=args.json, overwrite=args.overwrite, write=args.write,
                                 command=command_line())
    return run_calibrate_bench(job_config(args), args.seeds, args.frames, workers=args.workers, l2=args.l2,
                               epsilon1=args.epsilon1, epsilon2=args.epsilon2, balance=not args.no_balance,
                               json_out=args.json, overwrite=args.overwrite, write=args.write, command=command_line())
