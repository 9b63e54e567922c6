"""Autograd wrappers of the cpu backend's C++/OpenMP kernels: EWA projection and tile
compositing, each with its backward, tile binning, and the mean SSIM of the mapping loss with its
gradient. Each takes the extension `load_extension()` gave as its first argument.
"""

from __future__ import annotations

import functools
from types import ModuleType
from typing import Any

import torch

from gscompress.camera import Intrinsics
from gscompress.metrics import gaussian_window, ssim_constants
from gscompress.render.projection import Projection, TileBins, tile_grid


class _Composite(torch.autograd.Function):
    """Autograd wrapper: C++ forward, C++ backward."""

    @staticmethod
    def forward(
        ctx: Any,
        ext: ModuleType,
        means2d: torch.Tensor,
        conics: torch.Tensor,
        opacities: torch.Tensor,
        features: torch.Tensor,
        bins: TileBins,
        width: int,
        height: int,
        want_contribution: bool,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        geometry = (width, height, bins.tiles_x, bins.tiles_y)
        image, T_final, last, contribution, packed = ext.composite_forward(
            means2d,
            conics,
            opacities,
            features,
            bins.offsets,
            bins.ids,
            *geometry,
            want_contribution,
        )
        ctx.ext, ctx.geometry, ctx.n = ext, geometry, len(means2d)
        # The packed per-entry parameters are reused, so the backward reads no Gaussian twice.
        ctx.save_for_backward(packed, bins.offsets, bins.ids, T_final, last)
        ctx.mark_non_differentiable(contribution)
        return image, T_final, contribution

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(
        ctx: Any, grad_image: torch.Tensor, grad_T: torch.Tensor, _grad_contribution: Any
    ) -> tuple[Any, ...]:
        packed, offsets, ids, T_final, last = ctx.saved_tensors
        g_means2d, g_conics, g_opacities, g_features = ctx.ext.composite_backward(
            packed,
            offsets,
            ids,
            ctx.n,
            *ctx.geometry,
            T_final,
            last,
            grad_image.contiguous(),
            grad_T.contiguous(),
        )
        return None, g_means2d, g_conics, g_opacities, g_features, None, None, None, None


def composite_cpu(
    ext: ModuleType,
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    bins: TileBins,
    width: int,
    height: int,
    want_contribution: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """C++ counterpart of `gscompress.render.torch_backend.composite_torch` (same contract)."""
    image, T_final, contribution = _Composite.apply(
        ext,
        means2d.contiguous(),
        conics.contiguous(),
        opacities.contiguous(),
        features.contiguous(),
        bins,
        width,
        height,
        want_contribution,
    )
    return image, T_final, (contribution if want_contribution else None)


class _Project(torch.autograd.Function):
    """Autograd wrapper of the C++ projection: the backward recomputes it per Gaussian."""

    @staticmethod
    def forward(
        ctx: Any,
        ext: ModuleType,
        camera: tuple[float, float, float, float, int, int, float],
        means: torch.Tensor,
        quats: torch.Tensor,
        scales: torch.Tensor,
        T_cam_world: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        means2d, conics, depths, radii = ext.project_forward(
            means, quats, scales, T_cam_world, *camera
        )
        ctx.ext, ctx.camera = ext, camera
        ctx.save_for_backward(means, quats, scales, T_cam_world)
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, radii

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(
        ctx: Any, g_means2d: torch.Tensor, g_conics: torch.Tensor, g_depths: torch.Tensor, _: Any
    ) -> tuple[Any, ...]:
        # tracking renders detached Gaussians: then only the camera's gradient is computed
        want_params = any(ctx.needs_input_grad[2:5])
        d_means, d_quats, d_scales, d_T = ctx.ext.project_backward(
            *ctx.saved_tensors,
            *ctx.camera,
            g_means2d.contiguous(),
            g_conics.contiguous(),
            g_depths.contiguous(),
            want_params,
        )
        if not want_params:
            d_means = d_quats = d_scales = None
        return None, None, d_means, d_quats, d_scales, d_T


def project_cpu(
    ext: ModuleType,
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    T_cam_world: torch.Tensor,
    intrinsics: Intrinsics,
    near: float,
) -> Projection:
    """C++ counterpart of `gscompress.render.projection.project_gaussians` (same contract)."""
    i = intrinsics
    camera = (i.fx, i.fy, i.cx, i.cy, i.width, i.height, near)
    means2d, conics, depths, radii = _Project.apply(
        ext,
        camera,
        means.contiguous(),
        quats.contiguous(),
        scales.contiguous(),
        T_cam_world.contiguous(),
    )
    return Projection(means2d=means2d, conics=conics, depths=depths, radii=radii)


class _Ssim(torch.autograd.Function):
    """Autograd wrapper of the fused C++ mean SSIM; the gradient reaches the first image only."""

    @staticmethod
    def forward(
        ctx: Any,
        ext: ModuleType,
        x: torch.Tensor,
        y: torch.Tensor,
        k: torch.Tensor,
        constants: tuple[float, float],
    ) -> torch.Tensor:
        mean, filtered = ext.ssim_forward(x, y, k, *constants)
        ctx.ext, ctx.constants = ext, constants
        ctx.save_for_backward(x, y, k, filtered)
        return mean

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[Any, ...]:
        x, y, k, filtered = ctx.saved_tensors
        dx = ctx.ext.ssim_backward(x, y, k, filtered, grad, *ctx.constants)
        return None, dx, None, None, None


@functools.cache
def _ssim_window(dtype: torch.dtype) -> torch.Tensor:
    """SSIM's window in `dtype`, made once (the mapping loss asks at every iteration); the
    kernels only read it."""
    return gaussian_window().to(dtype=dtype).contiguous()


def ssim_mean_cpu(ext: ModuleType, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """C++ counterpart of `gscompress.metrics.ssim_maps(x[None], y[None])[0].mean()` for [C, H,
    W] images in [0, 1], differentiable in x; y (the observation) gets no gradient."""
    if y.requires_grad:
        raise ValueError("ssim_mean_cpu differentiates only its first image")
    k = _ssim_window(x.dtype)
    return _Ssim.apply(ext, x.contiguous(), y.to(x.dtype).contiguous(), k, ssim_constants(1.0))


def bin_tiles_cpu(ext: ModuleType, projection: Projection, width: int, height: int) -> TileBins:
    """C++ counterpart of `gscompress.render.projection.bin_tiles` (the same lists)."""
    tiles_x, tiles_y = tile_grid(width, height)
    offsets, ids = ext.bin_tiles(
        projection.means2d.detach().contiguous(),
        projection.radii.contiguous(),
        projection.depths.detach().contiguous(),
        tiles_x,
        tiles_y,
    )
    return TileBins(tiles_x=tiles_x, tiles_y=tiles_y, offsets=offsets, ids=ids)
