"""SLAM losses: tracking mask and detached adaptive weights, the fusion target, mapping loss."""

import numpy as np
import pytest
import torch

from gscompress.render import RenderOutput
from gscompress.slam.config import MappingConfig, TrackingConfig
from gscompress.slam.losses import (
    adaptive_weights,
    depth_edges,
    fuse_target,
    mapping_loss,
    masked_median,
    tracking_loss,
    tracking_mask,
)

H, W = 24, 32


def fake_render(color, depth, silhouette):
    """A RenderOutput built from tensors (only the fields the losses read matter)."""
    return RenderOutput(
        color=color,
        depth=depth,
        depth_normalized=depth / silhouette.clamp_min(1e-10),
        silhouette=silhouette,
        contribution=None,
        backend="torch",
        radii_of=lambda: torch.zeros(0, dtype=torch.int32),
    )


@pytest.fixture()
def scene():
    g = torch.Generator().manual_seed(0)
    color_gt = torch.rand(H, W, 3, generator=g)
    depth_gt = 1.0 + torch.rand(H, W, generator=g)
    depth_gt[0, :5] = 0.0  # missing measurements
    color = (color_gt + 0.1 * torch.randn(H, W, 3, generator=g)).requires_grad_(True)
    depth = (depth_gt + 0.05 * torch.randn(H, W, generator=g)).requires_grad_(True)
    silhouette = torch.full((H, W), 0.999)
    silhouette[5:10, 5:10] = 0.99  # exactly at the threshold: excluded
    silhouette[12:, 20:] = 0.3
    return color_gt, depth_gt, color, depth, silhouette


def test_tracking_mask_excludes_low_silhouette_and_missing_depth(scene):
    _, depth_gt, _, _, silhouette = scene
    mask = tracking_mask(silhouette, depth_gt, 0.99)
    assert not mask[5:10, 5:10].any() and not mask[12:, 20:].any() and not mask[0, :5].any()
    assert mask[2, 2] and mask[11, 15]
    assert int(mask.sum()) == H * W - 25 - 12 * 12 - 5


def test_tracking_loss_ignores_masked_pixels(scene):
    color_gt, depth_gt, color, depth, silhouette = scene
    config = TrackingConfig()
    a = tracking_loss(fake_render(color, depth, silhouette), color_gt, depth_gt, config)
    color2, depth2 = color.detach().clone(), depth.detach().clone()
    color2[5:10, 5:10] = 7.0  # wrong only where the silhouette is <= 0.99
    depth2[12:, 20:] = -3.0
    b = tracking_loss(fake_render(color2, depth2, silhouette), color_gt, depth_gt, config)
    assert float(a.total.detach()) == pytest.approx(float(b.total.detach()), rel=1e-6)
    assert a.pixels == b.pixels == int(tracking_mask(silhouette, depth_gt, 0.99).sum())


def test_adaptive_weights_carry_no_gradient(scene):
    color_gt, depth_gt, color, depth, silhouette = scene
    config = TrackingConfig(balance_weight=3.0, rho=2.0, outlier_factor=0.0)
    mask = tracking_mask(silhouette, depth_gt, config.silhouette_min)
    l_color = (color - color_gt).abs().mean(-1)[mask].mean()
    l_depth = (depth / silhouette - depth_gt).abs()[mask].mean()  # normalised depth
    w_im, w_depth = adaptive_weights(l_color, l_depth, config)
    assert not w_im.requires_grad and not w_depth.requires_grad
    expected = config.gamma_color / (float(l_color.detach()) + config.gamma_color)
    assert float(w_im) == pytest.approx(expected)
    # the total's gradient is that of w_im L_color + w_depth L_depth: the balance term is constant
    terms = tracking_loss(fake_render(color, depth, silhouette), color_gt, depth_gt, config)
    assert terms.weights is not None and terms.weights["balance"] > 0
    g_total = torch.autograd.grad(terms.total, [color, depth])
    g_plain = torch.autograd.grad(w_im * l_color + w_depth * l_depth, [color, depth])
    for a, b in zip(g_total, g_plain, strict=True):
        torch.testing.assert_close(a, b)


def test_tracking_leaves_out_depth_outliers(scene):
    color_gt, depth_gt, color, depth, silhouette = scene
    depth = depth.detach().clone()
    depth[20, 3] += 5.0  # a 5 m error: far above 10x the median (~4 cm)
    out = fake_render(color, depth, silhouette)
    kept = tracking_loss(out, color_gt, depth_gt, TrackingConfig(outlier_factor=10.0))
    everything = tracking_loss(out, color_gt, depth_gt, TrackingConfig(outlier_factor=0.0))
    assert kept.pixels == everything.pixels - 1  # only that pixel is left out
    assert kept.depth < 0.1 and everything.depth > kept.depth + 4.0 / everything.pixels


