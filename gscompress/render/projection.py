"""EWA projection of 3D Gaussians and 16x16 tile binning: the torch backend's, and the oracle of
the cpu backend's C++ versions (`gscompress/render/cpu/project.cpp`).

Conventions (the rasterizer's spec; `gscompress.render` documents the compositing half):

- Pixel column `i`, row `j` has its centre at image coordinates `(u, v) = (i, j)`, the OpenCV /
  TUM convention in which `Intrinsics.cx, cy` are given.
- A Gaussian is culled when its camera depth `z < near`, when its projected covariance is not
  positive definite, or when its 3-sigma footprint touches no tile of the image.
- The 2D covariance is `J W Sigma W^T J^T + 0.3 I` (`W` the camera rotation, `J` the pinhole
  Jacobian at the Gaussian's centre). The 0.3 px^2 added to the diagonal is the usual low-pass
  dilation of 3DGS / gsplat (`eps2d`): it keeps every splat at least about a pixel wide, so
  tiny or distant Gaussians cannot alias between pixel centres. Like gsplat, the Jacobian is
  evaluated with `x/z`, `y/z` clamped to 0.3 tan(fov/2) beyond the image border (the outer
  pixel edges, u = -0.5 and u = width - 0.5), which bounds the footprint of Gaussians far
  outside the view.
- The radius is `ceil(3 sqrt(lambda_max))` px of the dilated 2D covariance.
- A Gaussian is binned to every 16x16 tile whose pixel centres span
  `[16 t, 16 t + 15]` intersects `[u - r, u + r]` (and likewise in `v`); within a tile the list
  is in increasing depth (as float32; ties by Gaussian index).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from gscompress.camera import Intrinsics

TILE_SIZE = 16
"""Edge of a square tile in pixels."""

EPS2D = 0.3
"""Low-pass dilation (px^2) added to the diagonal of every projected 2D covariance."""


@dataclass
class Projection:
    """Per-Gaussian screen-space quantities; differentiable except `radii`.

    Attributes:
        means2d: [N, 2] centre in pixels (u right, v down).
        conics: [N, 3] inverse 2D covariance as (a, b, c) of [[a, b], [b, c]].
        depths: [N] camera-space z.
        radii: [N] int32 footprint radius in pixels; 0 for a culled Gaussian.
    """

    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    radii: torch.Tensor


@dataclass
class TileBins:
    """Gaussian lists per tile, front to back.

    Attributes:
        tiles_x: number of tile columns.
        tiles_y: number of tile rows.
        offsets: [tiles_y * tiles_x + 1] int64; tile t's list is `ids[offsets[t]:offsets[t+1]]`.
        ids: [I] int64 Gaussian indices, sorted by tile (row-major) then depth.
    """

    tiles_x: int
    tiles_y: int
    offsets: torch.Tensor
    ids: torch.Tensor


def rotation_rows(quats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The three rows ([N, 3] each) of the rotations of unnormalised (w, x, y, z) quaternions."""
    w, x, y, z = torch.unbind(quats / quats.norm(dim=-1, keepdim=True), dim=-1)  # [N] each
    return (
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    )


def tile_grid(width: int, height: int) -> tuple[int, int]:
    """Number of tile columns and rows covering a `width` x `height` image."""
    return math.ceil(width / TILE_SIZE), math.ceil(height / TILE_SIZE)


