"""Folding what a prune or share leaves out into what it keeps (gscompress.ops.fold)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from gscompress.camera import Intrinsics, make_transform, quat_to_rotmat, rotmat_to_quat
from gscompress.gaussians import GaussianMap, random_map
from gscompress.io.mcap_log import LogMetadata, LogWriter
from gscompress.ops import fold as fold_module
from gscompress.ops.budget import Budget, largest_count_within
from gscompress.ops.fold import FOLD_REACH, Folding, fold, fold_groups, moment_match
from gscompress.pipeline.share.cut import ShareCut
from gscompress.pipeline.share.options import ShareOptions
from gscompress.selection import select_by, select_count, selection_scores, top_k
from gscompress.threads import use_threads


def row_map(n: int, spacing: float, scale: float, isotropic: bool = True) -> GaussianMap:
    """n opaque grey Gaussians in a row along x, at z = 1 m, scored by position."""
    means = np.stack([np.arange(n) * spacing, np.zeros(n), np.ones(n)], 1)
    log_scales = np.full((n, 1 if isotropic else 3), np.log(scale))
    return GaussianMap.new(
        means=means,
        log_scales=log_scales,
        quats=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
        opacity_logits=np.full(n, 3.0),
        sh_dc=np.zeros((n, 3)),
        importance_sum=np.arange(n, 0, -1, dtype=np.float64),
        importance_weight=np.ones(n),
        alpha_t_sum=np.ones(n),
    )


def test_moment_match_of_two_equal_gaussians():
    means = np.array([[-0.1, 0.0, 0.0], [0.1, 0.0, 0.0]])
    covs = np.stack([np.eye(3) * 0.01] * 2)
    mean, cov = moment_match(np.ones(2), means, covs, np.zeros(2, np.int64), 1)
    np.testing.assert_allclose(mean[0], 0.0, atol=1e-15)
    np.testing.assert_allclose(cov[0], np.diag([0.01 + 0.01, 0.01, 0.01]), atol=1e-15)


def test_fold_keeps_count_ids_and_order_and_leaves_kept_only_maps_alone():
    g = random_map(200, seed=3)
    kept, index = select_count(g, 50, "pwas", 0)
    folded = fold(g, index)
    assert len(folded) == 50
    np.testing.assert_array_equal(folded.ids, kept.ids)
    assert fold(g, np.arange(len(g))).equals(g)  # nothing dropped: nothing changes


def test_only_near_gaussians_fold_and_the_sums_follow_them():
    g = row_map(4, spacing=0.01, scale=0.01)  # 0, 1, 2 touch; 3 is moved far away
    g.means[3, 0] = 10.0
    groups = fold_groups(g, np.array([0]))
    np.testing.assert_array_equal(groups, [0, 0, 0, -1])
    folded = fold(g, np.array([0]))
    assert folded.importance_sum[0] == pytest.approx(4 + 3 + 2)  # not the far one's 1
    assert folded.importance_weight[0] == g.importance_weight[0]
    assert folded.importance[0] >= g.importance[0]
    assert folded.means[0, 0] == pytest.approx(0.01)  # the three's centre
    assert np.exp(folded.log_scales[0, 0]) > 0.01  # spread over the three


def test_reach_bounds_the_fold():
    g = row_map(2, spacing=1.0, scale=0.01)
    assert fold_groups(g, np.array([0]))[1] == -1
    g = row_map(2, spacing=FOLD_REACH * 0.02 * 0.99, scale=0.01)
    assert fold_groups(g, np.array([0]))[1] == 0


def test_the_nearest_kept_query_uses_the_threads_gsc_is_given(monkeypatch, threads_restored):
    used = []

    class Tree(fold_module.cKDTree):  # type: ignore[misc]
        def query(self, x, *args, **kwargs):  # type: ignore[no-untyped-def]
            used.append(kwargs.get("workers"))
            return super().query(x, *args, **kwargs)

    monkeypatch.setattr(fold_module, "cKDTree", Tree)
    n = 2 * fold_module.PARALLEL_QUERIES  # (fewer queries run on one thread)
    gaussians = row_map(n, spacing=0.01, scale=0.01)
    use_threads(3)  # what `gsc --threads 3` and an experiment worker's share do
    fold_groups(gaussians, np.arange(0, n, 2))
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    fold_groups(gaussians, np.arange(0, n, 2))
    fold_groups(gaussians, np.arange(0, 10, 2))
    assert used == [3, 1, 1]


def test_anisotropic_fold_matches_the_moments():
    g = random_map(30, seed=5, isotropic=False)
    index = np.array([0, 1, 2])
    folded = fold(g, index, reach=1e9)  # every dropped one folds somewhere
    groups = fold_groups(g, index, reach=1e9)
    weights = g.opacities().astype(np.float64) * g.scales().astype(np.float64).mean(1) ** 2
    _, expected = moment_match(weights, g.means.astype(np.float64), g.covariances(), groups, 3)
    R = quat_to_rotmat(folded.quats)
    got = np.einsum("nij,nj,nkj->nik", R, np.exp(2.0 * folded.log_scales.astype(np.float64)), R)
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-9)


def test_a_folded_prune_draws_the_surface_a_dropped_one_leaves_as_holes():
    from gscompress.ops.evaluate import render_view
    from gscompress.ops.score import activated_tensors

    n = 40
    g = row_map(n, spacing=0.02, scale=0.01)
    g = GaussianMap.new(
        **{
            **{f: getattr(g, f) for f in ("means", "log_scales", "quats")},
            "opacity_logits": g.opacity_logits,
            "sh_dc": np.full((n, 3), 1.5),
        }
    )
    intrinsics = Intrinsics(60.0, 60.0, 32.0, 8.0, 64, 16)
    pose = make_transform(np.eye(3), np.array([0.39, 0.0, 0.0]))

    def draw(m: GaussianMap) -> np.ndarray:
        return render_view(activated_tensors(m), pose, intrinsics, backend="torch")[0]

    whole = draw(g)
    index = np.arange(0, n, 4)  # keep a quarter, evenly
    dropped, folded = draw(g.select(index)), draw(fold(g, index))
    err_dropped = np.abs(dropped - whole).mean()
    err_folded = np.abs(folded - whole).mean()
    assert err_folded < 0.8 * err_dropped, (err_folded, err_dropped)  # (0.046 against 0.066)


def test_interpolate_pose_follows_the_shorter_arc_and_the_segment():
    from gscompress.camera import interpolate_pose, rotation_angle_deg

    def about_z(deg: float, x: float) -> np.ndarray:
        a = np.deg2rad(deg)
        R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        return make_transform(R, np.array([x, 0.0, 0.0]))

    T_a, T_b = about_z(10, 0.0), about_z(100, 2.0)
    np.testing.assert_allclose(interpolate_pose(T_a, T_b, 0.0), T_a, atol=1e-12)
    np.testing.assert_allclose(interpolate_pose(T_a, T_b, 1.0), T_b, atol=1e-12)
    np.testing.assert_allclose(interpolate_pose(T_a, T_b, 0.25), about_z(32.5, 0.5), atol=1e-12)
    T_c = about_z(-170, 0.0)  # 90 degrees on from T_b through 180 (270 the other way)
    mid = interpolate_pose(T_b, T_c, 0.5)
    assert rotation_angle_deg(mid[:3, :3] @ about_z(145, 0)[:3, :3].T) < 1e-5


# ---------------------------------------------------------------- against a plain reference


def reference_fold(gaussians: GaussianMap, kept: np.ndarray) -> tuple[np.ndarray, GaussianMap]:
    """The fold written out plainly: one k-d tree query of every dropped Gaussian against the
    kept ones, the moments of each group over its full 3x3 covariances. Its groups and map."""
    kept = np.asarray(kept, dtype=np.int64)
    k, n = len(kept), len(gaussians)
    group = np.full(n, -1, dtype=np.int64)
    group[kept] = np.arange(k)
    dropped = np.flatnonzero(group < 0)
    means = gaussians.means.astype(np.float64)
    scale = gaussians.scales().astype(np.float64).mean(axis=1)
    if len(dropped) and k:
        distance, nearest = cKDTree(means[kept]).query(means[dropped])
        near = distance <= FOLD_REACH * (scale[kept][nearest] + scale[dropped])
        group[dropped[near]] = nearest[near]
    members = np.flatnonzero(group >= 0)
    if len(members) == k:
        return group, gaussians.select(kept)
    g, src = group[members], gaussians.select(members)
    opacity = src.opacities().astype(np.float64)
    weights = np.maximum(opacity * np.square(scale[members]), np.finfo(np.float64).tiny)
    total = np.bincount(g, weights, k)
    mean = np.stack([np.bincount(g, weights * means[members, c], k) for c in range(3)], 1)
    mean = mean / total[:, None]
    offset = means[members] - mean[g]
    spread = src.covariances() + offset[:, :, None] * offset[:, None, :]
    cov = np.zeros((k, 3, 3))
    for a in range(3):
        for b in range(3):
            cov[:, a, b] = np.bincount(g, weights * spread[:, a, b], k) / total
    top = np.zeros(k)
    np.maximum.at(top, g, opacity)
    top = np.clip(top, 1e-6, 1.0 - 1e-6)
    if gaussians.isotropic:
        log_scales = 0.5 * np.log(np.trace(cov, axis1=1, axis2=2) / 3.0)[:, None]
        quats = gaussians.quats[kept]
    else:
        variances, axes = np.linalg.eigh(cov)
        axes[np.linalg.det(axes) < 0, :, 2] *= -1.0
        log_scales = 0.5 * np.log(np.maximum(variances, np.finfo(np.float32).tiny))
        quats = rotmat_to_quat(axes)

    def mean_of(values: np.ndarray) -> np.ndarray:
        flat = values.reshape(len(values), -1).astype(np.float64)
        columns = [np.bincount(g, weights * flat[:, j], k) / total for j in range(flat.shape[1])]
        out = np.stack(columns, 1) if columns else np.zeros((k, 0))
        return out.reshape((k, *values.shape[1:]))

    folded = replace(
        gaussians.select(kept),
        means=mean.astype(np.float32),
        log_scales=log_scales.astype(np.float32),
        quats=np.asarray(quats, dtype=np.float32),
        opacity_logits=np.log(top / (1.0 - top)).astype(np.float32),
        sh_dc=mean_of(src.sh_dc).astype(np.float32),
        sh_rest=mean_of(src.sh_rest).astype(np.float32),
        importance_sum=np.bincount(g, src.importance_sum.astype(np.float64), k),
        alpha_t_sum=np.bincount(g, src.alpha_t_sum.astype(np.float64), k),
    )
    return group, folded


def varied_map(seed: int, n: int, isotropic: bool = True, sh_degree: int = 0) -> GaussianMap:
    """A random map whose density varies over space: dense clusters, where most dropped
    Gaussians fold, and a sparse field, where many lie beyond the reach."""
    rng = np.random.default_rng(seed)
    g = random_map(n, seed, isotropic, sh_degree, extent=3.0)
    clustered = rng.random(n) < 0.6
    centres = rng.uniform(-3.0, 3.0, (5, 3))
    g.means[clustered] = centres[rng.integers(0, 5, clustered.sum())] + rng.normal(
        0.0, 0.1, (clustered.sum(), 3)
    )
    return g.validate()


@pytest.mark.parametrize("seed", range(6))
def test_the_fold_equals_the_plain_reference(seed: int) -> None:
    """Groups and every folded parameter, bit for bit, on maps of each layout and SH degree,
    kept sets of every size (none folded, some, nearly all)."""
    rng = np.random.default_rng(seed)
    g = varied_map(seed, int(rng.integers(50, 3000)), bool(seed % 2), int(seed % 4))
    scores = selection_scores(g, "pwas")
    outcomes = set()
    for k in (1, 2, max(1, len(g) // 10), len(g) // 2, len(g) - 1, len(g)):
        kept = top_k(scores, g.ids, k)
        group, expected = reference_fold(g, kept)
        np.testing.assert_array_equal(fold_groups(g, kept), group)
        assert fold(g, kept).equals(expected), (seed, k)
        outcomes.update(np.sign(np.delete(group, kept)).tolist())
    assert outcomes == {-1, 0, 1}  # (some dropped beyond the reach, some folded)


def test_a_large_fold_bounds_its_query_and_equals_the_reference(monkeypatch) -> None:
    """80,000 dropped Gaussians are queried within a bound first (`BOUNDED_QUERIES`), the few
    beyond it again: the same groups and Gaussians as the plain query."""
    g = varied_map(11, 100_000)
    kept = top_k(selection_scores(g, "pwas"), g.ids, 20_000)
    bounds = []

    class Tree(fold_module.cKDTree):  # type: ignore[misc]
        def query(self, x, *args, **kwargs):  # type: ignore[no-untyped-def]
            bounds.append(kwargs.get("distance_upper_bound", np.inf))
            return super().query(x, *args, **kwargs)

    monkeypatch.setattr(fold_module, "cKDTree", Tree)
    group, expected = reference_fold(g, kept)
    folding = Folding(g)
    np.testing.assert_array_equal(folding.groups(kept), group)
    assert folding.fold(kept).equals(expected)
    assert np.isfinite(bounds[1]) and len(bounds) <= 3  # (a sample, bounded, the rest)


@contextlib.contextmanager
def looked_up_around() -> Iterator[list[int]]:
    """The sizes of the sets of added Gaussians `Folding._around` looks up, while in the block."""
    around: list[int] = []
    original = Folding._around

    def spy(self, adds, *args):  # type: ignore[no-untyped-def]
        around.append(len(adds))
        return original(self, adds, *args)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Folding, "_around", spy)
        yield around


@pytest.mark.parametrize("seed", range(4))
def test_one_folding_of_many_kept_sets_equals_the_reference_for_each(seed: int) -> None:
    """A `Folding` asked for the K best at counts that grow and shrink, as a byte budget's
    search asks (the nearest kept taken from the earlier kept sets inside the new one and
    holding it), folds each exactly as a fresh reference fold; a few Gaussians added to the
    largest set yet are looked up around them."""
    rng = np.random.default_rng(seed)
    g = varied_map(100 + seed, 6000, isotropic=seed != 3)
    scores = selection_scores(g, "pwas")
    folding = Folding(g)
    counts = [1, 900, 3000, 3050, 1000, 950, 960, 958, int(rng.integers(10, 6000)), 5999, 2]
    with looked_up_around() as around:
        for k in counts:
            kept = top_k(scores, g.ids, k)
            group, expected = reference_fold(g, kept)
            np.testing.assert_array_equal(folding.groups(kept), group)
            assert folding.fold(kept).equals(expected), (seed, k)
    assert around and max(around) <= 100  # (3050 from 3000)


@pytest.mark.parametrize("isotropic", [True, False])
def test_a_fold_between_two_earlier_sets_queries_only_what_the_larger_one_lost(
    isotropic: bool,
) -> None:
    """Between a kept set inside its own and one holding it, a fold takes the nearest from the
    larger set and queries only the Gaussians whose nearest that set held and it drops (and
    those it drops), against the few it adds to the smaller set: no ball query of the whole
    map, the same groups and Gaussians as the reference, and as a fresh `Folding`."""
    g = varied_map(9, 20_000, isotropic)
    scores = selection_scores(g, "pwas")
    folding = Folding(g)
    trees: list[int] = []

    class Tree(fold_module.cKDTree):  # type: ignore[misc]
        def __init__(self, data, *args, **kwargs):  # type: ignore[no-untyped-def]
            trees.append(len(data))
            super().__init__(data, *args, **kwargs)

    for k in (1, 4000, 8000):
        folding.fold(top_k(scores, g.ids, k))
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(fold_module, "cKDTree", Tree)
        for k in (4100, 4050, 4070, 4069):  # (the nearer side alternates)
            trees.clear()
            kept = top_k(scores, g.ids, k)
            group, expected = reference_fold(g, kept)
            np.testing.assert_array_equal(folding.groups(kept), group)
            assert folding.fold(kept).equals(expected), k
            assert trees and max(trees) <= 100, (k, trees)  # (what the set inside lacks)
            assert Folding(g).fold(kept).equals(expected), k
    assert "_everything" not in vars(folding)  # (the whole map's tree, never built)


@pytest.mark.parametrize("points", [2000, 70_000])
def test_a_query_for_the_nearer_than_known_gives_every_nearer_one(points: int) -> None:
    """`Folding._query` asked only for the nearest nearer than known distances (`nearer_than`,
    queried within a bound first, those beyond it that found none again) gives the plain
    query's nearest wherever that is nearer, and nothing nearer anywhere else."""
    rng = np.random.default_rng(points)
    g = varied_map(3, points + 500)
    folding = Folding(g)
    kept = np.sort(rng.choice(len(g), 500, replace=False))
    others = np.setdiff1d(np.arange(len(g)), kept)
    plain, i_plain = cKDTree(g.means[kept].astype(np.float64)).query(g.means[others])
    known = plain * rng.uniform(0.5, 1.5, len(others))  # (about half nearer than the plain)
    gap, i = folding._query(kept, others, nearer_than=known)
    nearer = plain < known
    assert 0.3 < nearer.mean() < 0.7
    np.testing.assert_array_equal(gap[nearer], plain[nearer])
    np.testing.assert_array_equal(i[nearer], i_plain[nearer])
    assert np.all(gap[~nearer] >= known[~nearer]) and np.all((0 <= i) & (i < len(kept)))


