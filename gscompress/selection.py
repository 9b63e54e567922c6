"""Budgeted selection of Gaussians: the scores each strategy ranks by, and exact top-K.

Pruning (keep a fraction of a map) and sharing (send a fraction of a map) are the same
operation: rank by a score, keep the K best. Both go through `select_top`, or `select_count` when
K comes from elsewhere (a byte budget, see `gscompress.ops.budget`).

Rounding: K = floor(ratio * N + 0.5), i.e. round half up (with a 1e-9 guard against binary
floating point, so 0.35 * 10 keeps 4). A ratio that rounds to zero Gaussians is an error rather
than an empty map.

Ties: Gaussians with equal scores are ranked by ascending id, so a selection does not depend on
the order the Gaussians are stored in.
"""

from __future__ import annotations

import math
from enum import Enum

import numpy as np

from gscompress.errors import BudgetError, InputError
from gscompress.gaussians import GaussianMap
from gscompress.seeds import seeded_rng


class Strategy(str, Enum):
    """What a selection ranks Gaussians by."""

    PWAS = "pwas"
    """Proximity-weighted accumulated alpha*T (the paper's importance score)."""
    OPACITY = "opacity"
    """Opacity (equivalently its logit)."""
    RANDOM = "random"
    """Uniformly random, seeded."""
    ALPHA_T = "alpha-t"
    """Unweighted sum of alpha*T over all views (LightGaussian / Mini-Splatting style)."""


STRATEGIES = tuple(s.value for s in Strategy)


def is_fraction(value: object) -> bool:
    """True for a finite number in (0, 1]: a retention ratio, a budget fraction."""
    return isinstance(value, int | float) and math.isfinite(value) and 0.0 < value <= 1.0


def percent_hint(number: float) -> str:
    """What a number given for a fraction may have meant when it reads as a percentage (above 1,
    up to 100): "0.3 or 30%" for 30; else ""."""
    if not (math.isfinite(number) and 1.0 < number <= 100.0):
        return ""
    return f"{number / 100:g} or {number:g}%"


def check_ratio(ratio: float, name: str = "ratio", options: tuple[str, ...] = ()) -> float:
    """Return `ratio` if it lies in (0, 1], else raise InputError (naming it `name`, which
    names the parameters `options`, as `GscError`'s)."""
    if not is_fraction(ratio):
        raise InputError(f"{name} must be in (0, 1], got {ratio}", options=options)
    return float(ratio)


def keep_count(n: int, ratio: float, what: str = "ratio", options: tuple[str, ...] = ()) -> int:
    """Number of Gaussians kept out of `n` for a retention `ratio` in (0, 1] (round half up);
    `what` names the ratio in the error when that is none (a budget, for a share), and the
    parameters `options` (as `GscError`'s)."""
    check_ratio(ratio)
    k = min(n, math.floor(ratio * n + 0.5 + 1e-9))
    if n > 0 and k == 0:
        raise BudgetError(
            f"keeping {ratio:g} of {n} Gaussians rounds to none; raise the {what}", options=options
        )
    return k


def check_strategy(strategy: str | Strategy) -> Strategy:
    """The strategy called `strategy`.

    Raises:
        InputError: not one of `STRATEGIES`.
    """
    try:
        return Strategy(strategy)
    except ValueError:
        raise InputError(
            f"unknown strategy {strategy!r}; choose one of {', '.join(STRATEGIES)}"
        ) from None


def strategy_scores(gaussians: GaussianMap, strategy: str | Strategy, seed: int = 0) -> np.ndarray:
    """[N] float64 scores for `strategy`; higher is more important.

    Raises:
        InputError: unknown strategy, or a negative seed for the random one.
        BudgetError: an empty map, or no scores for a score-based strategy.
    """
    strategy = check_strategy(strategy)
    if len(gaussians) == 0:  # (which would read as a map without scores below)
        raise BudgetError("the map is empty: there is nothing to select from")
    if strategy is Strategy.PWAS:
        if not gaussians.has_importance:
            raise BudgetError(
                "this map has no PWAS scores: record it with `gsc slam`, or score an existing "
                "map with `gsc score MAP --seq SEQ`, or rank by another score (`by` opacity)",
                options=("by",),
            )
        return gaussians.importance.astype(np.float64)
    if strategy is Strategy.ALPHA_T:
        if not np.any(gaussians.alpha_t_sum > 0):
            raise BudgetError(
                "this map has no alpha*T sums: record it with `gsc slam` or `gsc score`"
            )
        return gaussians.alpha_t_sum.astype(np.float64)
    if strategy is Strategy.OPACITY:
        return gaussians.opacity_logits.astype(np.float64)
    return seeded_rng(seed).random(len(gaussians))


