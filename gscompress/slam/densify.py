"""New Gaussians from RGB-D pixels (SplaTAM-style initialisation and densification).

Each selected pixel with valid depth becomes one isotropic Gaussian at its back-projected point,
coloured by the pixel, with opacity 0.5 and a standard deviation of depth / mean focal length
(the size of the pixel's footprint at that depth) times the sampling stride.
"""

from __future__ import annotations

import numpy as np

from gscompress.camera import Intrinsics
from gscompress.gaussians import SH_C0, GaussianMap


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
    x = (u - intrinsics.cx) / intrinsics.fx * z
    y = (v - intrinsics.cy) / intrinsics.fy * z
    points_cam = np.stack([x, y, z], axis=1)
    T = np.asarray(T_world_cam, dtype=np.float64)
    means = points_cam @ T[:3, :3].T + T[:3, 3]
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
