"""Folding what a prune or share leaves out into what it keeps (gscompress.ops.fold)."""

from __future__ import annotations

import numpy as np
import pytest

from gscompress.camera import Intrinsics, make_transform, quat_to_rotmat
from gscompress.gaussians import GaussianMap, random_map
from gscompress.ops import fold as fold_module
from gscompress.ops.fold import FOLD_REACH, fold, fold_groups, moment_match
from gscompress.selection import select_count
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
    gaussians = row_map(10, spacing=0.01, scale=0.01)
    use_threads(3)  # what `gsc --threads 3` and an experiment worker's share do
    fold_groups(gaussians, np.arange(0, 10, 2))
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    fold_groups(gaussians, np.arange(0, 10, 2))
    assert used == [3, 1]


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
    g = GaussianMap.new(**{**{f: getattr(g, f) for f in ("means", "log_scales", "quats")},
                           "opacity_logits": g.opacity_logits,
                           "sh_dc": np.full((n, 3), 1.5)})  # fmt: skip
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