def top_k(scores: np.ndarray, ids: np.ndarray, k: int) -> np.ndarray:
    """Indices of the `k` highest scores, ties broken by ascending id, in ascending index order.

    Runs in O(N) plus O(T log T) for the T entries tied at the threshold.

    Args:
        scores: [N] scores (higher is better).
        ids: [N] unique ids used to break ties.
        k: how many to keep, 0 <= k <= N.

    Returns:
        [k] int64 indices into `scores`, sorted ascending (so the kept map keeps storage order).
    """
    n = scores.shape[0]
    if not 0 <= k <= n:
        raise BudgetError(f"cannot keep {k} of {n}")
    if k == n:
        return np.arange(n, dtype=np.int64)
    if k == 0:
        return np.zeros(0, dtype=np.int64)
    return _top_from(scores, ids, k, np.partition(scores, n - k)[n - k])


def _top_from(scores: np.ndarray, ids: np.ndarray, k: int, threshold: float) -> np.ndarray:
    """`top_k` given its threshold, the (N - k)-th smallest score (0 < k < N)."""
    above = scores > threshold
    tied = np.flatnonzero(scores == threshold)
    need = k - np.count_nonzero(above)
    if need == len(tied):  # (every tied one: already in ascending order)
        return np.flatnonzero(scores >= threshold)
    tied = tied[np.argsort(ids[tied], kind="stable")[:need]]
    return np.sort(np.concatenate([np.flatnonzero(above), tied]))


SPREAD_LEVELS = 32
"""How many times `spread_ranks` halves its grid (cells of 1/2^32 of the map's extent: finer
than float32 centres tell apart); entries that share a cell even then come last."""


def spread_ranks(scores: np.ndarray, ids: np.ndarray, means: np.ndarray) -> np.ndarray:
    """[N] int64 rank of each entry (0 first) when a selection is spread over space.

    Space is cut by ever finer grids (a cube of the map's extent, then halves, quarters, ...
    of its edge). An entry's level is the coarsest grid in which it is the best of its cell
    (highest score, then lowest id); the ranks go by level, then score, then id. The first K
    entries are then the best of K distinct places before any place gets a second one: the K
    best scores when they lie apart, one per cell of a grid when they cluster. The grids nest,
    so an entry that wins its cell wins every finer cell too, and a larger K keeps everything
    a smaller one kept.

    Args:
        scores: [N] scores (higher is better).
        ids: [N] unique ids used to break ties.
        means: [N, 3] positions.
    """
    n = len(scores)
    order = np.lexsort((ids, -scores))  # best first
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n)
    level = np.full(n, SPREAD_LEVELS + 1, dtype=np.int64)
    if n == 0:
        return rank
    points = np.asarray(means, dtype=np.float64)
    low = points.min(axis=0)
    extent = float((points.max(axis=0) - low).max())
    if not math.isfinite(extent) or extent <= 0:
        return rank  # one place: the scores alone
    for k in range(SPREAD_LEVELS + 1):
        cells = np.floor((points - low) / (extent / 2**k)).astype(np.int64)
        _, cell = np.unique(cells, axis=0, return_inverse=True)
        cell = cell.ravel()
        by_cell = np.lexsort((rank, cell))  # each cell's best first
        best = by_cell[np.r_[True, cell[by_cell][1:] != cell[by_cell][:-1]]]
        level[best] = np.minimum(level[best], k)
        if len(best) == n:
            break
    ranked = np.lexsort((rank, level))
    out = np.empty(n, dtype=np.int64)
    out[ranked] = np.arange(n)
    return out


def select_top(
    gaussians: GaussianMap, ratio: float, strategy: str | Strategy = Strategy.PWAS, seed: int = 0
) -> tuple[GaussianMap, np.ndarray]:
    """Keep the round(ratio * N) most important Gaussians of a map.

    Args:
        gaussians: the map.
        ratio: fraction to keep, in (0, 1].
        strategy: what to rank by (see `Strategy`).
        seed: random seed for `Strategy.RANDOM`.

    Returns:
        The kept map and the [K] indices of the kept Gaussians in the input.
    """
    return select_count(gaussians, keep_count(len(gaussians), ratio), strategy, seed)


