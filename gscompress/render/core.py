"""The `render()` front door: input checks, backend choice, and the shared post-processing."""

from __future__ import annotations

import functools
import logging

import torch

from gscompress.camera import Intrinsics
from gscompress.errors import InputError, MissingDependencyError
from gscompress.render.output import RenderOutput, finish_output
from gscompress.render.projection import bin_tiles, project_gaussians
from gscompress.render.torch_backend import composite_torch

logger = logging.getLogger(__name__)


def _warm_up_vector_math() -> None:
    """Call torch's vectorised transcendental functions once, on one thread, at import.

    With torch 2.13's CPU build on an AVX-512 Xeon, the first torch.exp of a process that ran
    on two threads (2048 elements or more) sometimes came back with one thread's half of the
    tensor slightly off; every later call was exact to rounding. In `gsc slam` that first call
    is the activation of the scales at frame 0, so some runs took a different course. A first
    call below torch's parallel grain (one thread, still vectorised) made none do so (measured
    in docs/performance.md, "Reproducibility and threads"). The same is done for the other
    functions the maps and losses use.
    """
    x = torch.linspace(0.5, 1.5, 1024)
    for fn in (torch.exp, torch.log, torch.sqrt, torch.sigmoid, torch.tanh):
        fn(x)


_warm_up_vector_math()

BACKENDS = ("auto", "torch", "cpu", "gsplat")
"""Accepted values of `render(..., backend=...)`."""


def render(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    intrinsics: Intrinsics,
    T_cam_world: torch.Tensor,
    *,
    backend: str = "auto",
    want_contribution: bool = False,
    near: float = 0.01,
    background: torch.Tensor | None = None,
) -> RenderOutput:
    """Differentiably render colour, depth and silhouette of activated 3D Gaussians.

    EWA splatting with 16x16 tiles and front-to-back compositing, as in 3DGS; the exact rules
    are in the `gscompress.render` module docstring. Every output except `radii` and
    `contribution` is differentiable w.r.t. every input tensor (`background` included).

    Args:
        means: [N, 3] centres in world coordinates.
        quats: [N, 4] rotations (w, x, y, z), need not be normalised.
        scales: [N, 3] standard deviations (expand isotropic scales to 3 columns).
        opacities: [N] opacities in (0, 1).
        colors: [N, 3] RGB.
        intrinsics: pinhole intrinsics; the image size is `intrinsics.width` x `.height`.
        T_cam_world: [4, 4] world-to-camera transform.
        backend: "torch" (pure torch), "cpu" (C++ kernels; pure torch if no compiler), "gsplat"
            (CUDA) or "auto" (gsplat for CUDA tensors when installed, else cpu, else torch).
        want_contribution: also compute the per-Gaussian sum over pixels of alpha_i T_i.
        near: Gaussians with camera depth z < near are culled.
        background: [3] colour seen where the Gaussians leave transmittance; None for black.

    Returns:
        The rendered view.

    Raises:
        InputError: on inconsistent shapes, dtypes or devices, or an unknown backend.
        MissingDependencyError: backend="gsplat" without gsplat installed.
    """
    _check_inputs(means, quats, scales, opacities, colors, intrinsics, T_cam_world, background)
    if not near > 0:
        raise InputError(f"near must be positive, got {near}")
    backend = resolve_backend(backend, means.device)
    if backend == "gsplat" and means.shape[0] == 0:
        backend = "torch"  # nothing to rasterize; the pure-torch path handles it on any device
    if backend == "gsplat":
        from gscompress.render.gsplat_backend import render_gsplat

        return render_gsplat(
            means,
            quats,
            scales,
            opacities,
            colors,
            intrinsics,
            T_cam_world,
            want_contribution=want_contribution,
            near=near,
            background=background,
        )

    project, bin_, composite = project_gaussians, bin_tiles, composite_torch
    if backend == "cpu":
        from gscompress.render import cpu

        ext = cpu.load_extension()  # cached: resolve_backend has built or loaded it
        if ext is not None:
            project = functools.partial(cpu.project_cpu, ext)
            bin_ = functools.partial(cpu.bin_tiles_cpu, ext)
            composite = functools.partial(cpu.composite_cpu, ext)

    width, height = intrinsics.width, intrinsics.height
    proj = project(means, quats, scales, T_cam_world, intrinsics, near)
    bins = bin_(proj, width, height)
    features = torch.cat([colors, proj.depths[:, None]], dim=1)  # [N, 4] r g b z
    image, T_final, contribution = composite(
        proj.means2d, proj.conics, opacities, features, bins, width, height, want_contribution
    )
    radii = proj.radii  # the closure keeps only these, not the projection's autograd graph
    return finish_output(
        image[..., :3], image[..., 3], T_final, lambda: radii, contribution, background, backend
    )


