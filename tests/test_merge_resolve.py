"""A merge that keeps what a share brings: alignment, surfaces resolved, the share kept still.

A constructed wall of Gaussians is seen by two agents: A maps its left part, B its right part,
the two overlapping in the middle, and B's map (with its views) sits a centimetre or two off A's,
as two SLAM agents anchored at one ground truth do.
"""

from __future__ import annotations

import sys
from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from gscompress.camera import Intrinsics, invert_transform
from gscompress.errors import MissingDependencyError, OptionError
from gscompress.gaussians import GaussianMap
from gscompress.ops.icp import ICP
from gscompress.ops.merge import (
    EXACT,
    MergeOptions,
    align_share,
    combine,
    resolve_overlap,
    share_rates,
    transform_map,
    voxel_evidence,
)
from gscompress.render import render
from gscompress.slam.config import preset
from gscompress.slam.keyframes import View
from gscompress.slam.params import GaussianParams

K = Intrinsics(fx=80.0, fy=80.0, cx=16.0, cy=12.0, width=32, height=24)
SPACING = 0.04
RESOLVED = MergeOptions(align=True, resolve="evidence", share_rate=0.0, by_view=False)
"""Aligned, the overlap resolved by evidence, the share held still in the refinement."""
B_OFFSET = np.array([0.012, -0.006, 0.01])
"""Where B's world frame sits in A's (B's map and views are moved by it)."""


def wall() -> GaussianMap:
    """A textured wall at z = 2 m, one Gaussian every 4 cm (centres mid-voxel)."""
    xs = np.arange(-0.58, 0.6, SPACING)
    ys = np.arange(-0.38, 0.4, SPACING)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    n = gx.size
    depth = 2.0 + np.random.default_rng(0).uniform(-0.004, 0.004, n)  # (no ties in the sort)
    means = np.stack([gx.ravel(), gy.ravel(), depth], axis=1)
    rgb = np.stack(
        [
            0.5 + 0.4 * np.sin(9 * gx.ravel()),
            0.5 + 0.4 * np.cos(7 * gy.ravel()),
            0.5 + 0.3 * np.sin(5 * (gx + gy).ravel()),
        ],
        axis=1,
    )
    return GaussianMap.new(
        means=means,
        log_scales=np.full((n, 1), np.log(0.025)),
        quats=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
        opacity_logits=np.full(n, 4.0),
        sh_dc=(rgb - 0.5) / 0.28209479177387814,
        alpha_t_sum=np.ones(n),
    )


def shift(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, 3] = T
    return out


def pose(x: float) -> np.ndarray:
    """A camera at (x, 0, 0) looking down +z at the wall."""
    return shift(np.array([x, 0.0, 0.0]))


def image(gaussians: GaussianMap, T_world_cam: np.ndarray) -> torch.Tensor:
    params = GaussianParams.from_map(gaussians)
    with torch.no_grad():
        T = torch.as_tensor(invert_transform(T_world_cam), dtype=torch.float32)
        return render(*params.render_inputs(), K, T).color


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(10 * torch.log10(1.0 / torch.mean((a - b) ** 2).clamp_min(1e-12)))


@pytest.fixture(scope="module")
def agents() -> dict[str, object]:
    scene = wall()
    a = scene.select(scene.means[:, 0] < 0.15)
    b_part = scene.select(scene.means[:, 0] > -0.15)
    b = transform_map(replace(b_part, ids=b_part.ids + np.uint32(10_000)), shift(B_OFFSET))
    return {
        "scene": scene,
        "a": a,
        "b": b,
        "a_views": [pose(x) for x in (-0.35, -0.3, -0.25)],
        "b_views": [pose(x) for x in (0.25, 0.3, 0.35)],
    }


def test_merge_of_a_map_with_itself_renders_like_the_map(agents: dict) -> None:
    scene = agents["scene"]
    merged, from_share, offset, stats = combine(scene, scene, RESOLVED)
    assert stats["align_shift_cm"] == 0.0 and stats["share_dropped"] == len(scene)
    assert not from_share.any() and offset == 0
    stacked, *_ = combine(scene, scene, EXACT)
    assert len(stacked) == 2 * len(scene)
    for T in agents["a_views"] + agents["b_views"]:
        own = image(scene, T)
        assert torch.equal(image(merged, T), own)
        assert psnr(image(stacked, T), own) < 40.0  # stacking a map on itself changes it


