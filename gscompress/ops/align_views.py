"""Refining a map-to-map transform on the target agent's own frames.

Registration of the two maps' Gaussians (`gscompress.ops.align`) can leave a flat scene turned
by degrees: a table top slides and turns in itself, and two agents' maps of it differ by their
own drift. The receiver has its frames, which say directly where the sender's map must sit to
draw them: the source map, moved by the transform, is rendered at some of the target's
keyframes (at the target's estimated poses) and compared with those frames by the tracking
loss (paper Eq. 4, the silhouette mask keeping only the pixels the source draws, so only
where the maps overlap counts). The transform is refined as one rigid increment about the
centre c of the source's Gaussians:

    T' = K(c) Delta(x) K(c)^-1 T,    T_cam_source_i = P_i^-1 T',

with Delta(x) the tracker's increment (`slam.poses.pose_increment`, x = (qx, qy, qz, tau)),
K(c) the translation by c (so that turning does not swing the map about the target's origin)
and P_i view i's camera-to-world pose in the target's frame. The loss is summed over the views
and x follows Adam's steps (`slam.poses.PoseAdam`) with the gradient

    dL/dDelta = sum_i (P_i^-1 K)^T (dL/dT_cam_i) (K^-1 T)^T.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from gscompress.camera import Intrinsics, invert_transform
from gscompress.gaussians import GaussianMap
from gscompress.ops.align import transform_error
from gscompress.ops.score import activated_tensors
from gscompress.render import render
from gscompress.slam.config import TrackingConfig
from gscompress.slam.keyframes import frame_tensors
from gscompress.slam.losses import LossTerms, tracking_loss
from gscompress.slam.params import RenderInputs, decay_per_step
from gscompress.slam.poses import PoseAdam, orthonormalize, pose_gradient, pose_increment

VIEW_ALIGN = TrackingConfig(
    iters=300, lr_rotation=2e-3, lr_translation=4e-3, lr_final_fraction=0.05, silhouette_min=0.9
)
"""The refinement's settings: 300 steps whose learning rates decay to a twentieth, so that the
first ones can cross degrees and centimetres and the last ones settle (on tabletop's agents a
registration far off came to the same transform as one started from the truth, where fewer
steps at lower rates stopped short: docs/align.md, "Refined on the target's frames"); pixels
where the source's silhouette passes 0.9 (its edges, half drawn, left out)."""


@dataclass(frozen=True)
class ViewAlignment:
    """A transform refined on the target's views.

    Attributes:
        T_target_source: [4, 4] the refined transform.
        loss_before, loss_after: the summed tracking loss at the first and last step.
        pixels: pixels in the masks at the last step, over all views.
        views: views that drew any of the source.
    """

    T_target_source: np.ndarray
    loss_before: float
    loss_after: float
    pixels: int
    views: int

    def record(self, T_before: np.ndarray) -> dict[str, Any]:
        """What to report: the change from `T_before` (cm, degrees), the losses and counts."""
        shift, turn = transform_error(self.T_target_source, T_before)
        return {
            "change_cm": 100 * shift,
            "change_deg": turn,
            "loss_before": self.loss_before,
            "loss_after": self.loss_after,
            "pixels": self.pixels,
            "views": self.views,
        }


def _terms(
    fixed: RenderInputs,
    T_cam: np.ndarray,
    observed: tuple[torch.Tensor, torch.Tensor],
    intrinsics: Intrinsics,
    config: TrackingConfig,
    backend: str,
    grad: bool,
) -> tuple[LossTerms, np.ndarray | None]:
    """One view's tracking loss with the source at camera `T_cam` (world-to-camera), and with
    `grad` its gradient dL/dT_cam (None when the view draws none of the source)."""
    pose = torch.tensor(
        T_cam, dtype=fixed.means.dtype, device=observed[0].device, requires_grad=grad
    )
    terms = tracking_loss(render(*fixed, intrinsics, pose, backend=backend), *observed, config)
    if not grad or terms.pixels == 0:
        return terms, None
    terms.total.backward()
    assert pose.grad is not None
    return terms, pose.grad.cpu().double().numpy()


