"""The SLAM losses: tracking (paper Eq. 4-5) and mapping (paper Eq. 2-3).

Images are [H, W, 3] in [0, 1], depths [H, W] in metres with 0 = no measurement. Mapping
compares the renderer's sum_i w_i z_i (not normalised) with the observed depth, which also pulls
the silhouette towards 1 on observed pixels (as in SplaTAM). Tracking compares the normalised
(expected) depth instead: on its mask the silhouette is only known to exceed 0.99, and the
unnormalised depth would be biased by up to 1% of the depth (4 cm at 4 m), enough to pull the
pose along the optical axis. The price is a smaller offset of the other sign where mapping has
fitted the accumulated depth with a silhouette just below 1: against a map built from
ground-truth poses, tracking from the true pose settles slightly away from it, mostly along the
optical axis (less so on the accumulated depth). End to end, though, tracking on the accumulated
depth measured a worse ATE, and so did mapping on the normalised depth plus a silhouette term
(docs/design-experiments.md, "What moves B's ATE in inject mode").

Tracking:
    mask = (silhouette > s_min) & (D_gt > 0) & (|D_norm - D_gt| <= k median |D_norm - D_gt|)
    L_color = mean_mask |I - I_gt|,   L_depth = mean_mask |D_norm - D_gt|
    w_im = g_im / (L_color + g_im),   w_depth = g_d / (L_depth + g_d)   (from detached losses)
    L_track = w_im L_color + w_depth L_depth + lambda (log(w_depth / w_im) - log rho)^2
The weights shrink a term whose error is large relative to its scale g, a robust per-frame
balance of colour against depth. Because they come from detached losses, the balance term is
a constant for the optimiser (zero gradient): it is reported, as in the paper, but steers nothing.

Mapping:
    L_map = a L_color + b L_depth + w_illum L_illum
    L_color = 0.8 L1 + 0.2 (1 - SSIM) over the whole image, L_depth = L1 on D_gt > 0,
    L_illum = mean |I - I_fuse|,  w_illum = min(L_illum / (L_color + eps), tau)  (detached).

The fusion Phi (the paper leaves it open) chosen here is a depth-edge-aware blend, see
`fuse_target`: I_fuse = e I_gt + (1 - e) sg(I_render), where e = 1 - exp(-g / sigma) grows with
the relative depth gradient g = |grad D_gt| / D_gt and sg stops gradients. On flat geometry the
target is the render itself (no loss, no gradient); across depth discontinuities it is the
observed image. L_illum is thus an L1 loss concentrated on depth edges, where splats of the
foreground and background blend and colour bleeds across object boundaries; w_illum scales it to
the size of the colour loss, capped at tau.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from gscompress.metrics import ssim_maps
from gscompress.render import RenderOutput
from gscompress.slam.config import MappingConfig, TrackingConfig

EPS = 1e-8


@dataclass
class LossTerms:
    """A loss to minimise and its parts (plain floats, for stats).

    Attributes:
        total: the scalar tensor to backpropagate.
        color, depth, illum: the unweighted terms.
        weights: named weights that were applied (w_im, w_depth, w_illum, ...).
        pixels: pixels that entered the loss (tracking: the mask's size).
    """

    total: torch.Tensor
    color: float
    depth: float
    illum: float = 0.0
    weights: dict[str, float] | None = None
    pixels: int = 0


def masked_mean(values: torch.Tensor, mask: torch.Tensor, count: int) -> torch.Tensor:
    """Mean of `values` where `mask` holds (`count` = mask.sum() > 0); no gradient elsewhere."""
    return torch.where(mask, values, 0.0).sum() / count


def masked_median(values: torch.Tensor, mask: torch.Tensor, count: int) -> torch.Tensor:
    """`values[mask].median()` (the lower middle value) without gathering the masked values.

    `count` = mask.sum() must be > 0. Unlike `median()`, a NaN among the masked values does not
    make the result NaN: `kthvalue` orders NaN above every number, so NaN pixels count as the
    largest (and the tracking outlier rule then leaves them out).
    """
    filled = torch.where(mask, values, torch.inf).flatten()
    return filled.kthvalue((count + 1) // 2).values


def tracking_mask(
    silhouette: torch.Tensor, depth_gt: torch.Tensor, silhouette_min: float
) -> torch.Tensor:
    """[H, W] bool: pixels the tracking loss uses (well-mapped and with a depth measurement)."""
    return (silhouette.detach() > silhouette_min) & (depth_gt > 0)


def adaptive_weights(
    loss_color: torch.Tensor, loss_depth: torch.Tensor, config: TrackingConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """(w_im, w_depth) = (g_im / (L_c + g_im), g_d / (L_d + g_d)) from the detached losses."""
    lc, ld = loss_color.detach(), loss_depth.detach()
    return config.gamma_color / (lc + config.gamma_color), config.gamma_depth / (
        ld + config.gamma_depth
    )


def tracking_loss(
    out: RenderOutput, color_gt: torch.Tensor, depth_gt: torch.Tensor, config: TrackingConfig
) -> LossTerms:
    """Paper Eq. 4-5 on one rendered view (see the module docstring).

    Args:
        out: the render at the pose being optimised.
        color_gt: [H, W, 3] observed colour.
        depth_gt: [H, W] observed depth, 0 = invalid.
        config: tracking settings (silhouette threshold, gammas, lambda, rho).

    Returns:
        The terms; `total` is 0 (without gradient) when no pixel passes the mask.
    """
    mask = tracking_mask(out.silhouette, depth_gt, config.silhouette_min)
    depth_error = (out.depth_normalized - depth_gt).abs()
    count = int(mask.sum())
    if config.outlier_factor > 0 and count:
        # SplaTAM's outlier rule: depth errors far above the median are unmodelled geometry
        # (depth edges, missing surfaces), not pose error
        limit = config.outlier_factor * masked_median(depth_error.detach(), mask, count)
        mask = mask & (depth_error.detach() <= limit)
        count = int(mask.sum())
    if count == 0:
        zero = out.color.sum() * 0.0
        return LossTerms(total=zero, color=0.0, depth=0.0, weights={}, pixels=0)
    # masked sums rather than boolean indexing: the same means without a gather and a scatter
    # per term and iteration
    l_color = masked_mean((out.color - color_gt).abs().mean(dim=-1), mask, count)
    l_depth = masked_mean(depth_error, mask, count)
    w_im, w_depth = adaptive_weights(l_color, l_depth, config)
    balance = (
        config.balance_weight
        * (torch.log(w_depth / w_im) - torch.log(torch.as_tensor(config.rho, dtype=w_im.dtype)))
        ** 2
    )
    total = w_im * l_color + w_depth * l_depth + balance
    return LossTerms(
        total=total,
        color=float(l_color.detach()),
        depth=float(l_depth.detach()),
        weights={"w_im": float(w_im), "w_depth": float(w_depth), "balance": float(balance)},
        pixels=count,
    )


def depth_edges(depth: torch.Tensor, sigma: float) -> torch.Tensor:
    """[H, W] edge strength e = 1 - exp(-(|grad D| / D) / sigma) in [0, 1).

    The gradient is the larger absolute forward/backward difference of each pixel to its four
    neighbours, divided by the pixel's depth so that a step means the same near and far. A pixel
    next to a missing measurement is not an edge (0), nor is a pixel without depth.
    """
    d = depth
    pad = F.pad(d[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]  # [H+2, W+2]
    centre = pad[1:-1, 1:-1]
    grad = torch.zeros_like(d)
    valid = d > 0
    for neighbour in (pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]):
        both = valid & (neighbour > 0)
        grad = torch.where(both, torch.maximum(grad, (neighbour - centre).abs()), grad)
    rel = torch.where(valid, grad / d.clamp_min(EPS), torch.zeros_like(d))
    return 1.0 - torch.exp(-rel / sigma)


def fuse_target(
    color_render: torch.Tensor, color_gt: torch.Tensor, edges: torch.Tensor
) -> torch.Tensor:
    """Phi: the illumination pseudo-target I_fuse = e I_gt + (1 - e) sg(I_render).

    Args:
        color_render: [H, W, 3] rendered colour.
        color_gt: [H, W, 3] observed colour.
        edges: [H, W] edge strength e of the observed depth (`depth_edges`).

    Returns:
        [H, W, 3] target without gradient: the render on flat geometry, the observation on
        depth discontinuities.
    """
    e = edges[..., None]
    return (e * color_gt + (1.0 - e) * color_render.detach()).detach()


def ssim_mean(image: torch.Tensor, reference: torch.Tensor, backend: str = "torch") -> torch.Tensor:
    """Mean SSIM (window 11, sigma 1.5; `gscompress.metrics`) of [H, W, 3] images in [0, 1],
    differentiable in `image`.

    Renders of the cpu backend use its fused C++ kernel (equal to the torch maps to rounding),
    which replaces some forty small tensor operations per mapping iteration.
    """
    x = image.permute(2, 0, 1)
    y = reference.permute(2, 0, 1)
    if backend == "cpu" and not reference.requires_grad:
        from gscompress.render import cpu

        ext = cpu.load_extension()  # cached; a cpu render implies it loaded
        if ext is not None:
            return cpu.ssim_mean_cpu(ext, x, y)
    return ssim_maps(x[None], y[None], 1.0)[0].mean()


def mapping_loss(
    out: RenderOutput,
    color_gt: torch.Tensor,
    depth_gt: torch.Tensor,
    config: MappingConfig,
    edges: torch.Tensor | None = None,
) -> LossTerms:
    """Paper Eq. 2-3 on one rendered view (see the module docstring).

    Args:
        out: the render of the current Gaussians at the view's (fixed) pose.
        color_gt: [H, W, 3] observed colour.
        depth_gt: [H, W] observed depth, 0 = invalid.
        config: mapping settings (weights, SSIM share, tau, edge sigma).
        edges: `depth_edges(depth_gt, config.illum_edge_sigma)` when the caller keeps it (a
            view's is the same at every iteration); computed here when None.
    """
    l1 = (out.color - color_gt).abs().mean()
    if config.ssim_weight > 0 and min(color_gt.shape[:2]) >= 11:
        l_color = (1.0 - config.ssim_weight) * l1 + config.ssim_weight * (
            1.0 - ssim_mean(out.color, color_gt, out.backend)
        )
    else:
        l_color = l1
    valid = depth_gt > 0
    count = int(valid.sum())
    l_depth = masked_mean((out.depth - depth_gt).abs(), valid, count) if count else l1 * 0.0
    total = config.color_weight * l_color + config.depth_weight * l_depth
    l_illum_value, w_illum_value = 0.0, 0.0
    if config.illum_tau > 0:
        if edges is None:
            edges = depth_edges(depth_gt, config.illum_edge_sigma)
        target = fuse_target(out.color, color_gt, edges)
        l_illum = (out.color - target).abs().mean()
        w_illum = torch.clamp(l_illum.detach() / (l_color.detach() + EPS), max=config.illum_tau)
        total = total + w_illum * l_illum
        l_illum_value, w_illum_value = float(l_illum.detach()), float(w_illum)
    return LossTerms(
        total=total,
        color=float(l_color.detach()),
        depth=float(l_depth.detach()),
        illum=l_illum_value,
        weights={"w_illum": w_illum_value},
        pixels=int(color_gt.shape[0] * color_gt.shape[1]),
    )