@pytest.mark.parametrize("icp", ICP)
def test_align_share_recovers_the_offset_between_two_agents(agents: dict, icp: str) -> None:
    if icp == "open3d":
        pytest.importorskip("open3d", reason="Open3D's ICP: pip install 'gscompress[align]'")
    T, stats = align_share(agents["b"], agents["a"], max_distance=SPACING, icp=icp)
    np.testing.assert_allclose(T[:3, 3], B_OFFSET, atol=1e-4)
    np.testing.assert_allclose(T[:3, :3], np.eye(3), atol=1e-5)
    assert stats["align_rmse_before_cm"] > 1.0 and stats["align_rmse_after_cm"] < 0.01
    far = transform_map(agents["a"], shift(np.array([5.0, 0.0, 0.0])))
    T, stats = align_share(agents["b"], far, max_distance=SPACING, icp=icp)
    assert np.array_equal(T, np.eye(4)) and stats["align_pairs"] == 0  # no overlap: unmoved


def test_an_alignment_that_takes_the_share_off_the_receiver_is_not_kept(
    agents: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    import gscompress.ops.align as align

    turned = np.eye(4)
    turned[:3, :3] = Rotation.from_euler("z", 5.0, degrees=True).as_matrix()
    found = align.refine_alignment  # (the library's step, replaced by one that turns 5 degrees)
    monkeypatch.setattr(
        align,
        "refine_alignment",
        lambda s, t, T, o: replace(found(s, t, T, o), T_target_source=turned),
    )
    T, stats = align_share(agents["b"], agents["a"], max_distance=SPACING)
    assert np.array_equal(T, np.eye(4)) and stats["align_kept"] is False
    assert stats["align_rmse_after_cm"] == stats["align_rmse_before_cm"] > 1.0


def test_without_open3d_the_default_merge_aligns_and_open3ds_icp_names_the_extra(
    agents: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "open3d", None)  # (an import of it now fails)
    assert MergeOptions().align and MergeOptions().icp == "builtin"
    _, _, _, stats = combine(agents["b"], agents["a"], replace(MergeOptions(), by_view=False))
    T = np.asarray(stats["align_transform"])  # (B's offset, recovered to a tenth of a mm)
    np.testing.assert_allclose(T[:3, 3], B_OFFSET, atol=1e-4)
    np.testing.assert_allclose(T[:3, :3], np.eye(3), atol=1e-5)
    assert stats["align_kept"] and stats["align_rmse_after_cm"] < 0.01
    with pytest.raises(MissingDependencyError, match=r"gscompress\[align\].*`no_align`"):
        combine(agents["b"], agents["a"], replace(RESOLVED, icp="open3d"))
    merged, from_share, _, stats = combine(agents["b"], agents["a"], replace(RESOLVED, align=False))
    assert "align_pairs" not in stats
    shared = merged.select(np.flatnonzero(from_share))
    kept = np.isin(agents["a"].means, shared.means).all(axis=1)
    assert kept.sum() == len(shared)  # the share's Gaussians where they were sent


def test_merge_of_two_halves_renders_each_half_as_well_as_its_source(agents: dict) -> None:
    scene, a, b = agents["scene"], agents["a"], agents["b"]
    merged, from_share, _, stats = combine(b, a, RESOLVED)  # B receives A's whole map
    stacked, *_ = combine(b, a, EXACT)
    assert stats["share_dropped"] > 0 and stats["receiver_dropped"] == 0  # a tie: B keeps its own
    assert from_share.sum() == len(a) - stats["share_dropped"]
    for T in agents["a_views"]:  # A's frames, at A's poses moved into B's frame
        truth = image(scene, T)
        source = psnr(image(a, T), truth)
        assert psnr(image(merged, shift(B_OFFSET) @ T), truth) >= source - 0.5
        assert psnr(image(stacked, shift(B_OFFSET) @ T), truth) < source - 0.5
    for T in agents["b_views"]:
        truth = image(scene, T)
        source = psnr(image(b, shift(B_OFFSET) @ T), truth)
        assert psnr(image(merged, shift(B_OFFSET) @ T), truth) >= source - 0.5


def test_overlap_goes_to_the_map_with_more_evidence() -> None:
    scene = wall()
    twin = replace(scene, ids=scene.ids + np.uint32(10_000))
    keep_r, keep_s, _ = resolve_overlap(scene, twin, np.ones(len(scene)), np.full(len(scene), 2.0))
    assert not keep_r.any() and keep_s.all()
    left = scene.means[:, 0] < 0
    keep_r, keep_s, _ = resolve_overlap(
        scene, twin, np.where(left, 3.0, 1.0), np.full(len(scene), 2.0)
    )
    assert np.array_equal(keep_r, left) and np.array_equal(keep_s, ~left)


def test_a_margin_gives_near_ties_to_the_receiver() -> None:
    scene = wall()
    twin = replace(scene, ids=scene.ids + np.uint32(10_000))
    left = scene.means[:, 0] < 0
    share_evidence = np.where(left, 3.0, 1.5)  # 3x the receiver's on the left, 1.5x elsewhere
    keep_r, keep_s, stats = resolve_overlap(
        scene, twin, np.ones(len(scene)), share_evidence, margin=2.0
    )
    assert np.array_equal(keep_s, left) and np.array_equal(keep_r, ~left)
    assert stats["share_dropped"] == int((~left).sum())
    keep_r, keep_s, _ = resolve_overlap(scene, twin, np.ones(len(scene)), share_evidence)
    assert keep_s.all() and not keep_r.any()  # without a margin the share wins both sides
    with pytest.raises(OptionError, match="`margin`"):
        MergeOptions(margin=0.5).check()


def test_a_fold_of_many_does_not_take_a_cell_from_the_receivers_small_gaussians() -> None:
    # B holds a patch of four small Gaussians (5 mm) in one 4 cm cell, each seen with evidence 1;
    # the share sends one fold of 25 Gaussians there (10 cm across, its group's evidence 25).
    small = GaussianMap.new(
        means=np.array([[x, y, 2.0] for x in (0.01, 0.03) for y in (0.01, 0.03)]),
        log_scales=np.full((4, 1), np.log(0.005)),
        quats=np.tile([1.0, 0, 0, 0], (4, 1)),
        opacity_logits=np.full(4, 4.0),
        sh_dc=np.zeros((4, 3)),
        alpha_t_sum=np.ones(4),
    )
    fold = GaussianMap.new(
        means=np.array([[0.02, 0.02, 2.0]]),
        log_scales=np.full((1, 1), np.log(0.05)),
        quats=np.array([[1.0, 0, 0, 0]]),
        opacity_logits=np.full(1, 4.0),
        sh_dc=np.zeros((1, 3)),
        alpha_t_sum=np.array([25.0]),
        ids=np.array([100], np.uint32),
    )
    assert np.allclose(voxel_evidence(small, 0.04), 1.0)  # (each fits in a cell face)
    assert voxel_evidence(fold, 0.04)[0] == 0.0  # (its 2-sigma ellipse is 20 times a face)
    assert voxel_evidence(fold, None)[0] == 25.0
    options = MergeOptions(align=False)
    merged, from_share, _, stats = combine(small, fold, options)
    assert len(merged) == 4 and not from_share.any() and stats["receiver_dropped"] == 0
    # However much its group was seen: counted for the part of its footprint a cell face holds
    # (1/20 of it), sums 400 times the receiver's would still have taken the cell.
    seen = replace(fold, alpha_t_sum=np.array([1600.0], np.float32))
    merged, from_share, _, stats = combine(small, seen, options)
    assert len(merged) == 4 and not from_share.any() and stats["receiver_dropped"] == 0
    merged, from_share, _, stats = combine(small, fold, replace(options, footprint=False))
    assert len(merged) == 1 and from_share.all() and stats["receiver_dropped"] == 4


def test_refinement_keeps_the_share_still_where_its_rate_is_zero(agents: dict) -> None:
    from gscompress.ops.refine import refine

    scene, a, b = agents["scene"], agents["a"], agents["b"]
    merged, from_share, _, _ = combine(b, a, RESOLVED)
    views = []
    for T in agents["b_views"]:
        color = image(scene, T)
        views.append(View(0, color, torch.full(color.shape[:2], 2.0), shift(B_OFFSET) @ T))
    config = preset("tiny")
    rates = share_rates(from_share, RESOLVED)
    assert rates is not None and np.array_equal(rates, (~from_share).astype(np.float32))
    out, _ = refine(merged, views, K, config, 5, rates=rates)
    assert np.array_equal(out.means[from_share], merged.means[from_share])
    assert np.array_equal(out.sh_dc[from_share], merged.sh_dc[from_share])
    assert not np.array_equal(out.sh_dc[~from_share], merged.sh_dc[~from_share])
    moving, _ = refine(merged, views, K, config, 5)
    seen = ~np.all(moving.sh_dc == merged.sh_dc, axis=1) & from_share
    assert seen.any()  # without rates, B's views move some of A's Gaussians
    assert share_rates(from_share, EXACT) is None
    by_view = share_rates(
        from_share,
        MergeOptions(share_rate=0.0, by_view=True),
        np.full(len(merged), 3.0),
        np.full(len(merged), 1.0),
    )
    assert by_view is not None and np.allclose(by_view[from_share], 0.75)
