"""Co-selection as a QUBO: choose the binary vector m that maximises mᵀQm.

    Q_ii = θ_i − ε1,        Q_ij = −½·ε2·Σ_t o_t(i, j)  (i ≠ j, t over the frames both tubes span)

Q_ii rewards a tube for its score θ_i; Q_ij ≤ 0 punishes two selected tubes that explain
the same pixels, so selecting both costs ε2·Σ_t o_t (paper Eq. "F(b)", with the sign
flipped: minimising F is maximising mᵀQm). The per-frame overlap o of masks A, B is one of
(``SelectConfig.overlap``):

* REFERENCE (``"iou"``, the default): o = |A∩B| / |A∪B|, the mask IoU, where the boxes'
  IoU > 0.1. A duplicate (the same object twice) costs nearly ε2 a frame, but a part of
  an object (a wheel arch inside a car) only its share of the object's area, ~0.1·ε2, or
  nothing once its box IoU with the object's is under the gate: part and object both win.
* ours (``"min"``): o = |A∩B| / min(|A|, |B|), intersection over the smaller mask, where
  the boxes' intersection over the smaller box > 0.1. A part inside a selected object costs
  ε2 a frame, as a duplicate does, so it loses to the object it belongs to; two distinct
  objects that touch share only boundary pixels and stay cheap (why ε2 stays 30:
  ``mining.select.config``).

The paper prints φ = Σ_t ln IoU; REFERENCE.md sums the IoU itself, as here (ln IoU ≤ 0
would reward overlap).

Solvers, all plain numpy:

* ``solve_exhaustive`` — exact, by enumerating all 2^N selections (N ≤ 26).
* ``solve_multibranch`` — the original's greedy multi-branch search (Schindler et al.,
  ECCV 2006, as used by Leibe et al., TPAMI 2008). Kept as the reference baseline.
* ``solve_large`` — multi-branch, then 1-flip tabu search and a 1/2-flip steepest ascent
  from the multi-branch and greedy results; never worse than multi-branch.
* ``solve`` — production: fix the candidates whose choice is forced, split the rest into
  independent groups (tubes that never overlap do not interact), solve each group
  exactly when small and with ``solve_large`` otherwise.

Every solver accepts any square Q; a non-symmetric Q is replaced by (Q + Qᵀ)/2, which
has the same mᵀQm for every m.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from mining.errors import ConfigError, InputError
from mining.select.config import SelectConfig

EXHAUSTIVE_MAX = 26  # ours: 2^26 selections is about the most enumeration stays practical for
_ENUM_BLOCK = 1 << 22  # ours: values evaluated per numpy block during enumeration (32 MiB)
_TOL = 1e-9  # ours: improvements smaller than this (relative to |Q|) are rounding noise


# --------------------------------------------------------------------------- the energy


def build_qubo(unary: np.ndarray, overlap: np.ndarray, cfg: SelectConfig | None = None,
               model: str = "reference") -> np.ndarray:
    """Q from tube scores and summed pairwise overlaps.

    ``unary[i]`` is tube i's score θ(T_i); ``overlap[i, j]`` is Σ over the frames both
    tubes share in the window of their per-frame overlap o (mask IoU, or intersection over
    the smaller mask; gated frames already left out: ``mining.select.coselect``). Returns Q
    with Q_ii = θ_i − ε1 and Q_ij = −½·ε2·overlap_ij, ε1 and ε2 those of the unary ``model``
    the scores come from (``SelectConfig.energy_weights``).
    """
    cfg = cfg or SelectConfig()
    epsilon1, epsilon2 = cfg.energy_weights(model)
    unary = np.asarray(unary, dtype=np.float64)
    overlap = np.asarray(overlap, dtype=np.float64)
    n = unary.shape[0] if unary.ndim == 1 else -1
    if unary.ndim != 1:
        raise InputError(f"co-selection: unary scores must be a vector, got shape {unary.shape}")
    if overlap.shape != (n, n):
        raise InputError(f"co-selection: overlap must be {n}×{n} for {n} tubes, got shape {overlap.shape}")
    if not (np.isfinite(unary).all() and np.isfinite(overlap).all()):
        raise InputError("co-selection: scores and overlaps must be finite")
    if (overlap < 0).any():
        raise InputError("co-selection: summed mask overlap must not be negative")
    if not np.array_equal(overlap, overlap.T):
        raise InputError("co-selection: overlap matrix must be symmetric")
    if np.any(np.diagonal(overlap) != 0):
        raise InputError("co-selection: overlap of a tube with itself must be 0 (it is not a pair)")
    Q = -0.5 * epsilon2 * overlap
    Q[np.diag_indices(n)] = unary - epsilon1
    return Q


def qubo_value(Q: np.ndarray, m: np.ndarray) -> float:
    """mᵀQm."""
    x = np.asarray(m, dtype=np.float64)
    return float(x @ np.asarray(Q, dtype=np.float64) @ x)


def _symmetric(Q: np.ndarray) -> np.ndarray:
    Q = np.asarray(Q, dtype=np.float64)
    if Q.ndim != 2 or Q.shape[0] != Q.shape[1]:
        raise InputError(f"co-selection: Q must be a square matrix, got shape {Q.shape}")
    if not np.isfinite(Q).all():
        raise InputError("co-selection: Q has non-finite entries")
    return 0.5 * (Q + Q.T)


def _tol(Q: np.ndarray) -> float:
    return _TOL * max(1.0, float(np.abs(Q).max(initial=0.0)))


# --------------------------------------------------------------------------- exact


def _bit_table(k: int) -> np.ndarray:
    """All 2^k selections of k items as rows of 0/1 (row r = binary digits of r)."""
    return ((np.arange(1 << k)[:, None] >> np.arange(k)) & 1).astype(np.float64)


def solve_exhaustive(Q: np.ndarray) -> tuple[np.ndarray, float]:
    """The best m by enumerating every selection; for N ≤ 26.

    The items split into a low and a high half. mᵀQm = lowᵀQ_LL·low + highᵀQ_HH·high
    + 2·lowᵀQ_LH·high, so one matrix product gives the values of a whole block of
    (low, high) combinations.
    """
    return _exhaustive(_symmetric(Q))


def _exhaustive(Q: np.ndarray) -> tuple[np.ndarray, float]:
    n = Q.shape[0]
    if n > EXHAUSTIVE_MAX:
        raise InputError(f"co-selection: exhaustive search takes at most {EXHAUSTIVE_MAX} candidates, got {n}")
    if n == 0:
        return np.zeros(0, dtype=bool), 0.0
    n_hi = n // 2
    n_lo = n - n_hi
    lo, hi = _bit_table(n_lo), _bit_table(n_hi)
    q_ll, q_hh, q_lh = Q[:n_lo, :n_lo], Q[n_lo:, n_lo:], Q[:n_lo, n_lo:]
    v_lo = ((lo @ q_ll) * lo).sum(axis=1)
    v_hi = ((hi @ q_hh) * hi).sum(axis=1)
    cross = 2.0 * lo @ q_lh  # (2^lo, n_hi)
    best_v, best = -np.inf, (0, 0)
    step = max(1, _ENUM_BLOCK // lo.shape[0])
    for h0 in range(0, hi.shape[0], step):
        vals = cross @ hi[h0 : h0 + step].T
        vals += v_lo[:, None]
        vals += v_hi[None, h0 : h0 + step]
        k = int(np.argmax(vals))  # first maximum: ties go to the smaller selection index
        r, c = divmod(k, vals.shape[1])
        if vals[r, c] > best_v:
            best_v, best = float(vals[r, c]), (r, h0 + c)
    m = np.concatenate([lo[best[0]], hi[best[1]]]).astype(bool)
    return m, qubo_value(Q, m)


# --------------------------------------------------------------------------- multi-branch


def multibranch_widths(n: int, cfg: SelectConfig | None = None) -> list[int]:
    """The original's branch width per search level for a problem of n candidates."""
    cfg = cfg or SelectConfig()
    if len(cfg.branch_head_widths) != len(cfg.branch_size_limits) + 1:
        raise ConfigError("select: branch_head_widths needs one entry more than branch_size_limits")
    k = next((i for i, limit in enumerate(cfg.branch_size_limits) if n < limit), len(cfg.branch_size_limits))
    return list(cfg.branch_head_widths[k]) + list(cfg.branch_tail_widths)