def view_loss(
    gaussians: GaussianMap,
    T_target_source: np.ndarray,
    frames: list[Any],
    poses: list[np.ndarray],
    intrinsics: Intrinsics,
    config: TrackingConfig = VIEW_ALIGN,
    *,
    backend: str = "auto",
    device: str | torch.device = "cpu",
) -> float | None:
    """The mean tracking loss over the views that draw any of `gaussians` once moved by
    `T_target_source` (None when none does): how well a map draws the target's frames where
    it covers them (the target's own map at the identity gives the scale to judge by)."""
    fixed = RenderInputs(**activated_tensors(gaussians, device))  # (no gradients)
    T = np.asarray(T_target_source, dtype=np.float64)
    losses = []
    for frame, P in zip(frames, poses, strict=True):
        T_cam = invert_transform(np.asarray(P, np.float64)) @ T
        view = frame_tensors(frame, device)
        terms, _ = _terms(fixed, T_cam, view, intrinsics, config, backend, grad=False)
        if terms.pixels:
            losses.append(float(terms.total))
    return float(np.mean(losses)) if losses else None


def refine_on_views(
    source: GaussianMap,
    T_target_source: np.ndarray,
    frames: list[Any],
    poses: list[np.ndarray],
    intrinsics: Intrinsics,
    config: TrackingConfig = VIEW_ALIGN,
    *,
    backend: str = "auto",
    device: str | torch.device = "cpu",
    progress: Callable[[int], object] | None = None,
) -> ViewAlignment:
    """Refine the transform from `source`'s world to the target's on the target's frames.

    Args:
        source: the source's map, in its own world frame.
        T_target_source: [4, 4] the starting transform (e.g. `gsc align`'s registration).
        frames: the target's frames (`color` [H, W, 3], `depth` [H, W], 0 = invalid).
        poses: each frame's camera-to-world pose in the target's world frame.
        intrinsics: the frames' camera.
        config: iterations, learning rates, decay and the loss's settings.
        backend, device: how to render.
        progress: called with 1 after each iteration.

    Returns:
        The refined transform (the starting one when no view draws the source).
    """
    fixed = RenderInputs(**activated_tensors(source, device))  # (no gradients)
    observed = [frame_tensors(f, device) for f in frames]
    T = np.asarray(T_target_source, dtype=np.float64)
    centre = np.eye(4)
    centre[:3, 3] = T[:3, :3] @ source.means.astype(np.float64).mean(axis=0) + T[:3, 3]
    after = invert_transform(centre) @ T  # K^-1 T
    befores = [invert_transform(np.asarray(P, np.float64)) @ centre for P in poses]  # P^-1 K
    x = np.zeros(6)
    adam = PoseAdam(
        np.repeat([config.lr_rotation, config.lr_translation], 3),
        decay_per_step(config.lr_final_fraction, config.iters),
    )
    first = last = math.nan
    pixels = seen = 0
    for step in range(config.iters):
        delta = pose_increment(x)
        g_delta = np.zeros((4, 4))
        total, pixels, seen = 0.0, 0, 0
        for before, view in zip(befores, observed, strict=True):
            terms, g_cam = _terms(
                fixed, before @ delta @ after, view, intrinsics, config, backend, grad=True
            )
            if g_cam is None:
                continue
            g_delta += before.T @ g_cam @ after.T
            total += float(terms.total.detach())
            pixels += terms.pixels
            seen += 1
        if seen == 0:
            break
        first = total if step == 0 else first
        last = total
        x = adam.step(x, pose_gradient(x, np.eye(4), g_delta))
        if progress is not None:
            progress(1)
    refined = T if seen == 0 else orthonormalize(centre @ pose_increment(x) @ after)
    return ViewAlignment(refined, first, last, pixels, seen)
