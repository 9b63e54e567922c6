"""New Gaussians from RGB-D pixels (SplaTAM-style initialisation and densification).

`densification_mask` picks the pixels of a frame that the map does not explain yet (SplaTAM's
silhouette and depth rule, optionally also where the rendered colour is far off and the map is
coarser there than the Gaussians it would add, `rendered_footprint`); `gaussians_from_rgbd`
turns selected pixels into Gaussians.

Each selected pixel with valid depth becomes one isotropic Gaussian at its back-projected point,
coloured by the pixel, with opacity 0.5 and a standard deviation of depth / mean focal length
(the size of the pixel's footprint at that depth) times the sampling stride.
"""

from __future__ import annotations

import numpy as np
import torch

from gscompress.camera import Intrinsics
from gscompress.gaussians import SH_C0, GaussianMap
from gscompress.render import render
from gscompress.slam.params import RenderInputs


def gaussians_from_rgbd(
    color: np.ndarray,
    depth: np.ndarray,
    intrinsics: Intrinsics,
    T_world_cam: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    stride: int = 1,
    first_id: int = 0,
    opacity: float = 0.5,
) -> GaussianMap:
    """Back-project pixels into isotropic Gaussians.

    Args:
        color: [H, W, 3] RGB in [0, 1].
        depth: [H, W] metres, 0 = invalid.
        intrinsics: pinhole intrinsics of the image (pixel centres at integer coordinates).
        T_world_cam: [4, 4] camera-to-world pose.
        mask: [H, W] bool, pixels that may spawn a Gaussian (default: all).
        stride: use every `stride`-th pixel in each direction.
        first_id: id of the first new Gaussian; the others follow consecutively.
        opacity: initial opacity in (0, 1).

    Returns:
        The new Gaussians (ids first_id, first_id + 1, ...), without importance.
    """
    keep = depth > 0
    if mask is not None:
        keep &= mask
    sub = np.zeros_like(keep)
    sub[::stride, ::stride] = True
    v, u = np.nonzero(keep & sub)
    z = depth[v, u].astype(np.float64)
    means = intrinsics.backproject(u, v, z, T_world_cam)
    focal = 0.5 * (intrinsics.fx + intrinsics.fy)
    n = len(z)
    quats = np.zeros((n, 4))
    quats[:, 0] = 1.0
    return GaussianMap.new(
        means=means,
        log_scales=np.log(z * stride / focal)[:, None],
        quats=quats,
        opacity_logits=np.full(n, np.log(opacity / (1.0 - opacity))),
        sh_dc=(color[v, u].astype(np.float64) - 0.5) / SH_C0,
        ids=np.arange(first_id, first_id + n, dtype=np.uint32),
    )


def densification_mask(
    silhouette: np.ndarray,
    rendered_depth: np.ndarray,
    depth: np.ndarray,
    *,
    silhouette_max: float = 0.5,
    depth_error_factor: float = 50.0,
    color_residual: np.ndarray | None = None,
    color_error: float = 0.0,
    footprint: np.ndarray | None = None,
    min_footprint: float = 0.0,
) -> np.ndarray:
    """[H, W] bool: observed pixels the map does not explain yet (SplaTAM's rule, plus colour).

    A pixel with a depth measurement qualifies when the rendered silhouette is below
    `silhouette_max` (nothing there yet), or when the observed surface lies in front of the
    rendered one by more than `depth_error_factor` times the median depth error over the
    observed, well-covered pixels (new geometry in front of the map). With `color_error` > 0
    it also qualifies when its `color_residual` is at least `color_error` (detail the map does
    not hold there yet, although it covers the pixel), provided the map's `footprint` there is
    wider than `min_footprint` pixels: where the map already shows the surface as finely as a
    new Gaussian would, a wrong colour is mapping's to correct, and another Gaussian would only
    add a second layer (on every revisit, as the map grew before).

    Args:
        silhouette: [H, W] rendered accumulated opacity.
        rendered_depth: [H, W] rendered expected depth (normalised by the silhouette).
        depth: [H, W] observed depth, 0 = invalid.
        silhouette_max: silhouette threshold.
        depth_error_factor: multiple of the median depth error.
        color_residual: [H, W] mean absolute RGB error of the render; needed when
            `color_error` > 0.
        color_error: colour threshold in RGB units (0-1); 0 leaves colour out.
        footprint: [H, W] the map's rendered footprint (`rendered_footprint`); None: the
            colour rule does not look at it.
        min_footprint: the footprint, in pixels, at or below which colour adds nothing.
    """
    valid = depth > 0
    empty = silhouette < silhouette_max
    covered = valid & ~empty
    front = np.zeros_like(valid)
    if np.any(covered):
        error = np.abs(rendered_depth - depth)
        threshold = depth_error_factor * float(np.median(error[covered]))
        front = covered & (rendered_depth > depth) & (error > threshold)
    off_colour = np.zeros_like(valid)
    if color_error > 0:
        if color_residual is None:
            raise ValueError("color_error > 0 needs color_residual")
        off_colour = covered & (color_residual >= color_error)
        if footprint is not None:
            off_colour &= footprint > min_footprint
    return valid & (empty | front | off_colour)


def rendered_footprint(
    inputs: RenderInputs, intrinsics: Intrinsics, T_cam_world: torch.Tensor, backend: str
) -> np.ndarray:
    """[H, W] how wide the Gaussians a view shows at each pixel are, in pixels.

    Each Gaussian's largest standard deviation over its camera depth, times the mean focal
    length, composited with the render's weights and divided by the silhouette (0 where the
    silhouette is 0). A Gaussian that `gaussians_from_rgbd` makes with stride s is s pixels
    wide at its own view.
    """
    with torch.no_grad():
        R, t = T_cam_world[:3, :3].to(inputs.means), T_cam_world[:3, 3].to(inputs.means)
        z = (inputs.means @ R.T + t)[:, 2].clamp(min=1e-6)
        focal = 0.5 * (intrinsics.fx + intrinsics.fy)
        width = inputs.scales.max(dim=-1).values * focal / z
        channels = torch.stack([width, torch.zeros_like(width), torch.zeros_like(width)], -1)
        out = render(
            inputs.means,
            inputs.quats,
            inputs.scales,
            inputs.opacities,
            channels,
            intrinsics,
            T_cam_world,
            backend=backend,
        )
        return (out.color[..., 0] / out.silhouette.clamp(min=1e-10)).cpu().numpy()
