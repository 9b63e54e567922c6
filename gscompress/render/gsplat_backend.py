"""CUDA rendering through gsplat's `rasterization()` (optional extra `gscompress[gpu]`).

gsplat samples pixel (i, j) at (i + 0.5, j + 0.5) with `u = fx x / z + cx`, whereas gscompress
samples it at (i, j) (OpenCV convention); the principal point handed to gsplat is therefore
shifted by +0.5 px so that both put every Gaussian at the same place relative to the pixels.
gsplat's kernels are float32: float64 inputs are rendered in float32 and the outputs cast back.

gsplat clamps alpha at 0.999 where gscompress clamps at 0.99; opacities are therefore capped at
0.99 before they reach gsplat, so that an opaque Gaussian still lets 1% through and the
silhouette saturates at the same levels (0.99, 0.9999, ...) as on the other backends. For
o > 0.99 that gives alpha = 0.99 G instead of min(0.99, o G): slightly fainter edges.

Other known differences from the torch/cpu backends, all at the level of single pixels or
rounding: gsplat stops compositing when T would become <= 1e-4 (we stop at < 1e-4), and recent
gsplat versions size a Gaussian's tile footprint from its opacity (up to 3.33 sigma) instead of
3 sigma. That footprint decides only which pixels gsplat composites: the returned `radii`, and
so which Gaussians count as visible (the frames in a PWAS weight), come from gscompress's own
projection, run when they are first read, so a map scores alike on every backend.
tests/test_render.py checks that values agree with the pure-torch backend to 1e-5 and gradients
to 1e-4 relative, with opacities up to 0.35, where both footprints hold every pixel with alpha
>= 1/255 (what it gave with gsplat 1.5.3 on an H100, and with higher opacities:
docs/performance.md, "Renderer").
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
from typing import Any

import torch

from gscompress.camera import Intrinsics
from gscompress.errors import InputError, MissingDependencyError
from gscompress.render.output import RenderOutput, finish_output
from gscompress.render.projection import project_gaussians
from gscompress.render.torch_backend import ALPHA_MAX

logger = logging.getLogger(__name__)


@functools.cache
def gsplat_kernels() -> tuple[Callable[..., Any] | None, str | None]:
    """(gsplat's `rasterization`, None) once its CUDA kernels are loaded, else (None, why).

    gsplat loads or builds its kernels when `gsplat.cuda._backend` is imported (minutes on
    first use without prebuilt ones). The outcome is kept, so a failed build is neither retried
    nor reported again by later renders.
    """
    try:
        from gsplat import rasterization
    except ImportError:
        return None, "backend='gsplat' needs the gsplat package: pip install gscompress[gpu]"
    try:
        from gsplat.cuda._backend import _C
    except Exception as exc:  # a failed build raises the compiler's error
        reason = f" ({type(exc).__name__}: {(str(exc).splitlines() or [''])[0]})"
    else:
        if _C is not None:
            return rasterization, None
        reason = " (gsplat found no CUDA toolkit to build them with)"
    why = (
        f"gsplat is installed but its CUDA kernels could not be loaded or built{reason}; "
        "`backend` torch renders on CUDA without them"
    )
    logger.warning(why)
    return None, why


def load_gsplat() -> Callable[..., Any]:
    """gsplat's `rasterization`, its CUDA kernels loaded.

    Raises:
        MissingDependencyError: gsplat is not installed or its kernels cannot be loaded.
    """
    rasterization, why = gsplat_kernels()
    if rasterization is None:
        raise MissingDependencyError(why, options=("backend",))
    return rasterization


def render_gsplat(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    intrinsics: Intrinsics,
    T_cam_world: torch.Tensor,
    *,
    want_contribution: bool,
    near: float,
    background: torch.Tensor | None,
) -> RenderOutput:
    """`gscompress.render.render` on CUDA via gsplat (same arguments and output).

    The contribution uses the identity contribution_i = d(sum over pixels of an extra
    rendered channel) / d(f_i) with f_i = 1 for every Gaussian: that channel renders
    sum_i alpha_i T_i f_i, so its gradient w.r.t. f_i is sum over pixels of alpha_i T_i.

    Raises:
        InputError: the tensors are not on a CUDA device.
        MissingDependencyError: gsplat or its CUDA kernels cannot be loaded.
    """
    if means.device.type != "cuda":
        raise InputError(f"backend='gsplat' needs CUDA tensors, got {means.device}")
    rasterization = load_gsplat()

    dtype, device = means.dtype, means.device
    n = means.shape[0]
    if n == 0:
        raise InputError("render_gsplat needs at least one Gaussian (render() draws an empty map)")
    width, height = intrinsics.width, intrinsics.height
    K = torch.tensor(
        [
            [intrinsics.fx, 0.0, intrinsics.cx + 0.5],
            [0.0, intrinsics.fy, intrinsics.cy + 0.5],
            [0.0, 0.0, 1.0],
        ],
        dtype=torch.float32,
        device=device,
    )  # [3, 3]
    grad_wanted = torch.is_grad_enabled()
    with torch.enable_grad():
        features = colors.float()  # [N, 3]
        ones = None
        if want_contribution:
            ones = torch.ones(n, 1, dtype=torch.float32, device=device, requires_grad=True)
            features = torch.cat([features, ones], dim=1)  # [N, 4]
        rendered, alphas, _meta = rasterization(  # _meta's radii are opacity-sized: unused
            means.float(),
            quats.float(),
            scales.float(),
            opacities.float().clamp(max=ALPHA_MAX),
            features,
            T_cam_world.float()[None],
            K[None],
            width,
            height,
            near_plane=near,
            eps2d=0.3,
            packed=False,
            render_mode="RGB+D",
        )  # rendered [1, H, W, 3 (+1) + 1], alphas [1, H, W, 1]
        contribution = None
        if ones is not None:
            (grad_ones,) = torch.autograd.grad(
                rendered[0, ..., 3].sum(), ones, retain_graph=grad_wanted
            )  # [N, 1]
            contribution = grad_ones[:, 0].to(dtype)  # [N]
    rendered = rendered[0].to(dtype)  # [H, W, C]
    T_final = 1.0 - alphas[0, ..., 0].to(dtype)  # [H, W]
    if not grad_wanted:
        rendered, T_final = rendered.detach(), T_final.detach()
    # copies: an optimizer step may change the parameters in place before radii are read
    inputs = [t.detach().clone() for t in (means, quats, scales, T_cam_world)]

    def radii_of() -> torch.Tensor:
        with torch.no_grad():
            means, quats, scales, T_cam_world = inputs
            return project_gaussians(means, quats, scales, T_cam_world, intrinsics, near).radii

    return finish_output(
        rendered[..., :3],
        rendered[..., -1],
        T_final,
        radii_of,
        contribution,
        background,
        "gsplat",
    )
