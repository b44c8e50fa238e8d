"""Fitting helpers shared by ``mine bench calibrate`` and its ``--calling`` fit: a penalised
logistic fit, the weights that balance unknown objects against known ones, ROC AUC, the
leave-one-seed-out check on the seeds given, and ``--write``: a fit table with its provenance
into the fit files (``mining.score.fits``)."""

from __future__ import annotations

import shlex
import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import minimize
from scipy.stats import rankdata

from mining.catalog import safe_files
from mining.errors import ConfigError
from mining.score.fits import updated_fit

L2 = 1.0  # ours: penalty on the standardised evidence (a prior of unit variance per standardised weight)


def fit_log_odds(x: np.ndarray, y: np.ndarray, l2: float = L2, sample_weight: np.ndarray | None = None) -> np.ndarray:
    """Weights w (in ``x``'s own units) of P(y=1) = σ(w·x), maximum a-posteriori.

    ``x``'s first column is the constant 1 (w₀, not penalised); the other columns are
    standardised for the fit and the weights mapped back, so the penalty does not depend on
    the terms' units. ``sample_weight`` weighs each row's log-likelihood (default 1).
    """
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    sw = np.ones(len(y)) if sample_weight is None else np.asarray(sample_weight, np.float64)
    mu, sd = x[:, 1:].mean(axis=0), x[:, 1:].std(axis=0)
    sd = np.where(sd > 1e-12, sd, 1.0)
    z = np.column_stack([np.ones(len(x)), (x[:, 1:] - mu) / sd])

    def loss(w):
        s = z @ w
        nll = np.sum(sw * (np.logaddexp(0.0, s) - y * s))
        grad = z.T @ (sw * (1.0 / (1.0 + np.exp(-s)) - y))
        return nll + 0.5 * l2 * w[1:] @ w[1:], grad + l2 * np.concatenate([[0.0], w[1:]])

    w = minimize(loss, np.zeros(z.shape[1]), jac=True, method="L-BFGS-B").x
    out = np.concatenate([[w[0] - np.sum(w[1:] * mu / sd)], w[1:] / sd])
    return out


def balance_weights(y: np.ndarray, unknown: np.ndarray) -> np.ndarray:
    """Row weights giving the unknown objects among the positives the same total weight as the
    known ones (1 elsewhere): the unary is to find objects, known or not, while the training
    seeds' objects are mostly known (a fit on them alone learns "object = a COCO class")."""
    y, unknown = np.asarray(y, bool), np.asarray(unknown, bool) & np.asarray(y, bool)
    w = np.ones(len(y))
    n_known, n_unknown = int((y & ~unknown).sum()), int(unknown.sum())
    if n_known and n_unknown:
        w[unknown] = n_known / n_unknown
    return w


def roc_auc(score: np.ndarray, y: np.ndarray) -> float:
    """P(score of a random positive > that of a random negative), ties half (Mann–Whitney)."""
    score, y = np.asarray(score, np.float64), np.asarray(y, bool)
    n1, n0 = int(y.sum()), int((~y).sum())
    if not n1 or not n0:
        return float("nan")
    ranks = rankdata(score)  # average ranks over ties
    return float((ranks[y].sum() - n1 * (n1 + 1) / 2.0) / (n1 * n0))


def check_seeds(seeds: Sequence[str]) -> None:
    """ConfigError unless ``seeds`` holds at least two distinct seeds: one is held out in
    each fold, and the others are the fold's training data."""
    if len(set(seeds)) < 2:
        raise ConfigError(f"--seeds {' '.join(seeds)}: leave-one-seed-out needs at least two distinct seeds")


def command_line() -> str:
    """The ``mine`` command this process runs, as typed (a fit's provenance)."""
    return shlex.join(["mine", *sys.argv[1:]])


def code_commit() -> str:
    """The commit of the code running (``-dirty`` with uncommitted changes), or "unknown" outside a
    git checkout: a fit's provenance."""
    try:
        done = subprocess.run(["git", "-C", str(Path(__file__).resolve().parent), "describe", "--always", "--dirty"],
                              capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return done.stdout.strip() if done.returncode == 0 and done.stdout.strip() else "unknown"


def provenance(command: str, proposer: str, seeds: Sequence[str], n_frames: int, note: str) -> dict[str, Any]:
    """The provenance keys every fit table starts with (``mining.score.fits``)."""
    return {"command": command, "commit": code_commit(), "proposer": proposer, "seeds": list(seeds),
            "frames": int(n_frames), "note": note}


def fold_range(values: Sequence[float]) -> list[float]:
    """[min, max] of a per-fold figure, to three decimals (a fit's AUC over its folds)."""
    return [round(float(np.nanmin(values)), 3), round(float(np.nanmax(values)), 3)]


def write_fit(name: str, fit: str, table: Mapping[str, Any], folder: str | Path) -> Path:
    """Replace the fit table ``fit`` of fit file ``name`` in ``folder`` (``mining.score.fits.updated_fit``),
    the file's other tables kept; returns the file written."""
    path, text = updated_fit(name, fit, table, folder)
    safe_files.write_file(path, text.encode("utf-8"), overwrite=True)
    return path