def _first_of_each_set(sets: np.ndarray) -> np.ndarray:
    """Indices (ascending) of the first row of each distinct row of a boolean matrix."""
    packed = np.packbits(sets, axis=1)
    words = np.zeros((packed.shape[0], -(-packed.shape[1] // 8) * 8), dtype=np.uint8)
    words[:, : packed.shape[1]] = packed
    words = words.view(np.uint64)  # 64 items per word
    order = np.lexsort(words.T[::-1])
    w = words[order]
    new = np.ones(len(order), dtype=bool)
    new[1:] = (w[1:] != w[:-1]).any(axis=1)
    return np.sort(order[new])


def solve_multibranch(Q: np.ndarray, widths: list[int] | None = None) -> tuple[np.ndarray, float]:
    """The original's greedy multi-branch search.

    From the empty set, level ℓ branches into the widths[ℓ] candidates with the largest
    positive gain (the change of mᵀQm when the candidate is added); below the listed
    levels every branch continues greedily (width 1) until no addition gains. The best
    selection met anywhere in the tree wins. ``widths=[]`` is plain greedy selection.

    The tree is walked one level at a time for all branches at once. Branches that
    reach the same set by different orders are merged: what follows depends on the set
    only, so this returns what the original's depth-first recursion returns.
    """
    Q = _symmetric(Q)
    return _multibranch(Q, multibranch_widths(Q.shape[0]) if widths is None else widths)


def _multibranch(Q: np.ndarray, widths: list[int]) -> tuple[np.ndarray, float]:
    n = Q.shape[0]
    if n == 0:
        return np.zeros(0, dtype=bool), 0.0
    diag = np.diagonal(Q).copy()
    off = Q - np.diag(diag)
    tol = _tol(Q)

    sets = np.zeros((1, n), dtype=bool)
    values = np.zeros(1)
    gains = diag[None, :].copy()  # gain of adding each candidate to each branch's set
    best_v, best_set = 0.0, sets[0]

    def add(rows: np.ndarray, items: np.ndarray) -> None:
        nonlocal sets, values, gains
        sets, values, gains = sets[rows], values[rows] + gains[rows, items], gains[rows] + 2.0 * off[items]
        r = np.arange(rows.size)
        sets[r, items] = True
        gains[r, items] = -np.inf

    for width in widths:
        k = min(int(width), n)
        if k <= 0:
            raise ConfigError(f"multi-branch: branch widths must be positive, got {widths}")
        if k < n:
            top = np.argpartition(-gains, k - 1, axis=1)[:, :k]
        else:
            top = np.broadcast_to(np.arange(n), gains.shape)
        g = np.take_along_axis(gains, top, axis=1)
        rows, cols = np.nonzero(g > tol)
        if rows.size == 0:
            break
        add(rows, top[rows, cols])
        first = _first_of_each_set(sets)
        sets, values, gains = sets[first], values[first], gains[first]
        i = int(np.argmax(values))
        if values[i] > best_v:
            best_v, best_set = float(values[i]), sets[i].copy()

    # greedy completion of every branch (width 1 at every deeper level)
    while sets.shape[0]:
        j = np.argmax(gains, axis=1)
        g = gains[np.arange(j.size), j]
        live = g > tol
        if not live.any():
            break
        rows = np.nonzero(live)[0]
        add(rows, j[rows])
        first = _first_of_each_set(sets)  # greedy branches often converge
        sets, values, gains = sets[first], values[first], gains[first]
        i = int(np.argmax(values))
        if values[i] > best_v:
            best_v, best_set = float(values[i]), sets[i].copy()
    return best_set.copy(), qubo_value(Q, best_set)


# --------------------------------------------------------------------------- local search


def _flip_gains(diag: np.ndarray, field: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Change of mᵀQm when flipping each item alone; field = off·m."""
    return (1.0 - 2.0 * m) * (diag + 2.0 * field)


def _tabu(
    Q: np.ndarray, m0: np.ndarray, iterations: int, stall: int, rng: np.random.Generator, deadline: float
) -> tuple[np.ndarray, float]:
    """1-flip tabu search (Glover-style): always take the best flip that is not tabu,
    even when it loses, so the search walks out of local optima; a flipped item stays
    put for a short, slightly random tenure unless flipping it beats the best so far.
    Stops after ``iterations`` moves, or ``stall`` moves without a new best."""
    n = Q.shape[0]
    diag = np.diagonal(Q).copy()
    off = Q - np.diag(diag)  # symmetric: row i is column i, and rows are contiguous
    tol = _tol(Q)
    m = m0.astype(np.float64)
    s = 1.0 - 2.0 * m  # +1 where a flip adds the item, −1 where it removes it
    delta = _flip_gains(diag, off @ m, m)
    v = qubo_value(Q, m)
    best_m, best_v = m.copy(), v
    tenure = max(1, min(20, n // 4))
    free_at = np.zeros(n, dtype=np.int64)
    jitter = rng.integers(0, 3, size=iterations)
    last_best = 0
    for it in range(iterations):
        if it - last_best > stall:
            break
        i = int(np.argmax(delta))
        if free_at[i] > it and v + delta[i] <= best_v + tol:  # tabu, and no new best: aspiration fails
            i = int(np.argmax(np.where(free_at > it, -np.inf, delta)))
        gain = delta[i]
        if not np.isfinite(gain):  # everything tabu (tiny problems)
            continue
        v += gain
        # flipping i moves every other item's field by Q_ji·(change of m_i)
        delta += (2.0 * s[i]) * s * off[i]
        delta[i] = -gain
        m[i] = 1.0 - m[i]
        s[i] = -s[i]
        free_at[i] = it + tenure + jitter[it]
        if v > best_v + tol:
            best_m, best_v, last_best = m.copy(), v, it
        if it % 256 == 255:  # wash out the rounding that the running updates pick up
            delta, v = _flip_gains(diag, off @ m, m), qubo_value(Q, m)
            if deadline and time.perf_counter() > deadline:
                break
    return best_m.astype(bool), qubo_value(Q, best_m)


def _ascend(Q: np.ndarray, m0: np.ndarray) -> tuple[np.ndarray, float]:
    """Steepest ascent with 1-flips and 2-flips of interacting pairs, to a local optimum.

    Flipping i and j together gains Δi + Δj + 2·Q_ij·s_i·s_j (s = 1 − 2m); for Q_ij = 0 that is
    two separate 1-flips, so only interacting pairs need checking — typically swapping a
    selected tube for an overlapping competitor.
    """
    diag = np.diagonal(Q).copy()
    off = Q - np.diag(diag)
    tol = _tol(Q)
    pi, pj = np.nonzero(np.triu(off, 1))
    q_pair = off[pi, pj]
    m = m0.astype(np.float64)
    field = off @ m
    while True:
        delta = _flip_gains(diag, field, m)
        s = 1.0 - 2.0 * m
        pair = delta[pi] + delta[pj] + 2.0 * q_pair * s[pi] * s[pj] if pi.size else np.zeros(0)
        i = int(np.argmax(delta))
        k = int(np.argmax(pair)) if pair.size else -1
        if k >= 0 and pair[k] > max(delta[i], 0.0) + tol:
            flips = [pi[k], pj[k]]
        elif delta[i] > tol:
            flips = [i]
        else:
            break
        for f in flips:
            field += off[:, f] * (1.0 - 2.0 * m[f])
            m[f] = 1.0 - m[f]
    return m.astype(bool), qubo_value(Q, m)


def solve_large(Q: np.ndarray, cfg: SelectConfig | None = None) -> tuple[np.ndarray, float]:
    """Multi-branch, greedy, then tabu search + 1/2-flip ascent from both; the best wins.

    Starts include the multi-branch result, so the answer is never worse than the
    original's. Deterministic for a given cfg.seed (unless cfg.time_limit_s cuts it short).
    """
    return _large(_symmetric(Q), cfg or SelectConfig())


def _large(Q: np.ndarray, cfg: SelectConfig) -> tuple[np.ndarray, float]:
    n = Q.shape[0]
    if n == 0:
        return np.zeros(0, dtype=bool), 0.0
    rng = np.random.default_rng(cfg.seed)
    deadline = time.perf_counter() + cfg.time_limit_s if cfg.time_limit_s > 0 else 0.0
    iterations, stall = cfg.tabu_iterations, cfg.tabu_stall_iterations
    tol = _tol(Q)

    best_m, best_v = _multibranch(Q, multibranch_widths(n, cfg))
    greedy_m, _ = _multibranch(Q, [])

    def consider(m: np.ndarray) -> None:
        nonlocal best_m, best_v
        m, v = _ascend(Q, m)
        if v > best_v + tol:
            best_m, best_v = m, v

    starts = [best_m.copy()] if np.array_equal(greedy_m, best_m) else [best_m.copy(), greedy_m]
    for start in starts:
        consider(_tabu(Q, start, iterations, stall, rng, deadline)[0])
    for _ in range(cfg.tabu_restarts):
        if deadline and time.perf_counter() > deadline:
            break
        kick = best_m.copy()
        flip = rng.choice(n, size=max(1, n // 10), replace=False)
        kick[flip] = ~kick[flip]
        consider(_tabu(Q, kick, iterations, stall, rng, deadline)[0])
    return best_m, qubo_value(Q, best_m)


# --------------------------------------------------------------------------- production


def connected_groups(graph: csr_matrix) -> list[np.ndarray]:
    """The members of each connected component of an undirected graph (nonzero entries
    are edges), each group in ascending index order, groups in scipy's label order."""
    _, label = connected_components(graph, directed=False)
    order = np.argsort(label, kind="stable")
    return np.split(order, np.nonzero(np.diff(label[order]))[0] + 1)


def fix_forced(Q: np.ndarray) -> np.ndarray:
    """Candidates whose choice cannot matter for the optimum: −1 free, 0 drop, 1 keep.

    Candidate i's gain on being added is Q_ii + 2·Σ_j Q_ij·m_j. If even its best case
    (only the positive Q_ij selected) is ≤ 0, some optimum leaves it out; if its worst
    case is ≥ 0, some optimum takes it. Fixing changes the others' bounds, so repeat
    until nothing changes. In co-selection all Q_ij ≤ 0, so every tube with
    score ≤ ε1 is dropped at once.
    """
    return _fix_forced(_symmetric(Q))


def _fix_forced(Q: np.ndarray) -> np.ndarray:
    n = Q.shape[0]
    diag = np.diagonal(Q).copy()
    off = csr_matrix(Q)  # overlaps are sparse: most tube pairs never meet
    off.setdiag(0.0)
    off.eliminate_zeros()
    pos, neg = off.maximum(0.0), off.minimum(0.0)
    state = np.full(n, -1, dtype=np.int8)
    base = diag.copy()  # diag plus 2·Σ over kept candidates
    while True:
        free = (state < 0).astype(np.float64)
        hi = base + 2.0 * (pos @ free)
        lo = base + 2.0 * (neg @ free)
        drop = (free > 0) & (hi <= 0)
        keep = (free > 0) & (lo >= 0) & ~drop
        if not (drop.any() or keep.any()):
            return state
        state[drop] = 0
        state[keep] = 1
        base += 2.0 * (off @ keep.astype(np.float64))


def solve(Q: np.ndarray, cfg: SelectConfig | None = None) -> tuple[np.ndarray, float]:
    """The production co-selection solver; returns (m as bool array, mᵀQm).

    Exact when every group of interacting, undecided candidates has at most
    cfg.exact_max_candidates members; otherwise ``solve_large`` on the larger groups.
    """
    cfg = cfg or SelectConfig()
    Q = _symmetric(Q)
    n = Q.shape[0]
    if cfg.solver == "exhaustive":
        return _exhaustive(Q)
    if cfg.solver == "multibranch":
        return _multibranch(Q, multibranch_widths(n, cfg))
    if cfg.solver != "auto":
        raise ConfigError(f"select.solver: unknown solver {cfg.solver!r}; known: auto, multibranch, exhaustive")
    if cfg.exact_max_candidates > EXHAUSTIVE_MAX:
        raise ConfigError(f"select.exact_max_candidates: at most {EXHAUSTIVE_MAX}, got {cfg.exact_max_candidates}")

    state = _fix_forced(Q)
    m = state == 1
    free = np.nonzero(state < 0)[0]
    if free.size:
        # the free candidates' sub-problem: kept candidates fold into the diagonal
        sub = Q[np.ix_(free, free)].copy()
        sub[np.diag_indices(free.size)] += 2.0 * Q[np.ix_(free, np.nonzero(m)[0])].sum(axis=1)
        links = sub != 0
        np.fill_diagonal(links, False)
        for members in connected_groups(csr_matrix(links)):
            part = sub[np.ix_(members, members)]
            if members.size == 1:  # a tube that overlaps no undecided tube
                chosen = part[0, 0] > 0
            elif members.size <= cfg.exact_max_candidates:
                chosen = _exhaustive(part)[0]
            else:
                chosen = _large(part, cfg)[0]
            m[free[members]] = chosen
    return m, qubo_value(Q, m)