def test_gaussians_added_to_a_few_kept_ones_are_queried_not_looked_up_around() -> None:
    """A search's first steps fold the best one, then a few hundred: around so few kept ones
    the balls `Folding._around` looks in hold the whole map (for each Gaussian added), so the
    added ones are queried instead (`ADDED_SHARE`); the folds equal the reference."""
    g = varied_map(5, 20_000)
    scores = selection_scores(g, "pwas")
    folding = Folding(g)
    with looked_up_around() as around:
        for k in (1, 400, 20_000, 410):  # (400 <= 19,600 / 32, but not 1 / 32)
            kept = top_k(scores, g.ids, k)
            group, expected = reference_fold(g, kept)
            np.testing.assert_array_equal(folding.groups(kept), group)
            assert folding.fold(kept).equals(expected), k
    assert around == [10]  # (410 from 400)


def test_equal_distances_go_to_one_of_the_nearest_kept():
    """On a lattice every dropped Gaussian has several kept ones at the same distance; whichever
    it joins (the tie may go either way) is one of the nearest."""
    side = np.arange(12, dtype=np.float64) * 0.02
    means = np.stack(np.meshgrid(side, side, side, indexing="ij"), -1).reshape(-1, 3)
    n = len(means)
    g = GaussianMap.new(
        means=means,
        log_scales=np.full((n, 1), np.log(0.01)),
        quats=np.tile([1.0, 0, 0, 0], (n, 1)),
        opacity_logits=np.zeros(n),
        sh_dc=np.zeros((n, 3)),
        importance_sum=np.random.default_rng(0).random(n),
        importance_weight=np.ones(n),
    )
    scores = selection_scores(g, "pwas")
    folding = Folding(g)
    for k in (300, 800, 840, 836, 838):
        kept = top_k(scores, g.ids, k)
        group = folding.groups(kept)
        dropped = np.flatnonzero(~np.isin(np.arange(n), kept))
        nearest = cKDTree(means[kept]).query(means[dropped])[0]
        joined = np.linalg.norm(means[dropped] - means[kept[group[dropped]]], axis=1)
        assert np.all(group[dropped] >= 0)  # (all within reach on this lattice)
        np.testing.assert_allclose(joined, nearest, rtol=1e-12)