def select_count(
    gaussians: GaussianMap,
    k: int,
    strategy: str | Strategy = Strategy.PWAS,
    seed: int = 0,
    first: np.ndarray | None = None,
    spread: bool = False,
) -> tuple[GaussianMap, np.ndarray]:
    """Keep the `k` most important Gaussians of a map (a count, e.g. what a byte budget allows).

    `first` ([N] bool) ranks the Gaussians it marks above all the others (each group in the
    strategy's order): what a receiver-aware share sends before anything else. With `spread`,
    the strategy's order is spread over space first (`spread_ranks`).

    Returns:
        The kept map and the [k] indices of the kept Gaussians in the input.
    """
    scores = selection_scores(gaussians, strategy, seed, spread)
    return select_by(gaussians, k, scores, first)


def selection_scores(
    gaussians: GaussianMap, strategy: str | Strategy, seed: int = 0, spread: bool = False
) -> np.ndarray:
    """[N] float64 what a selection ranks by, higher first: the strategy's scores, or with
    `spread` their order spread over space (`spread_ranks`)."""
    scores = strategy_scores(gaussians, strategy, seed)
    if spread:
        scores = -spread_ranks(scores, gaussians.ids, gaussians.means).astype(np.float64)
    return scores


def select_by(
    gaussians: GaussianMap, k: int, scores: np.ndarray, first: np.ndarray | None = None
) -> tuple[GaussianMap, np.ndarray]:
    """The `k` Gaussians with the highest `scores` (`selection_scores`), those `first` marks
    ranked above the rest (`top_k_first`): the kept map and their [k] indices."""
    index = top_index(gaussians, k, scores, first)
    return gaussians.select(index), index


def top_index(
    gaussians: GaussianMap, k: int, scores: np.ndarray, first: np.ndarray | None = None
) -> np.ndarray:
    """[k] int64 ascending indices of the Gaussians `select_by` keeps (without copying them)."""
    if first is None:
        return top_k(scores, gaussians.ids, k)
    return top_k_first(scores, gaussians.ids, k, np.asarray(first, dtype=bool))


class Ranking:
    """`top_index` of one map's scores for many counts (a byte budget's search): from its
    second count on, each takes its threshold from the scores sorted once instead of a
    partition of them (the same indices: the k-th smallest score is the same number either
    way). A single count costs what `top_index` does.

    Args:
        gaussians: the map ranked (its ids break ties).
        scores: [N] scores (`selection_scores`).
        first: [N] bool, the Gaussians ranked above all others (`top_k_first`), or None.
    """

    def __init__(self, gaussians: GaussianMap, scores: np.ndarray, first: np.ndarray | None = None):
        self.gaussians, self.scores, self.first = gaussians, scores, first
        self._sorted: np.ndarray | None = None
        self._asked = 0

    def top(self, k: int) -> np.ndarray:
        """[k] int64 ascending indices: `top_index(gaussians, k, scores, first)`."""
        n = len(self.scores)
        self._asked += 1
        # (a receiver's preference ranks two sets apart: partitioned each time, as top_index)
        if self.first is not None or not 0 < k < n or self._asked < 2:
            return top_index(self.gaussians, k, self.scores, self.first)
        if self._sorted is None:
            self._sorted = np.sort(self.scores)
        return _top_from(self.scores, self.gaussians.ids, k, self._sorted[n - k])


def top_k_first(scores: np.ndarray, ids: np.ndarray, k: int, first: np.ndarray) -> np.ndarray:
    """`top_k` with the entries `first` marks ranked above every other entry.

    Returns:
        [k] int64 indices, sorted ascending.
    """
    if first.shape != scores.shape:
        raise InputError(f"the preferred set has {first.shape[0]} entries for {len(scores)} scores")
    head, rest = np.flatnonzero(first), np.flatnonzero(~first)
    if k <= len(head):
        return np.sort(head[top_k(scores[head], ids[head], k)])
    tail = rest[top_k(scores[rest], ids[rest], k - len(head))]
    return np.sort(np.concatenate([head, tail]))
