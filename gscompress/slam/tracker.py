"""Camera tracking: optimise one frame's pose against the fixed map (paper Eq. 4-5).

The pose is parameterised as a small rigid increment on top of the initial guess (usually the
constant-velocity prediction), applied in the camera frame:

    T_cam_world = Delta(q, tau) @ T_cam_world_guess,   Delta = [R(q) | tau],
    R(q) = rotation of the unit quaternion normalise(1, qx, qy, qz),

with (qx, qy, qz) and tau starting at zero. Near zero, 2 (qx, qy, qz) is the rotation vector, so
the Adam learning rates act like SplaTAM's on the world-to-camera quaternion and translation.
They may decay geometrically over the iterations (`TrackingConfig.lr_final_fraction`).
The Gaussians are rendered from detached tensors: only the six pose numbers get gradients.
The pose after the last iteration is returned. (SplaTAM returns the pose of lowest loss seen;
with a mask that changes with the pose, losses of different poses are sums over different
pixels, and on low-resolution maps the lowest one was measured to be a worse pose than the
final iterate.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from gscompress.camera import Intrinsics, invert_transform
from gscompress.render import render
from gscompress.slam.config import TrackingConfig
from gscompress.slam.losses import tracking_loss
from gscompress.slam.params import RenderInputs


@dataclass
class TrackResult:
    """The outcome of tracking one frame.

    Attributes:
        T_world_cam: [4, 4] float64 estimated camera-to-world pose.
        loss: tracking loss of the last iteration (NaN when no iteration ran).
        first_loss: tracking loss at the initial guess.
        iters: iterations run (stops early when no pixel passes the mask).
        pixels: pixels in the tracking mask at the last iteration.
    """

    T_world_cam: np.ndarray
    loss: float
    first_loss: float
    iters: int
    pixels: int


def quaternion_matrix(q_xyz: torch.Tensor) -> torch.Tensor:
    """[3, 3] rotation of the unit quaternion normalise(1, qx, qy, qz) (differentiable)."""
    q = torch.cat([q_xyz.new_ones(1), q_xyz])
    w, x, y, z = q / torch.linalg.vector_norm(q)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ]
    ).reshape(3, 3)  # fmt: skip


def pose_increment(q_xyz: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
    """[4, 4] rigid transform [R(q) | tau] (differentiable)."""
    top = torch.cat([quaternion_matrix(q_xyz), tau[:, None]], dim=1)
    bottom = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=top.dtype, device=top.device)
    return torch.cat([top, bottom], dim=0)


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """The rigid transform nearest to T [4, 4]: its rotation block projected onto SO(3).

    Products of poses gather rounding error, and `invert_transform` (which transposes the
    rotation) turns a rotation that is slightly off SO(3) into an inverse that is off by as
    much again; chained over frames by the constant-velocity model the error would grow
    geometrically. Every pose the tracker makes goes through here.
    """
    U, _, Vt = np.linalg.svd(np.asarray(T, dtype=np.float64)[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    out = np.array(T, dtype=np.float64)
    out[:3, :3] = R
    return out


def constant_velocity(T_prev: np.ndarray, T_prev2: np.ndarray | None) -> np.ndarray:
    """Camera-to-world guess for the next frame: repeat the last relative motion."""
    if T_prev2 is None:
        return orthonormalize(T_prev)
    motion = invert_transform(T_prev2) @ T_prev  # camera t-2 -> camera t-1
    return orthonormalize(np.asarray(T_prev, dtype=np.float64) @ motion)


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
    device = color.device
    T0 = torch.as_tensor(invert_transform(T_world_cam_guess), dtype=torch.float64, device=device)
    q = torch.zeros(3, dtype=torch.float64, device=device, requires_grad=True)
    tau = torch.zeros(3, dtype=torch.float64, device=device, requires_grad=True)
    optimizer = torch.optim.Adam(
        [{"params": [q], "lr": config.lr_rotation}, {"params": [tau], "lr": config.lr_translation}]
    )
    gamma = config.lr_final_fraction ** (1.0 / max(config.iters - 1, 1))
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma)
    first_loss = last_loss = float("nan")
    pixels = done = 0
    for _ in range(config.iters):
        T_cam_world = (pose_increment(q, tau) @ T0).to(fixed.means.dtype)
        out = render(*fixed, intrinsics, T_cam_world, backend=backend)
        terms = tracking_loss(out, color, depth, config)
        if terms.pixels == 0:
            break
        last_loss, pixels = float(terms.total.detach()), terms.pixels
        if done == 0:
            first_loss = last_loss
        optimizer.zero_grad(set_to_none=True)
        terms.total.backward()
        optimizer.step()
        scheduler.step()
        done += 1
    with torch.no_grad():
        T_cam_world = pose_increment(q, tau) @ T0
    return TrackResult(
        T_world_cam=orthonormalize(invert_transform(T_cam_world.cpu().numpy())),
        loss=last_loss,
        first_loss=first_loss,
        iters=done,
        pixels=pixels,
    )