def tile_rects(
    means2d: torch.Tensor, radii: torch.Tensor, tiles_x: int, tiles_y: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Half-open tile ranges [x0, x1) x [y0, y1) touched by each footprint ([N] int64 each).

    A range is empty (x1 <= x0 or y1 <= y0) when the footprint misses the image.
    """
    uv = means2d.detach()  # [N, 2]
    r = radii.to(uv.dtype)  # [N]
    u, v = uv[:, 0], uv[:, 1]
    x0 = torch.ceil((u - r - (TILE_SIZE - 1)) / TILE_SIZE).clamp(0, tiles_x).long()
    x1 = (torch.floor((u + r) / TILE_SIZE) + 1).clamp(0, tiles_x).long()
    y0 = torch.ceil((v - r - (TILE_SIZE - 1)) / TILE_SIZE).clamp(0, tiles_y).long()
    y1 = (torch.floor((v + r) / TILE_SIZE) + 1).clamp(0, tiles_y).long()
    return x0, x1, y0, y1


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    T_cam_world: torch.Tensor,
    intrinsics: Intrinsics,
    near: float,
) -> Projection:
    """Project activated 3D Gaussians into the image (EWA splatting); see the module docstring.

    Args:
        means: [N, 3] centres in world coordinates.
        quats: [N, 4] rotations (w, x, y, z), normalised here.
        scales: [N, 3] standard deviations along the rotated axes.
        T_cam_world: [4, 4] world-to-camera transform.
        intrinsics: pinhole intrinsics; the image size comes from it.
        near: Gaussians with camera depth below this are culled.

    Returns:
        The projection; gradients flow to every input through `means2d`, `conics`, `depths`.
    """
    fx, fy, cx, cy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
    width, height = intrinsics.width, intrinsics.height
    # Written with elementwise [N] / [N, 3] operations only: torch's batched 3x3 matmuls are
    # several times slower on CPU for this shape.
    W = T_cam_world[:3, :3]  # [3, 3] world-to-camera rotation
    t = T_cam_world[:3, 3]  # [3]
    x, y, z = ((means * W[i]).sum(-1) + t[i] for i in range(3))  # [N] each, camera frame
    in_front = z >= near  # [N]
    # Culled Gaussians get a harmless depth so that no inf/nan reaches the backward pass.
    z_safe = torch.where(in_front, z, torch.ones_like(z))  # [N]

    # Rows of W R S, whose outer product is the camera-frame covariance W R S S R^T W^T.
    M = [row * scales for row in rotation_rows(quats)]  # 3 x [N, 3], rows of R S
    WM = [W[i, 0] * M[0] + W[i, 1] * M[1] + W[i, 2] * M[2] for i in range(3)]  # 3 x [N, 3]

    # The image's border runs along the outer pixel edges, u = -0.5 and u = width - 0.5.
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    u_lo, u_hi = (cx + 0.5) / fx + 0.3 * tan_x, (width - 0.5 - cx) / fx + 0.3 * tan_x
    v_lo, v_hi = (cy + 0.5) / fy + 0.3 * tan_y, (height - 0.5 - cy) / fy + 0.3 * tan_y
    u = torch.clamp(x / z_safe, -u_lo, u_hi)
    v = torch.clamp(y / z_safe, -v_lo, v_hi)
    # Rows of J W R S with the pinhole Jacobian J = [[fx/z, 0, -fx u/z], [0, fy/z, -fy v/z]].
    inv_z = (1.0 / z_safe)[:, None]  # [N, 1]
    row_u = (fx * inv_z) * (WM[0] - u[:, None] * WM[2])  # [N, 3]
    row_v = (fy * inv_z) * (WM[1] - v[:, None] * WM[2])  # [N, 3]
    s_xx = (row_u * row_u).sum(-1) + EPS2D  # [N]
    s_xy = (row_u * row_v).sum(-1)  # [N]
    s_yy = (row_v * row_v).sum(-1) + EPS2D  # [N]
    det = s_xx * s_yy - s_xy * s_xy  # [N]
    ok = in_front & (det > 0)  # [N]
    det_safe = torch.where(ok, det, torch.ones_like(det))  # [N]
    conics = torch.stack([s_yy / det_safe, -s_xy / det_safe, s_xx / det_safe], dim=-1)  # [N, 3]
    means2d = torch.stack([fx * x / z_safe + cx, fy * y / z_safe + cy], dim=-1)  # [N, 2]

    with torch.no_grad():
        mid = 0.5 * (s_xx + s_yy)
        lam_max = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.0))  # [N]
        radii = torch.ceil(3.0 * torch.sqrt(lam_max.clamp(min=0.0)))
        radii = torch.where(ok & torch.isfinite(radii), radii, torch.zeros_like(radii))
        radii = radii.clamp(max=float(2**30)).to(torch.int32)  # [N]
        tiles_x, tiles_y = tile_grid(width, height)
        x0, x1, y0, y1 = tile_rects(means2d, radii, tiles_x, tiles_y)
        radii = torch.where((x1 > x0) & (y1 > y0), radii, torch.zeros_like(radii))
    return Projection(means2d=means2d, conics=conics, depths=z, radii=radii)


def bin_tiles(projection: Projection, width: int, height: int) -> TileBins:
    """Bin the visible Gaussians into 16x16 tiles, each list sorted front to back.

    One integer sort orders all (tile, Gaussian) pairs by the key `tile * 2^31 + depth bits`:
    the IEEE bits of a positive float32 sort like its value, so within a tile the order is by
    depth rounded to float32, ties by Gaussian index (the sort is stable).
    """
    tiles_x, tiles_y = tile_grid(width, height)
    n_tiles = tiles_x * tiles_y
    device = projection.radii.device
    take = torch.index_select  # much faster than advanced indexing on CPU
    gids = torch.nonzero(projection.radii > 0).squeeze(1)  # [V]
    x0, x1, y0, y1 = tile_rects(
        take(projection.means2d, 0, gids), take(projection.radii, 0, gids), tiles_x, tiles_y
    )  # [V] each
    span_x = x1 - x0  # [V]
    counts = span_x * (y1 - y0)  # [V], >= 1 for a visible Gaussian
    depth_bits = take(projection.depths.detach(), 0, gids).float().view(torch.int32).long()
    first = torch.cumsum(counts, 0) - counts  # [V] first slot of each Gaussian
    owner = torch.repeat_interleave(torch.arange(len(gids), device=device), counts)  # [I]
    # One gather of everything needed per (Gaussian, tile) slot.
    per_slot = take(torch.stack([first, span_x, x0, y0, depth_bits], dim=1), 0, owner)  # [I, 5]
    first_s, span_s, x0_s, y0_s, depth_s = per_slot.unbind(1)  # [I] each
    local = torch.arange(len(owner), device=device) - first_s  # [I] index within the rect
    row = local // span_s  # [I]
    tile = (y0_s + row) * tiles_x + x0_s + (local - row * span_s)  # [I]
    _, order = torch.sort(tile * 2**31 + depth_s, stable=True)  # [I]
    per_tile = torch.bincount(tile, minlength=n_tiles)  # [n_tiles]
    offsets = torch.zeros(n_tiles + 1, dtype=torch.int64, device=device)
    offsets[1:] = torch.cumsum(per_tile, 0)
    ids = take(gids, 0, take(owner, 0, order))  # [I]
    return TileBins(tiles_x=tiles_x, tiles_y=tiles_y, offsets=offsets, ids=ids)
