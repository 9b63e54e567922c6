"""Folding the Gaussians a prune or a share drops into the ones it keeps.

Dropping 70% of a map leaves holes where the dropped Gaussians drew surface. Folding keeps the
same kept Gaussians (same count, ids and order) but lets each stand for the dropped ones around
it: every dropped Gaussian joins its nearest kept one (by centre) when their centres lie within
`FOLD_REACH` times the sum of their mean scales, and each kept Gaussian becomes the moment-matched
Gaussian of its group (`moment_match`): the weighted mean of the centres, the weighted
covariance of the group about it, the weighted colour, with weights of opacity times mean
scale squared (how much of a view a Gaussian covers), and the group's largest opacity. A
dropped Gaussian farther than that from every kept one is dropped as before. The folded
Gaussian draws what its group drew, so its PWAS numerator and alpha*T sum are the group's sums,
over the kept Gaussian's own visibility weight: its score (Eq. 8) is at least what it was, and
a prune or share still keeps the highest scores.

On tabletop's unpruned map at `--keep 0.3`, folding drew the frames off the keyframes far better
than dropping, and each choice above (the reach, the weights, the largest opacity) did better
than the alternatives tried: a shorter reach or none, the group's weighted opacity or its union,
weights of opacity times scale^0 or ^3 (measured in docs/prune-refine.md, "The fold's choices").
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from gscompress.camera import rotmat_to_quat
from gscompress.gaussians import GaussianMap
from gscompress.io.quantise import column_ranges, morton_codes
from gscompress.selection import Ranking, top_index
from gscompress.threads import cpu_threads

if TYPE_CHECKING:
    from gscompress.ops.refine import MapRefiner

FOLD_REACH = 4.0
"""A dropped Gaussian folds into its nearest kept one when their centres lie within this many
times the sum of their mean scales."""

LOGIT_BOUND = 1e-6
"""Opacities are kept within [bound, 1 - bound] before taking their logit."""

ADDED_SHARE = 1 / 32
"""A fold that starts from an earlier kept set inside its own looks for the nearest of the
Gaussians it adds around those Gaussians (`Folding`) when they are at most this share of the
dropped ones and of that kept set, else by a query of every dropped one. (The balls it looks in
are about as wide as the gaps between the kept Gaussians: around each added one they hold about
N / K of the map's N Gaussians for K kept, all of them when K is 1.)"""

PARALLEL_QUERIES = 16384
"""A k-d tree query of fewer points runs on one thread (for so few, more threads cost more to
start than they save, and wait for each other on a busy machine); larger ones on
`cpu_threads()`."""

BOUNDED_QUERIES = 65536
"""A k-d tree query of at least this many points first bounds their distance (`Folding`)."""

SPATIAL_BITS = 5
"""Bits per axis of the Morton codes the nearest-kept queries are ordered by (3 x 5 bits fit
the 16-bit keys numpy sorts in linear time)."""


def fold_groups(gaussians: GaussianMap, kept: np.ndarray, reach: float = FOLD_REACH) -> np.ndarray:
    """[N] int64: for each Gaussian, the position in `kept` of the kept Gaussian it folds into
    (a kept one into itself), or -1 for a dropped one too far from every kept one."""
    return Folding(gaussians, reach).groups(kept)


def fold(gaussians: GaussianMap, kept: np.ndarray, reach: float = FOLD_REACH) -> GaussianMap:
    """The Gaussians at positions `kept`, each moment-matched to itself and the dropped ones
    that fold into it (module docstring). Same count, order and ids as `gaussians.select(kept)`;
    an isotropic map stays isotropic (the isotropic Gaussian of the same trace)."""
    return Folding(gaussians, reach).fold(kept)


def cut_pool(full: GaussianMap, refine: MapRefiner | None) -> GaussianMap:
    """The map a prune or a share cuts from: `full`, with three scales a Gaussian when `refine`
    refines them so (`RefineOptions.anisotropic`): the fold then keeps each group's covariance
    (`gscompress.ops.fold`) instead of the isotropic Gaussian of its trace."""
    return full.as_anisotropic() if refine is not None and refine.anisotropic else full


def cut_map(
    full: GaussianMap,
    count: int,
    scores: np.ndarray,
    fold: bool,
    first: np.ndarray | None = None,
    folding: Folding | None = None,
    ranking: Ranking | None = None,
) -> GaussianMap:
    """The `count` Gaussians of `full` with the highest `scores` (a strategy's, from
    `selection.selection_scores`: spread over space there if asked), each with the dropped ones
    near it folded into it when `fold` (`gscompress.ops.fold`; same Gaussians, ids and
    order either way). What `gsc prune` keeps and `gsc share` sends. `first` ([N] bool) ranks
    the Gaussians it marks above all the others (a receiver-aware share). `folding`, the
    `Folding` of `full`, folds it when given: a caller that cuts many counts of one map passes
    the same one each time, and likewise `ranking`, the `Ranking` of `scores` and `first`."""
    index = top_index(full, count, scores, first) if ranking is None else ranking.top(count)
    if not fold:
        return full.select(index)
    return (folding or Folding(full)).fold(index)


@dataclass(frozen=True)
class _Nearest:
    """The nearest kept Gaussian of every dropped one, for one kept set."""

    kept: np.ndarray  # [K] int64 positions of the kept Gaussians in the map
    is_kept: np.ndarray  # [N] bool
    index: np.ndarray  # [N] int64 position of the nearest kept one (-1 for the kept ones)
    distance: np.ndarray  # [N] float64 distance to it (inf for the kept ones)
    owner: np.ndarray  # [N] int64 position of the kept one each joins (itself; -1: none)


@dataclass(frozen=True)
class _Folded:
    """A fold's Gaussians, and whom each Gaussian of the map joined."""

    owner: np.ndarray  # [N] int64 position of the kept Gaussian each joined (-1: none)
    row: np.ndarray  # [N] int64 row of each kept Gaussian in `gaussians` (-1: not kept)
    gaussians: GaussianMap


class Folding:
    """The folds of one map (`fold`), one kept set after another: what `gsc prune` folds once
    and a byte budget's search (`gscompress.ops.budget.largest_count_within`) about 15 times.

    Most of a fold's time is finding the nearest kept Gaussian of each dropped one. The search
    folds the K best of one ranking for several K, sets that lie inside each other, and narrows
    around one count: after its first steps a fold adds or removes a few hundred Gaussians to
    the last set that fitted or the last that did not. So each fold starts from the earlier
    sets that lie inside it and hold it (the largest and the smallest):
    - holding it: the nearest in the larger set stands wherever the smaller set keeps it; for
      the Gaussians whose nearest was removed (and those removed), the nearest is the nearer of
      their nearest in the set inside it and the nearest of the Gaussians that set lacks (found
      by a k-d tree query within a bound), or, with no set inside it, a query of the kept set;
    - with none holding it, from the one inside it: the nearest in the larger set is the nearer
      of the smaller set's nearest and the nearest of the Gaussians added, found by a k-d tree
      query of every dropped Gaussian against them or, when they are few (`ADDED_SHARE`), among
      the dropped Gaussians around them.
    Likewise only the groups whose members changed since the earlier fold nearest in size (the
    last, or the nearest on either side of it) are moment-matched again, the others copied. A
    fold gives the same bits whichever folds came before it (ties in distance, which float
    data almost never has, may go to either Gaussian).

    Attributes:
        gaussians: the map folded from.
        reach: `FOLD_REACH`.
    """

    def __init__(self, gaussians: GaussianMap, reach: float = FOLD_REACH):
        self.gaussians, self.reach = gaussians, reach
        self._means = gaussians.means  # (float32: trees and sums widen them to float64, exactly)
        # standard deviations as GaussianMap.scales() rounds them, and their mean (of three
        # equal ones for an isotropic map, rounded as a mean of three)
        self._sigma = np.exp(gaussians.log_scales).astype(np.float64)
        self._scale = np.broadcast_to(self._sigma, (len(gaussians), 3)).mean(axis=1)
        self._done: list[_Nearest] = []  # (the last fold and the nearest sets on each side)
        self._folded: list[_Folded] = []  # (the last fold that moment-matched, and the nearest
        # in size on each side: the groups of a search's next fold are mostly one of theirs)

    def groups(self, kept: np.ndarray) -> np.ndarray:
        """`fold_groups` of the map for `kept`."""
        owner, row = self._owners(np.asarray(kept, dtype=np.int64))
        return row[owner]

    def fold(self, kept: np.ndarray) -> GaussianMap:
        """`fold` of the map into `kept`."""
        kept = np.asarray(kept, dtype=np.int64)
        owner, row = self._owners(kept)
        members = np.flatnonzero(owner >= 0)
        if len(members) == len(kept):  # (nothing folds: the kept Gaussians as they are)
            return self.gaussians.select(kept)
        group = row[owner[members]]  # (of each member)
        last = min(self._folded, key=lambda f: abs(len(f.gaussians) - len(kept)), default=None)
        redo = self._changed(owner, kept, last)
        slot = np.cumsum(redo) - 1
        again = redo[group]
        fresh = np.flatnonzero(redo)
        computed = self._moments(
            members[again], slot[group[again]], self.gaussians.quats[kept[fresh]]
        )
        folded = self._assembled(kept, fresh, computed, last)
        done = _Folded(owner, row, folded)
        smaller = [f for f in self._folded if len(f.gaussians) < len(kept)]
        larger = [f for f in self._folded if len(f.gaussians) > len(kept)]
        self._folded = [done]
        if smaller:
            self._folded.append(max(smaller, key=lambda f: len(f.gaussians)))
        if larger:
            self._folded.append(min(larger, key=lambda f: len(f.gaussians)))
        return folded

    def _owners(self, kept: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """[N] the position of the kept Gaussian each Gaussian of the map joins (a kept one
        itself, -1: none), and [N + 1] the row of each in `kept` (-1 for the others, and last,
        where an owner of -1 looks)."""
        n = len(self.gaussians)
        row = np.full(n + 1, -1, dtype=np.int64)
        row[kept] = np.arange(len(kept))
        is_kept = row[:n] >= 0
        if len(kept) == 0 or is_kept.all():
            owner = np.full(n, -1, dtype=np.int64)
            owner[kept] = kept
            return owner, row
        return self._nearest(kept, is_kept).owner, row

    def _joined(self, points: np.ndarray, index: np.ndarray, distance: np.ndarray) -> np.ndarray:
        """[P] whom each of the dropped Gaussians `points` joins: its nearest kept one `index`
        at `distance` when within the reach, else -1."""
        near = distance <= self.reach * (self._scale[index] + self._scale[points])
        return np.where(near, index, -1)

    def _assembled(
        self,
        kept: np.ndarray,
        fresh: np.ndarray,
        computed: dict[str, np.ndarray],
        last: _Folded | None,
    ) -> GaussianMap:
        """The folded map of the Gaussians at `kept`: at rows `fresh`, the groups `computed`
        (`_moments`; checked by `GaussianMap.validate`), at the others the groups of an earlier
        fold (`last`, also checked); the fields a fold leaves, the kept Gaussians' own."""
        names = [f.name for f in fields(GaussianMap) if f.name not in computed]
        left = {name: getattr(self.gaussians, name)[kept] for name in names}
        if len(fresh) == len(kept):  # (every group computed: the map is what is checked)
            return GaussianMap(**left, **computed).validate()
        GaussianMap(**{name: v[fresh] for name, v in left.items()}, **computed).validate()
        assert last is not None  # (the other groups as the earlier fold left them)
        rows = last.row[kept]  # (-1 for a Gaussian not kept then: one computed anew)
        for name, values in computed.items():
            computed[name] = getattr(last.gaussians, name)[rows]
            computed[name][fresh] = values
        return GaussianMap(**left, **computed)

    def _changed(self, owner: np.ndarray, kept: np.ndarray, last: _Folded | None) -> np.ndarray:
        """[K] whether each kept Gaussian's group differs from its group in the fold `last` (or
        it was not kept then; all when None): the groups a fold computes, the others it copies."""
        if last is None:
            return np.ones(len(kept), dtype=bool)
        moved = np.flatnonzero(owner != last.owner)
        touched = np.zeros(len(owner), dtype=bool)
        for who in (owner[moved], last.owner[moved]):
            touched[who[who >= 0]] = True
        return touched[kept] | (last.row[kept] < 0)

    def _moments(
        self, members: np.ndarray, g: np.ndarray, quats: np.ndarray
    ) -> dict[str, np.ndarray]:
        """The folded parameters of the groups `g` [M] (0..k-1) of the Gaussians `members` [M]
        (ascending), as float32 fields of a `GaussianMap`; `quats` [k] the kept ones' own."""
        k = len(quats)
        weights = self._weights[members]
        means = np.take(self._means, members, axis=0)
        mean, cov = moment_match(weights, means, self._spreads[members], g, k)
        opacity = np.zeros(k)
        np.maximum.at(opacity, g, self._opacities[members])
        opacity = np.clip(opacity, LOGIT_BOUND, 1.0 - LOGIT_BOUND)
        if self.gaussians.isotropic:  # (the trace, summed in np.trace's order)
            trace = cov[:, 0] + cov[:, 1] + cov[:, 2]
            log_scales = 0.5 * np.log(trace / 3.0)[:, None]
        else:
            variances, axes = np.linalg.eigh(cov)
            axes[np.linalg.det(axes) < 0, :, 2] *= -1.0  # (a rotation, not a reflection)
            log_scales = 0.5 * np.log(np.maximum(variances, np.finfo(np.float32).tiny))
            quats = rotmat_to_quat(axes)

        def summed(values: np.ndarray) -> np.ndarray:
            return np.bincount(g, values[members].astype(np.float64), k)

        def averaged(values: np.ndarray) -> np.ndarray:
            return group_mean(np.take(values, members, axis=0), weights, g, k)

        fields = {
            "means": mean,
            "log_scales": log_scales,
            "quats": quats,
            "opacity_logits": np.log(opacity / (1.0 - opacity)),
            "sh_dc": averaged(self.gaussians.sh_dc),
            "sh_rest": averaged(self.gaussians.sh_rest),
            "importance_sum": summed(self.gaussians.importance_sum),
            "alpha_t_sum": summed(self.gaussians.alpha_t_sum),
        }
        return {name: np.asarray(v, dtype=np.float32) for name, v in fields.items()}

    @cached_property
    def _opacities(self) -> np.ndarray:
        return self.gaussians.opacities().astype(np.float64)

    @cached_property
    def _weights(self) -> np.ndarray:
        """[N] each Gaussian's weight in a fold: opacity x (mean scale)^2, how much of a view it
        covers (kept above zero)."""
        weights = self._opacities * np.square(self._scale)
        return np.maximum(weights, np.finfo(np.float64).tiny)

    @cached_property
    def _spreads(self) -> np.ndarray:
        """[N] variances s^2 of an isotropic map, else [N, 3, 3] covariances (`moment_match`)."""
        if self.gaussians.isotropic:
            return np.square(self._sigma[:, 0])
        return self.gaussians.covariances()

    @cached_property
    def _space_order(self) -> np.ndarray:
        """[N] the Gaussians cell by cell along a Morton curve of 2^(3 x `SPATIAL_BITS`) cells:
        queries in this order walk the k-d tree through memory they have just visited, which
        makes them faster (docs/performance.md, "Folding")."""
        low, high = (np.asarray(v, dtype=np.float64) for v in column_ranges(self._means))
        extent = max(float((high - low).max()), np.finfo(np.float64).tiny)
        top = (1 << SPATIAL_BITS) - 1
        spread = morton_codes(np.arange(top + 1)[:, None] * [1, 0, 0]).astype(np.uint16)
        codes = np.zeros(len(self._means), dtype=np.uint16)  # (`morton_codes`, by a table)
        for axis, column in enumerate(self._means.T):
            cells = np.minimum((column - low[axis]) * (top / extent), top).astype(np.intp)
            codes |= spread[cells] << axis
        return np.argsort(codes, kind="stable")  # (a radix sort)

    @cached_property
    def _everything(self) -> cKDTree:
        return cKDTree(self._means, balanced_tree=False, compact_nodes=False)  # (for balls)

    def _nearest(self, kept: np.ndarray, is_kept: np.ndarray) -> _Nearest:
        """The nearest kept Gaussian of every dropped one, from the earlier kept sets that hold
        `kept` and lie inside it (the class docstring)."""
        size = len(kept)
        inside = [d for d in self._done if len(d.kept) <= size and is_kept[d.kept].all()]
        holding = [d for d in self._done if len(d.kept) >= size and d.is_kept[kept].all()]
        below = max(inside, key=lambda d: len(d.kept), default=None)
        above = min(holding, key=lambda d: len(d.kept), default=None)
        if below is not None and len(below.kept) == size:  # (this set again: the same nearest)
            return below
        dropped = self._space_order[~is_kept[self._space_order]]
        start = above if above is not None else below  # (the owners are patched from it)
        if above is not None:
            again = self._stale(above, is_kept, dropped)
            index, distance, changed = self._shrunk(above, below, kept, again)
        else:
            index, distance, changed = self._grown(below, kept, is_kept, dropped)
        index[kept], distance[kept] = -1, np.inf
        owner = np.full(len(is_kept), -1) if start is None else start.owner.copy()
        owner[changed] = self._joined(changed, index[changed], distance[changed])
        owner[kept] = kept
        done = _Nearest(kept, is_kept, index, distance, owner)
        self._done = [d for d in (below, done, above) if d is not None]  # (a search's bracket)
        return done

    def _grown(
        self, below: _Nearest | None, kept: np.ndarray, is_kept: np.ndarray, dropped: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """[N] nearest kept and [N] distances from a kept set inside `kept` (None: from none):
        the nearer of its nearest and the nearest of the Gaussians `kept` adds to it; and the
        dropped Gaussians whose nearest is not that set's."""
        if below is None:
            index, distance = np.full(len(is_kept), -1), np.full(len(is_kept), np.inf)
            adds = kept
        else:
            index, distance = below.index.copy(), below.distance.copy()
            adds = kept[~below.is_kept[kept]]
        if len(adds) == 0:
            return index, distance, adds
        if below is not None and len(adds) <= ADDED_SHARE * min(len(dropped), len(below.kept)):
            queried, found, gap = self._around(adds, dropped, distance, is_kept)
        else:
            nearer_than = None if below is None else distance[dropped]
            gap, i = self._query(adds, dropped, first=below is None, nearer_than=nearer_than)
            queried, found = dropped, adds[i]
        if below is None:
            index[queried], distance[queried] = found, gap
            return index, distance, queried
        return index, distance, _take_nearer(index, distance, queried, found, gap)

    def _stale(self, above: _Nearest, is_kept: np.ndarray, dropped: np.ndarray) -> np.ndarray:
        """The Gaussians `dropped` whose nearest in a kept set that holds `is_kept` is not kept
        any more, or which it kept itself (in the order of `dropped`)."""
        stale = above.is_kept[dropped]
        stale[~stale] = ~is_kept[above.index[dropped[~stale]]]
        return dropped[stale]

    def _shrunk(
        self, above: _Nearest, below: _Nearest | None, kept: np.ndarray, again: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """[N] nearest kept and [N] distances from a kept set that holds `kept`: its nearest
        where `kept` still holds it; for the rest (`again`, `_stale`, which it returns too), a
        query of `kept` or, given a kept set inside `kept` (`below`), the nearer of its nearest
        and the nearest of the Gaussians `kept` adds to it."""
        index, distance = above.index.copy(), above.distance.copy()
        if below is None:
            if len(again):
                distance[again], i = self._query(kept, again)
                index[again] = kept[i]
            return index, distance, again
        index[again], distance[again] = below.index[again], below.distance[again]
        adds = kept[~below.is_kept[kept]]
        if len(again) == 0 or len(adds) == 0:
            return index, distance, again
        gap, i = self._query(adds, again, nearer_than=distance[again])
        _take_nearer(index, distance, again, adds[i], gap)
        return index, distance, again

    def _around(
        self, adds: np.ndarray, dropped: np.ndarray, distance: np.ndarray, is_kept: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For the dropped Gaussians that one of `adds` may be nearer to than their `distance`,
        the nearest of `adds` and its distance: ([Q] dropped, [Q] added, [Q] distance).

        All but the 1% farthest from their nearest lie within `bound` of it; an added Gaussian
        nearer than that lies within `bound` of them, so the dropped Gaussians within `bound` of
        each added one are looked at (a ball query of the whole map's tree) and the far 1% are
        queried against the added ones."""
        gaps = distance[dropped]
        q = int(0.99 * (len(gaps) - 1))
        bound = float(np.partition(gaps, q)[q])
        far = dropped[gaps > bound]
        balls = self._everything.query_ball_point(
            self._means[adds], bound * (1 + 1e-9), return_sorted=False
        )
        near = np.concatenate([np.asarray(b, dtype=np.int64) for b in balls])
        source = np.repeat(adds, [len(b) for b in balls])
        near, source = near[~is_kept[near]], source[~is_kept[near]]
        gap_far, i = self._query(adds, far)
        queried = np.concatenate([near, far])
        found = np.concatenate([source, adds[i]])
        pairs = point_distances(
            np.take(self._means, near, axis=0), np.take(self._means, source, axis=0)
        )
        gap = np.concatenate([pairs, gap_far])
        order = np.lexsort((gap, queried))  # (the nearest of each, first)
        first = np.ones(len(order), dtype=bool)
        first[1:] = queried[order][1:] != queried[order][:-1]
        return queried[order[first]], found[order[first]], gap[order[first]]

    def _query(
        self,
        kept: np.ndarray,
        points: np.ndarray,
        first: bool = False,
        nearer_than: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The nearest of the Gaussians `kept` to each of `points`: ([P] distances, [P] their
        positions in `kept`), by a k-d tree of `kept` (of more than one). A fold from no
        earlier one (`first`) builds the tree the fold was first written with (scipy's default:
        the same choice among equal distances); the others a tree that builds faster (sliding
        midpoint).

        Many points are queried within a bound that holds all but about 0.1% of their nearest
        (from a sample of them), which prunes each search, and the few beyond it again without
        one. (What both save: docs/performance.md, "Folding".)

        `nearer_than` ([P], the distances of `points` to an earlier nearest) asks only for the
        nearest of those nearer than that: the others may come back at an infinite distance
        (and position 0). The points are then queried within a bound that holds 99% of these
        distances, and again without one those beyond it that found none within it."""
        where = np.take(self._means, points, axis=0)
        if len(kept) == 1:  # (the distance to it, as the tree gives it: a search's first fold)
            one = np.broadcast_to(self._means[kept[0]], where.shape)
            return point_distances(where, one), np.zeros(len(points), dtype=np.intp)
        tree = cKDTree(np.take(self._means, kept, axis=0), balanced_tree=first, compact_nodes=first)
        workers = cpu_threads() if len(points) >= PARALLEL_QUERIES else 1
        if nearer_than is not None and len(points):
            sample = nearer_than[::8]  # (any bound gives the same nearest: this one is quick)
            q = int(0.99 * (len(sample) - 1))
            bound = float(np.partition(sample, q)[q])
            if len(points) >= BOUNDED_QUERIES:  # (the nearest may lie far nearer: see above)
                bound = min(bound, self._bound(tree, where, workers))
            # (a little wider, so that rounding cannot hide one nearer than the bound)
            wider = bound * (1 + 1e-9)
            distance, i = tree.query(where, distance_upper_bound=wider, workers=workers)
            none = i == len(kept)
            beyond = np.flatnonzero(none & (nearer_than > bound))
            i[none] = 0
            if len(beyond):
                distance[beyond], i[beyond] = tree.query(where[beyond], workers=workers)
            return distance, i
        if len(points) < BOUNDED_QUERIES:
            return tree.query(where, workers=workers)
        bound = self._bound(tree, where, workers)
        distance, i = tree.query(where, distance_upper_bound=bound, workers=workers)
        beyond = np.flatnonzero(i == len(kept))
        if len(beyond):
            distance[beyond], i[beyond] = tree.query(where[beyond], workers=workers)
        return distance, i

    @staticmethod
    def _bound(tree: cKDTree, where: np.ndarray, workers: int) -> float:
        """A distance that holds about 99.9% of the nearest in `tree` of the points `where`
        (from a sample of them)."""
        return float(np.quantile(tree.query(where[::64], workers=workers)[0], 0.999))


def _take_nearer(
    index: np.ndarray, distance: np.ndarray, points: np.ndarray, found: np.ndarray, gap: np.ndarray
) -> np.ndarray:
    """Where `found` ([P]) lies nearer to `points` ([P]) than their nearest so far (`gap`
    against `distance`), make it their nearest in `index` and `distance`; those points."""
    closer = gap < distance[points]
    index[points[closer]] = found[closer]
    distance[points[closer]] = gap[closer]
    return points[closer]


def point_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[N] float64 distances between the rows of `a` and `b` ([N, 3], as float64), rounded as
    scipy's k-d tree rounds them (x, y, z summed in order), so the two compare exactly."""
    d = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    return np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])


def moment_match(
    weights: np.ndarray, means: np.ndarray, covariances: np.ndarray, group: np.ndarray, k: int
) -> tuple[np.ndarray, np.ndarray]:
    """The Gaussian each of `k` groups stands for, matching its first two moments.

    mu_g = sum_i w_i mu_i / W_g and Sigma_g = sum_i w_i (Sigma_i + (mu_i - mu_g)(mu_i - mu_g)^T)
    / W_g over the members i of group g (W_g = sum_i w_i).

    Args:
        weights: [N] positive weights.
        means: [N, 3] centres.
        covariances: [N, 3, 3] covariances, or [N] variances s^2 of isotropic ones (s^2 I):
            then only the diagonal of each Sigma_g is returned, as [k, 3].
        group: [N] group of each Gaussian in [0, k) (every group has a member).
        k: number of groups.

    Returns:
        ([k, 3] means, [k, 3, 3] covariances or [k, 3] their diagonals), float64.
    """
    total = np.bincount(group, weights, k)
    mean: np.ndarray = weighted_sums(means, weights, group, k) / total[:, None]
    if covariances.ndim == 1:  # (isotropic: the diagonal alone, an axis at a time)
        diagonal = np.empty((k, 3))
        spread = np.empty(len(group))  # (one buffer: w (s^2 + (mu_i - mu_g)^2) for each axis)
        for c in range(3):
            np.take(mean[:, c], group, out=spread)
            np.subtract(means[:, c], spread, out=spread)
            np.multiply(spread, spread, out=spread)
            spread += covariances
            spread *= weights
            diagonal[:, c] = np.bincount(group, spread, k)
        return mean, diagonal / total[:, None]
    offset = means - mean[group]
    outer = covariances + offset[:, :, None] * offset[:, None, :]
    cov = weighted_sums(outer, weights, group, k).reshape(k, 3, 3)
    return mean, cov / total[:, None, None]


def weighted_sums(values: np.ndarray, weights: np.ndarray, group: np.ndarray, k: int) -> np.ndarray:
    """[k, C] float64 sums of `weights` x `values` ([N, ...], C components) over each of `k`
    groups: a bincount per component (many times faster than np.add.at), through one buffer."""
    flat = values.reshape(len(values), int(np.prod(values.shape[1:])))
    sums = np.empty((k, flat.shape[1]))
    product = np.empty(len(values))
    for j in range(flat.shape[1]):
        np.multiply(weights, flat[:, j], out=product)
        sums[:, j] = np.bincount(group, product, k)
    return sums


def group_mean(values: np.ndarray, weights: np.ndarray, group: np.ndarray, k: int) -> np.ndarray:
    """[k, ...] weighted mean of `values` [N, ...] over each of `k` groups."""
    total = np.bincount(group, weights, k)
    return (weighted_sums(values, weights, group, k) / total[:, None]).reshape(
        (k, *values.shape[1:])
    )