def test_masked_median_equals_the_median_of_the_masked_values():
    """Odd and even counts, a single pixel and all pixels: torch's median (the lower middle
    value) of values[mask], with values above and below the masked ones left out."""
    g = torch.Generator().manual_seed(5)
    values = torch.randn(6, 7, generator=g)
    order = torch.randperm(values.numel(), generator=g)
    for count in (1, 2, 3, 10, 11, values.numel()):
        mask = torch.zeros(values.numel(), dtype=torch.bool)
        mask[order[:count]] = True
        mask = mask.reshape(values.shape)
        assert torch.equal(masked_median(values, mask, count), values[mask].median())


def test_tracking_loss_is_zero_without_pixels(scene):
    color_gt, depth_gt, color, depth, _ = scene
    out = fake_render(color, depth, torch.full((H, W), 0.5))
    terms = tracking_loss(out, color_gt, depth_gt, TrackingConfig())
    assert terms.pixels == 0 and float(terms.total.detach()) == 0.0


def test_depth_edges_flat_is_zero_and_steps_are_edges():
    depth = torch.full((H, W), 2.0)
    assert float(depth_edges(depth, 0.05).abs().max()) == 0.0
    depth[:, 16:] = 4.0  # a 2 m step between columns 15 and 16
    depth[0, 0] = 0.0
    e = depth_edges(depth, 0.05)
    assert float(e[:, 15:17].min()) > 0.99
    assert float(e[3:, :14].max()) == 0.0 and float(e[:, 18:].max()) == 0.0
    assert float(e[0, 0]) == 0.0  # no depth, no edge
    assert float(e[0, 1]) == 0.0  # next to a hole is not an edge
    # relative: the same 5 cm step is a stronger edge at 1 m than at 4 m
    near = torch.full((4, 8), 1.0)
    near[:, 4:] += 0.05
    far = torch.full((4, 8), 4.0)
    far[:, 4:] += 0.05
    assert float(depth_edges(near, 0.05)[0, 3]) > float(depth_edges(far, 0.05)[0, 3])


def test_fuse_target_is_render_on_flat_geometry_and_observation_on_edges():
    g = torch.Generator().manual_seed(1)
    render_color = torch.rand(H, W, 3, generator=g, requires_grad=True)
    color_gt = torch.rand(H, W, 3, generator=g)
    depth = torch.full((H, W), 1.5)
    depth[:, 16:] = 3.0
    target = fuse_target(render_color, color_gt, depth_edges(depth, 0.05))
    assert not target.requires_grad
    flat = depth_edges(depth, 0.05) == 0
    torch.testing.assert_close(target[flat], render_color.detach()[flat])
    edge = depth_edges(depth, 0.05) > 0.999
    assert edge.any()
    torch.testing.assert_close(target[edge], color_gt[edge], atol=2e-3, rtol=0)
    # so L_illum = mean |I - I_fuse| pulls only edge pixels towards the observation
    loss = (render_color - target).abs().mean()
    (grad,) = torch.autograd.grad(loss, [render_color])
    assert float(grad[flat].abs().max()) == 0.0 and float(grad[edge].abs().min()) > 0


def test_mapping_loss_terms_and_capped_detached_illum_weight(scene):
    color_gt, depth_gt, color, depth, _ = scene
    depth_gt = depth_gt.clone()
    depth_gt[:, 16:] *= 3.0  # depth edges, so L_illum is not zero
    out = fake_render(color, depth, torch.ones(H, W))
    config = MappingConfig(illum_tau=0.05)
    terms = mapping_loss(out, color_gt, depth_gt, config)
    valid = depth_gt > 0
    l1 = float((color.detach() - color_gt).abs().mean())
    expected_depth = float((depth.detach() - depth_gt).abs()[valid].mean())
    assert terms.depth == pytest.approx(expected_depth, rel=1e-6)
    assert terms.color < l1  # 0.8 L1 + 0.2 (1 - SSIM), SSIM of a noisy copy > 1 - L1 here
    assert terms.illum > 0 and terms.weights is not None
    w = terms.weights["w_illum"]
    assert w == pytest.approx(min(terms.illum / terms.color, 0.05), rel=1e-5)
    expected = 0.5 * terms.color + terms.depth + w * terms.illum
    assert float(terms.total.detach()) == pytest.approx(expected, rel=1e-5)
    no_illum = mapping_loss(out, color_gt, depth_gt, MappingConfig(illum_tau=0.0))
    assert no_illum.illum == 0.0
    assert float(no_illum.total.detach()) == pytest.approx(
        0.5 * terms.color + terms.depth, rel=1e-5
    )
    terms.total.backward()
    assert color.grad is not None and np.isfinite(color.grad.numpy()).all()
