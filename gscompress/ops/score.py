"""PWAS scores for an existing map: render it from a sequence's views and accumulate.

No optimisation happens: a map made by any 3DGS tool (or by gsc) gets its importance sums from
the views it is seen from, so that it can be pruned and shared like a map recorded by
`gsc slam`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np
import torch

from gscompress.camera import Intrinsics, invert_transform
from gscompress.gaussians import GaussianMap
from gscompress.importance import ImportanceSums
from gscompress.render import render
from gscompress.render.output import RenderOutput
from gscompress.slam.params import activate


def activated_tensors(
    gaussians: GaussianMap, device: str | torch.device = "cpu"
) -> dict[str, torch.Tensor]:
    """The renderer's inputs for a map: means, quats, [N, 3] scales, opacities, RGB colours."""
    t = gaussians.to_tensors(device)
    inputs = activate(t["means"], t["log_scales"], t["quats"], t["opacity_logits"], t["sh_dc"])
    return dict(inputs._asdict())


def render_at(
    params: dict[str, torch.Tensor],
    T_world_cam: np.ndarray,
    intrinsics: Intrinsics,
    backend: str = "auto",
    want_contribution: bool = False,
) -> RenderOutput:
    """Render activated Gaussians (`activated_tensors`) from a camera-to-world pose, without
    gradients."""
    device = params["means"].device
    T_cam_world = torch.as_tensor(invert_transform(np.asarray(T_world_cam)), dtype=torch.float32)
    with torch.no_grad():
        return render(
            params["means"],
            params["quats"],
            params["scales"],
            params["opacities"],
            params["colors"],
            intrinsics,
            T_cam_world.to(device),
            backend=backend,
            want_contribution=want_contribution,
        )


def score_map(
    gaussians: GaussianMap,
    T_world_cams: Iterable[np.ndarray],
    intrinsics: Intrinsics,
    *,
    sigma_d: float,
    backend: str = "auto",
    device: str | torch.device = "cpu",
    accumulate: bool = False,
    progress: Callable[[int], object] | None = None,
) -> GaussianMap:
    """Render `gaussians` from every camera pose and return the map with its PWAS sums.

    Args:
        gaussians: the map.
        T_world_cams: camera-to-world 4x4 poses of the views to score from.
        intrinsics: camera intrinsics (and image size) of the views.
        sigma_d: distance scale of the proximity weight, metres (resolved, see
            `gscompress.importance.resolve_sigma_d`; inf: none).
        backend: render backend (see `gscompress.render.render`).
        device: torch device for rendering.
        accumulate: add to the map's existing sums instead of starting from zero.
        progress: called with 1 after each view.

    Returns:
        A copy of the map with importance_sum, importance_weight and alpha_t_sum set.
    """
    params = activated_tensors(gaussians, device)
    n = len(gaussians)
    sums = ImportanceSums.zeros(n, device)
    if accumulate:
        t = gaussians.to_tensors(device, torch.float64)
        sums = ImportanceSums(t["importance_sum"], t["importance_weight"], t["alpha_t_sum"])
    for T_world_cam in T_world_cams:
        out = render_at(params, T_world_cam, intrinsics, backend, want_contribution=True)
        assert out.contribution is not None
        center = torch.as_tensor(np.asarray(T_world_cam)[:3, 3], device=device)
        sums.accumulate(out.contribution, out.visible, params["means"], center, sigma_d)
        if progress is not None:
            progress(1)
    return gaussians.with_importance(
        sums.importance_sum.cpu().numpy(),
        sums.importance_weight.cpu().numpy(),
        sums.alpha_t_sum.cpu().numpy(),
    )
