"""Camera tracking: optimise one frame's pose against the fixed map (paper Eq. 4-5).

The pose is an increment on the initial guess (usually the constant-velocity prediction), as
`gscompress.slam.poses` describes; the learning rates may decay geometrically over the
iterations (`TrackingConfig.lr_final_fraction`). The Gaussians are rendered from detached
tensors: only the six pose numbers get gradients.
The pose after the last iteration is returned. (SplaTAM returns the pose of lowest loss seen;
with a mask that changes with the pose, losses of different poses are sums over different
pixels, and on low-resolution maps the lowest one was measured to be a worse pose than the
final iterate.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.linalg import expm, logm

from gscompress.camera import Intrinsics, invert_transform
from gscompress.errors import DivergenceError
from gscompress.render import render
from gscompress.slam.config import TrackingConfig
from gscompress.slam.losses import tracking_loss
from gscompress.slam.params import RenderInputs, decay_per_step
from gscompress.slam.poses import PoseAdam, orthonormalize, pose_gradient, pose_increment

TOO_HIGH = "lower its learning rates, tracking.lr_rotation and lr_translation"


@dataclass
class TrackResult:
    """The outcome of tracking one frame.

    Attributes:
        T_world_cam: [4, 4] float64 estimated camera-to-world pose.
        loss: tracking loss of the last iteration (NaN when no iteration ran).
        first_loss: tracking loss at the initial guess.
        iters: iterations run (stops early when no pixel passes the mask).
        pixels: pixels in the tracking mask at the last iteration.
        color: mean absolute colour error over the mask at the last iteration.
        depth: mean absolute depth error (metres) over the mask at the last iteration.
        relocalised: the frame's track was lost and this is its re-localisation
            (`gscompress.slam.lost`).
    """

    T_world_cam: np.ndarray
    loss: float
    first_loss: float
    iters: int
    pixels: int
    color: float = float("nan")
    depth: float = float("nan")
    relocalised: bool = False


def constant_velocity(T_prev: np.ndarray, T_prev2: np.ndarray | None) -> np.ndarray:
    """Camera-to-world guess for the next frame: repeat the last relative motion."""
    if T_prev2 is None:
        return orthonormalize(T_prev)
    motion = invert_transform(T_prev2) @ T_prev  # camera t-2 -> camera t-1
    return orthonormalize(np.asarray(T_prev, dtype=np.float64) @ motion)


DROPPED = 1.5
"""Frame intervals that differ by more than this factor (a frame dropped, or the frame after a
gap) scale the constant-velocity guess by their ratio; closer ones (stamp jitter) do not."""


def velocity_guess(
    T_prev: np.ndarray, T_prev2: np.ndarray, dt_prev: float, dt: float
) -> np.ndarray:
    """Camera-to-world guess for a frame `dt` seconds after T_prev, whose predecessor T_prev2 came
    `dt_prev` seconds before it: the last relative motion repeated, scaled by dt / dt_prev on
    SE(3) when the two intervals differ by more than `DROPPED` times."""
    steps = dt / dt_prev if dt_prev > 0 and dt > 0 else 1.0
    if 1 / DROPPED <= steps <= DROPPED:
        return constant_velocity(T_prev, T_prev2)
    motion = invert_transform(T_prev2) @ T_prev
    scaled = np.real(expm(steps * logm(motion)))
    return orthonormalize(np.asarray(T_prev, dtype=np.float64) @ scaled)


def track(
    gaussians: RenderInputs,
    color: torch.Tensor,
    depth: torch.Tensor,
    intrinsics: Intrinsics,
    T_world_cam_guess: np.ndarray,
    config: TrackingConfig,
    *,
    backend: str = "auto",
) -> TrackResult:
    """Estimate a frame's camera-to-world pose with the map held fixed.

    Args:
        gaussians: the map's render inputs (they are detached here).
        color: [H, W, 3] observed colour.
        depth: [H, W] observed depth, 0 = invalid.
        intrinsics: camera intrinsics at the image size.
        T_world_cam_guess: [4, 4] initial pose.
        config: iterations, learning rates and loss settings.
        backend: render backend.

    Returns:
        The pose after the last iteration, and the losses.
    """
    fixed = RenderInputs(*(t.detach() for t in gaussians))
    T0 = invert_transform(T_world_cam_guess)
    x = np.zeros(6)  # (qx, qy, qz, tau)
    gamma = decay_per_step(config.lr_final_fraction, config.iters)
    adam = PoseAdam(np.repeat([config.lr_rotation, config.lr_translation], 3), gamma)
    first_loss = last_loss = color_error = depth_error = float("nan")
    pixels = done = 0
    for _ in range(config.iters):
        T_cam_world = torch.tensor(
            pose_increment(x) @ T0, dtype=fixed.means.dtype, device=color.device, requires_grad=True
        )
        out = render(*fixed, intrinsics, T_cam_world, backend=backend)
        terms = tracking_loss(out, color, depth, config)
        if terms.pixels == 0:
            break
        last_loss, pixels = float(terms.total.detach()), terms.pixels
        color_error, depth_error = terms.color, terms.depth
        if not math.isfinite(last_loss):
            raise DivergenceError("tracking", f"its loss became {last_loss}", TOO_HIGH)
        if done == 0:
            first_loss = last_loss
        terms.total.backward()
        # (the renderers give a zero gradient, not None, when no Gaussian is in view)
        grad = T_cam_world.grad
        g_T = np.zeros((4, 4)) if grad is None else grad.cpu().double().numpy()
        x = adam.step(x, pose_gradient(x, T0, g_T))
        done += 1
    if not np.isfinite(x).all():
        raise DivergenceError("tracking", "the pose is not finite", TOO_HIGH)
    T_cam_world = pose_increment(x) @ T0
    return TrackResult(
        T_world_cam=orthonormalize(invert_transform(T_cam_world)),
        loss=last_loss,
        first_loss=first_loss,
        iters=done,
        pixels=pixels,
        color=color_error,
        depth=depth_error,
    )
