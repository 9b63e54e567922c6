"""EWA projection of 3D Gaussians and 16x16 tile binning, shared by the torch and cpu backends.

Conventions (the rasterizer's spec; `gscompress.render` documents the compositing half):

- Pixel column `i`, row `j` has its centre at image coordinates `(u, v) = (i, j)`, the OpenCV /
  TUM convention in which `Intrinsics.cx, cy` are given.
- A Gaussian is culled when its camera depth `z < near`, when its projected covariance is not
  positive definite, or when its 3-sigma footprint touches no tile of the image.
- The 2D covariance is `J W Sigma W^T J^T + 0.3 I` (`W` the camera rotation, `J` the pinhole
  Jacobian at the Gaussian's centre). The 0.3 px^2 added to the diagonal is the usual low-pass
  dilation of 3DGS / gsplat (`eps2d`): it keeps every splat at least about a pixel wide, so
  tiny or distant Gaussians cannot alias between pixel centres. Like gsplat, the Jacobian is
  evaluated with `x/z`, `y/z` clamped to 0.3 tan(fov/2) beyond the image border, which bounds
  the footprint of Gaussians far outside the view.
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


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [N, 3, 3] from unnormalised (w, x, y, z) quaternions [N, 4]."""
    w, x, y, z = torch.unbind(quats / quats.norm(dim=-1, keepdim=True), dim=-1)  # [N] each
    rows = (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(-1, 3, 3)


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
    R_cw = T_cam_world[:3, :3]  # [3, 3]
    t_cw = T_cam_world[:3, 3]  # [3]

    p_cam = means @ R_cw.T + t_cw  # [N, 3]
    x, y, z = torch.unbind(p_cam, dim=-1)  # [N] each
    in_front = z >= near  # [N]
    # Culled Gaussians get a harmless depth so that no inf/nan reaches the backward pass.
    z_safe = torch.where(in_front, z, torch.ones_like(z))  # [N]

    M = quat_to_rotmat(quats) * scales[:, None, :]  # [N, 3, 3] = R S
    cov_world = M @ M.transpose(1, 2)  # [N, 3, 3]
    cov_cam = R_cw @ cov_world @ R_cw.T  # [N, 3, 3]

    lim_x_pos = (width - cx) / fx + 0.3 * (0.5 * width / fx)
    lim_x_neg = cx / fx + 0.3 * (0.5 * width / fx)
    lim_y_pos = (height - cy) / fy + 0.3 * (0.5 * height / fy)
    lim_y_neg = cy / fy + 0.3 * (0.5 * height / fy)
    tx = z_safe * torch.clamp(x / z_safe, -lim_x_neg, lim_x_pos)  # [N]
    ty = z_safe * torch.clamp(y / z_safe, -lim_y_neg, lim_y_pos)  # [N]
    zeros = torch.zeros_like(z_safe)
    J = torch.stack(
        [fx / z_safe, zeros, -fx * tx / (z_safe * z_safe),
         zeros, fy / z_safe, -fy * ty / (z_safe * z_safe)],
        dim=-1,
    ).reshape(-1, 2, 3)  # [N, 2, 3]  # fmt: skip
    cov2d = J @ cov_cam @ J.transpose(1, 2)  # [N, 2, 2]
    s_xx = cov2d[:, 0, 0] + EPS2D  # [N]
    s_xy = 0.5 * (cov2d[:, 0, 1] + cov2d[:, 1, 0])  # [N]
    s_yy = cov2d[:, 1, 1] + EPS2D  # [N]
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
    gids = torch.nonzero(projection.radii > 0).squeeze(1)  # [V]
    x0, x1, y0, y1 = tile_rects(
        projection.means2d[gids], projection.radii[gids], tiles_x, tiles_y
    )  # [V] each
    span_x = x1 - x0  # [V]
    counts = span_x * (y1 - y0)  # [V], >= 1 for a visible Gaussian
    starts = torch.cumsum(counts, 0) - counts  # [V]
    owner = torch.repeat_interleave(torch.arange(len(gids), device=device), counts)  # [I]
    local = torch.arange(len(owner), device=device) - starts[owner]  # [I]
    row, col = local // span_x[owner], local % span_x[owner]  # [I]
    tile = (y0[owner] + row) * tiles_x + x0[owner] + col  # [I]
    depth_bits = projection.depths.detach()[gids].float().view(torch.int32).long()  # [V]
    _, order = torch.sort(tile * 2**31 + depth_bits[owner], stable=True)  # [I]
    per_tile = torch.bincount(tile, minlength=n_tiles)  # [n_tiles]
    offsets = torch.zeros(n_tiles + 1, dtype=torch.int64, device=device)
    offsets[1:] = torch.cumsum(per_tile, 0)
    return TileBins(tiles_x=tiles_x, tiles_y=tiles_y, offsets=offsets, ids=gids[owner[order]])
