"""Discovery measured on synthetic truth (issue 41): do the tube descriptors, the grouping and a
propagated label find what the tubes on unknown objects really are?

The tubes evaluated are the *selected* tubes whose split is unknown (``synthetic.py`` step 4:
matched, by IoU weight, more to unknown objects than to known ones), each with its **true kind**:
the category of the unknown ground-truth objects it collected the most IoU on in the joint
matching (``synthetic.tube_kinds``). The caller hands over each tube's stored descriptor (the
product's, ``mining/discovery/descriptors.py``), the product's grouping of those tubes
(``group_vectors`` with its defaults for that many tubes; −1 is noise) and each tube's cosine
distance to its group's mean direction (``centre_distances``); this module only scores them
(it imports no stage and no product code: the callers hand it what to measure).

* ``nn_same_kind``: the share of tubes whose nearest *other* evaluated tube (cosine distance over
  the descriptors; ties by row order) has the same true kind. A tube whose kind no other tube
  has cannot score, so it is left out of the share (``nn_counted`` tubes count; those left out
  are ``single_kind_tubes``) but stays a neighbour the others may wrongly find.
* ``group_purity``: Σ over groups of the count of the group's most common kind / Σ grouped
  tubes; noise is left out of it and reported as ``noise_share`` (noise tubes / tubes).
  ``groups``: groups found; ``kinds``: true kinds among the evaluated tubes. NaN when nothing
  is grouped.
* ``propagation``: one tube per group is labelled with its true kind, the product's exemplar
  (the gallery tile: the tube nearest the group's mean direction, smallest centre distance,
  ties by row order); every other evaluated tube, noise included (a researcher's propagation
  reaches them too), takes the kind of its nearest labelled tube (cosine). The share of those
  unlabelled tubes that get their true kind (the labelled ones, right by construction, are not
  counted); ``propagation_grouped`` is the same share over the unlabelled grouped tubes only.
  NaN when nothing is grouped (nothing is labelled).

Chance levels, to read the numbers against: ``nn_chance`` (Σ_k p_k², the share a random
neighbour of the same kind would give) and ``majority_share`` (the most common kind's share:
what one group of everything would score as purity).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence

import numpy as np

MIN_NORM = 1e-12  # ours: a zero vector has no direction; its norm is floored so it divides safely


def unit_rows(vectors: np.ndarray) -> np.ndarray:
    """Rows scaled to unit length (cosine similarity is then a dot product)."""
    v = np.asarray(vectors, np.float64)
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), MIN_NORM)


def nearest(unit: np.ndarray, rows: np.ndarray, among: np.ndarray) -> np.ndarray:
    """For each of ``rows``, the row of ``among`` (not itself) with the largest cosine
    similarity: the nearest by cosine distance (ties: the first in ``among``'s order)."""
    sim = unit[rows] @ unit[among].T
    sim[rows[:, None] == among[None, :]] = -np.inf
    return among[np.argmax(sim, axis=1)]


def nn_same_kind(vectors: np.ndarray, kinds: Sequence[str]) -> tuple[float, int, int]:
    """(share of tubes whose nearest other tube has its kind, tubes counted, tubes of a kind seen once)."""
    kinds_a = np.asarray(kinds, object)
    n = len(kinds_a)
    counts = Counter(kinds_a.tolist())
    counted = np.array([k for k in range(n) if counts[kinds_a[k]] > 1], np.int64)
    if n < 2 or not len(counted):
        return float("nan"), 0, n - len(counted)
    nb = nearest(unit_rows(vectors), counted, np.arange(n))
    return float(np.mean(kinds_a[nb] == kinds_a[counted])), len(counted), n - len(counted)


def group_purity(labels: np.ndarray, kinds: Sequence[str]) -> dict:
    """``group_purity``, ``groups``, ``kinds``, ``noise_share`` of a grouping (−1: noise)."""
    labels = np.asarray(labels, np.int64)
    kinds_a = np.asarray(kinds, object)
    grouped = labels >= 0
    top = sum(Counter(kinds_a[labels == g].tolist()).most_common(1)[0][1] for g in np.unique(labels[grouped]))
    return {"group_purity": top / int(grouped.sum()) if grouped.any() else float("nan"),
            "groups": int(len(np.unique(labels[grouped]))), "kinds": len(set(kinds_a.tolist())),
            "noise_share": float(np.mean(~grouped)) if len(labels) else float("nan")}


def exemplars(labels: np.ndarray, centre_distance: np.ndarray) -> np.ndarray:
    """Per group (in group order), the row nearest its mean direction: the gallery's tile."""
    labels = np.asarray(labels, np.int64)
    d = np.asarray(centre_distance, np.float64)
    return np.array([np.flatnonzero(labels == g)[np.argmin(d[labels == g])] for g in np.unique(labels[labels >= 0])],
                    np.int64)


def propagation(vectors: np.ndarray, kinds: Sequence[str], labels: np.ndarray,
                centre_distance: np.ndarray) -> dict:
    """``propagation`` (every unlabelled tube, noise included), ``propagation_grouped`` (the
    unlabelled grouped tubes) and ``labelled`` (the exemplars labelled, one per group)."""
    labels = np.asarray(labels, np.int64)
    kinds_a = np.asarray(kinds, object)
    seeds = exemplars(labels, centre_distance)
    rest = np.setdiff1d(np.arange(len(kinds_a)), seeds)
    if not len(seeds) or not len(rest):
        return {"propagation": float("nan"), "propagation_grouped": float("nan"), "labelled": int(len(seeds))}
    right = kinds_a[nearest(unit_rows(vectors), rest, seeds)] == kinds_a[rest]
    in_group = labels[rest] >= 0
    return {"propagation": float(np.mean(right)),
            "propagation_grouped": float(np.mean(right[in_group])) if in_group.any() else float("nan"),
            "labelled": int(len(seeds))}


def discovery_metrics(vectors: np.ndarray, kinds: Sequence[str], labels: np.ndarray,
                      centre_distance: np.ndarray) -> dict:
    """The ``discovery`` section of ``mine eval synthetic`` (see the module docstring) over the
    evaluated tubes' descriptors (rows), true kinds, groups and centre distances."""
    kinds = list(kinds)
    n = len(kinds)
    if not (len(vectors) == len(labels) == len(centre_distance) == n):
        raise ValueError(f"discovery metrics need one descriptor, group and centre distance per tube ({n} kinds)")
    counts = Counter(kinds)
    nn, counted, single = nn_same_kind(vectors, kinds)
    out = {"tubes": n, "kind_counts": dict(sorted(counts.items())),
           "nn_same_kind": nn, "nn_counted": counted, "single_kind_tubes": single,
           "nn_chance": sum((c / n) ** 2 for c in counts.values()) if n else float("nan"),
           "majority_share": max(counts.values()) / n if n else float("nan")}
    return out | group_purity(labels, kinds) | propagation(vectors, kinds, labels, centre_distance)


def format_discovery(d: dict) -> str:
    """Two lines of the printed table: the tubes and kinds, then the three measures."""
    def f(x: float) -> str:
        return "—" if x != x else f"{x:.2f}"
    return (f"discovery over {d['tubes']} tubes on unknown objects, {d['kinds']} kinds "
            f"({', '.join(f'{k} {n}' for k, n in d['kind_counts'].items())})\n"
            f"  nn_same_kind {f(d['nn_same_kind'])} (chance {f(d['nn_chance'])}); group_purity "
            f"{f(d['group_purity'])} over {d['groups']} groups, noise {f(d['noise_share'])}; propagation "
            f"{f(d['propagation'])} from {d['labelled']} labelled (grouped only {f(d['propagation_grouped'])})")