class PlainCut(ShareCut):
    """The share files of `ShareCut`, each cut by the plain reference fold."""

    def _cut(self, count: int) -> GaussianMap:
        _, index = select_by(self.pool, count, self._scores, self._first)
        return reference_fold(self.pool, index)[1]


@pytest.mark.parametrize("seed", range(4))
def test_a_byte_budget_search_chooses_the_count_and_bytes_of_the_plain_reference(
    tmp_path, seed: int
) -> None:
    """The search over folded shares (one `Folding` for every count it tries) chooses the same
    count as with a plain fold at every step, the same file bytes, within the budget."""
    rng = np.random.default_rng(seed)
    g = varied_map(200 + seed, int(rng.integers(2000, 8000)))
    src = tmp_path / "a.mcap"
    with LogWriter(src, LogMetadata(command="test")) as log:
        log.write_gaussians(g, 0)
    for codec in ("compact", "fp16"):
        whole = ShareCut(src, Budget.parse("1"), ShareOptions(codec=codec)).size(len(g))
        budget = Budget(budget_bytes=int(whole * rng.uniform(0.05, 0.6)))
        how = ShareOptions(codec=codec)
        cut, plain = ShareCut(src, budget, how), PlainCut(src, budget, how)
        count = largest_count_within(budget.budget_bytes, len(g), cut.size)
        assert count == largest_count_within(budget.budget_bytes, len(g), plain.size)
        data = cut.file(count)[0]
        assert data == plain.file(count)[0] and len(data) <= budget.budget_bytes
        assert 0 < count < len(g)


def test_a_byte_budget_search_reuses_the_nearest_kept_of_its_earlier_steps(tmp_path, monkeypatch):
    """The steps of a search start from the nearest kept Gaussians of earlier ones: its k-d tree
    queries look up fewer than half the points that a query of every dropped Gaussian at every
    step would (on this map 57k against 143k)."""
    g = varied_map(7, 20_000)
    src = tmp_path / "a.mcap"
    with LogWriter(src, LogMetadata(command="test")) as log:
        log.write_gaussians(g, 0)
    queried = []

    class Tree(fold_module.cKDTree):  # type: ignore[misc]
        def query(self, x, *args, **kwargs):  # type: ignore[no-untyped-def]
            queried.append(len(x))
            return super().query(x, *args, **kwargs)

    monkeypatch.setattr(fold_module, "cKDTree", Tree)
    cut = ShareCut(src, Budget.parse("30kB"))
    steps = []

    def size(count: int) -> int:
        steps.append(count)
        return cut.size(count)

    count = largest_count_within(30_000, len(g), size)
    every_step = sum(len(g) - k for k in set(steps) if k < len(g))
    assert len(set(steps)) >= 8 and 0 < count < len(g)
    assert sum(queried) < 0.5 * every_step, (queried, steps)