def gsplat_available() -> bool:
    """Whether gsplat can be imported (without importing it twice)."""
    import importlib.util

    return importlib.util.find_spec("gsplat") is not None


def resolve_backend(backend: str, device: torch.device) -> str:
    """The backend `render` uses for `backend` and tensors on `device`, ready to run.

    "auto" becomes gsplat for CUDA tensors when installed, else cpu on the CPU, else torch.
    "cpu" builds the C++ kernels on first use (under a minute, once per machine) and "gsplat" loads
    gsplat's CUDA kernels, which gsplat builds on first use when it has no prebuilt ones
    (minutes); calling this before a timed loop keeps either build out of it. When they cannot
    be built, "cpu" and an "auto" that picked gsplat become torch (with a warning).

    Raises:
        InputError: an unknown backend, or "cpu" / "gsplat" for tensors on the other device.
        MissingDependencyError: "gsplat" asked for, and it or its kernels cannot be loaded.
    """
    if backend not in BACKENDS:
        raise InputError(f"unknown render backend {backend!r}; choose one of {BACKENDS}")
    asked = backend
    if backend == "auto":
        if device.type == "cuda":
            backend = "gsplat" if gsplat_available() else "torch"
        else:
            backend = "cpu" if device.type == "cpu" else "torch"
    if backend == "cpu":
        if device.type != "cpu":
            raise InputError(f"backend='cpu' needs CPU tensors, got {device}")
        from gscompress.render.cpu import load_extension

        if load_extension() is None:
            return "torch"
    if backend == "gsplat":
        if device.type != "cuda":
            raise InputError(f"backend='gsplat' needs CUDA tensors, got {device}")
        from gscompress.render.gsplat_backend import gsplat_kernels

        rasterization, why = gsplat_kernels()
        if rasterization is None:
            if asked == "auto":
                return "torch"
            raise MissingDependencyError(why, options=("backend",))
    return backend


def resolve_device(device: str | torch.device, backend: str = "auto") -> torch.device:
    """`auto` -> the device the render `backend` runs on ("cpu": the CPU, "gsplat": CUDA), or
    for the other backends cuda when available, else cpu; anything else as torch understands it.
    """
    if str(device) == "auto":
        if backend != "cpu" and torch.cuda.is_available():
            return torch.device("cuda")
        if backend == "gsplat":
            raise InputError("backend 'gsplat' renders on CUDA, but torch sees no CUDA device")
        return torch.device("cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError(
            "`device` cuda asked for, but torch sees no CUDA device", options=("device",)
        )
    return dev


def _check_inputs(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    intrinsics: Intrinsics,
    T_cam_world: torch.Tensor,
    background: torch.Tensor | None,
) -> None:
    n = means.shape[0] if means.dim() == 2 else -1
    expected = {
        "means": (means, (n, 3), "[N, 3]"),
        "quats": (quats, (n, 4), "[N, 4]"),
        "scales": (scales, (n, 3), "[N, 3]"),
        "opacities": (opacities, (n,), "[N]"),
        "colors": (colors, (n, 3), "[N, 3]"),
        "T_cam_world": (T_cam_world, (4, 4), "[4, 4]"),
    }
    if background is not None:
        expected["background"] = (background, (3,), "[3]")
    for name, (tensor, shape, shown) in expected.items():
        if not isinstance(tensor, torch.Tensor):
            raise InputError(f"{name} must be a torch.Tensor, got {type(tensor).__name__}")
        if tuple(tensor.shape) != shape:
            raise InputError(f"{name} must have shape {shown}, got {list(tensor.shape)}")
        if tensor.dtype not in (torch.float32, torch.float64):
            raise InputError(f"{name} must be float32 or float64, got {tensor.dtype}")
        if tensor.dtype != means.dtype or tensor.device != means.device:
            raise InputError(
                f"{name} is {tensor.dtype} on {tensor.device} but means is "
                f"{means.dtype} on {means.device}"
            )
    if intrinsics.width <= 0 or intrinsics.height <= 0:
        raise InputError(f"image size must be positive, got {intrinsics.width}x{intrinsics.height}")
