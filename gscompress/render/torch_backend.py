"""Pure-torch tile compositing: the readable oracle of the C++ kernels and the fallback.

Vectorised over tiles and pixels (tiles are processed in padded chunks to bound memory); the
backward pass is torch autograd. The compositing rules are those documented in
`gscompress.render`.
"""

from __future__ import annotations

import torch

from gscompress.render.projection import TILE_SIZE, TileBins

ALPHA_MAX = 0.99
"""Upper clamp of a Gaussian's alpha."""

ALPHA_MIN = 1.0 / 255.0
"""Gaussians with alpha below this are skipped at a pixel."""

T_MIN = 1e-4
"""Compositing stops before a Gaussian that would bring transmittance below this."""

_CHUNK_ELEMENTS = 1 << 22
"""Upper bound on tiles x pixels x Gaussians handled in one vectorised chunk."""


def composite_torch(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    bins: TileBins,
    width: int,
    height: int,
    want_contribution: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Front-to-back alpha compositing of binned Gaussians.

    Args:
        means2d: [N, 2] pixel centres of the Gaussians.
        conics: [N, 3] inverse 2D covariances (a, b, c).
        opacities: [N] opacities in (0, 1).
        features: [N, C] per-Gaussian values to composite (colour and depth).
        bins: per-tile front-to-back Gaussian lists.
        width: image width in pixels.
        height: image height in pixels.
        want_contribution: also return sum over pixels of alpha_i T_i per Gaussian.

    Returns:
        image [H, W, C] = sum_i w_i f_i, final transmittance [H, W], contribution [N] or None.
    """
    n_ch = features.shape[1]
    dtype, device = features.dtype, features.device
    n_tiles = bins.tiles_x * bins.tiles_y
    P = TILE_SIZE * TILE_SIZE
    counts = (bins.offsets[1:] - bins.offsets[:-1]).tolist()  # [n_tiles]
    # Pixel centres of every tile; pixels beyond the image border are masked out.
    pix = torch.arange(P, device=device)
    local_x, local_y = pix % TILE_SIZE, pix // TILE_SIZE  # [P]
    tile_ids = torch.arange(n_tiles, device=device)
    px = (tile_ids % bins.tiles_x)[:, None] * TILE_SIZE + local_x  # [n_tiles, P]
    py = (tile_ids // bins.tiles_x)[:, None] * TILE_SIZE + local_y  # [n_tiles, P]
    inside = (px < width) & (py < height)  # [n_tiles, P]

    tile_feats = torch.zeros(n_tiles, P, n_ch, dtype=dtype, device=device)
    tile_T = torch.ones(n_tiles, P, dtype=dtype, device=device)
    feats_parts: list[torch.Tensor] = []
    T_parts: list[torch.Tensor] = []
    done_tiles: list[torch.Tensor] = []
    contribution = torch.zeros(len(opacities), dtype=dtype, device=device)

    start = 0
    while start < n_tiles:
        # Grow the chunk while the padded [B, P, K] block stays under the element budget.
        stop, k_max = start + 1, counts[start]
        while stop < n_tiles and (stop + 1 - start) * P * max(k_max, counts[stop], 1) <= (
            _CHUNK_ELEMENTS
        ):
            k_max = max(k_max, counts[stop])
            stop += 1
        chunk = torch.arange(start, stop, device=device)  # [B]
        start = stop
        if k_max == 0:
            continue
        k = torch.arange(k_max, device=device)  # [K]
        slot = bins.offsets[chunk][:, None] + k  # [B, K]
        valid = k < (bins.offsets[chunk + 1] - bins.offsets[chunk])[:, None]  # [B, K]
        gid = bins.ids[torch.where(valid, slot, torch.zeros_like(slot))]  # [B, K], 0 = pad

        dx = px[chunk][:, :, None].to(dtype) - means2d[gid][:, None, :, 0]  # [B, P, K]
        dy = py[chunk][:, :, None].to(dtype) - means2d[gid][:, None, :, 1]  # [B, P, K]
        a, b, c = conics[gid].unbind(-1)  # [B, K] each
        power = -0.5 * (a[:, None] * dx * dx + c[:, None] * dy * dy) - b[:, None] * dx * dy
        alpha = torch.clamp(opacities[gid][:, None] * torch.exp(power), max=ALPHA_MAX)
        keep = (alpha >= ALPHA_MIN) & valid[:, None, :] & inside[chunk][:, :, None]
        alpha = torch.where(keep, alpha, torch.zeros_like(alpha))  # [B, P, K]
        # The cumulative product is non-increasing, so "T after i stays >= T_MIN" is a prefix:
        # exactly the Gaussians composited before the stopping one (which is left out).
        T_after = torch.cumprod(1.0 - alpha, dim=-1)  # [B, P, K]
        alpha = torch.where(T_after >= T_MIN, alpha, torch.zeros_like(alpha))
        T_after = torch.cumprod(1.0 - alpha, dim=-1)  # [B, P, K]
        T_before = torch.cat([torch.ones_like(T_after[..., :1]), T_after[..., :-1]], dim=-1)
        weights = alpha * T_before  # [B, P, K]
        feats_parts.append(torch.einsum("bpk,bkc->bpc", weights, features[gid]))  # [B, P, C]
        T_parts.append(T_after[..., -1])  # [B, P]
        done_tiles.append(chunk)
        if want_contribution:
            per_slot = weights.detach().sum(dim=1)  # [B, K]
            contribution.index_add_(0, gid[valid], per_slot[valid])

    if done_tiles:
        index = torch.cat(done_tiles)
        tile_feats = tile_feats.index_put((index,), torch.cat(feats_parts))
        tile_T = tile_T.index_put((index,), torch.cat(T_parts))
    else:
        # Nothing visible: keep the outputs in the autograd graph so that callers can always
        # call backward (all gradients are then zero).
        anchor = 0.0 * (means2d.sum() + conics.sum() + opacities.sum() + features.sum())
        tile_feats, tile_T = tile_feats + anchor, tile_T + anchor
    image = _untile(tile_feats, bins, width, height)  # [H, W, C]
    T_final = _untile(tile_T[..., None], bins, width, height)[..., 0]  # [H, W]
    return image, T_final, (contribution if want_contribution else None)


def _untile(x: torch.Tensor, bins: TileBins, width: int, height: int) -> torch.Tensor:
    """[tiles, P, C] per-tile pixel values to a [H, W, C] image."""
    n_ch = x.shape[-1]
    x = x.reshape(bins.tiles_y, bins.tiles_x, TILE_SIZE, TILE_SIZE, n_ch)
    x = x.permute(0, 2, 1, 3, 4).reshape(bins.tiles_y * TILE_SIZE, bins.tiles_x * TILE_SIZE, n_ch)
    return x[:height, :width]
