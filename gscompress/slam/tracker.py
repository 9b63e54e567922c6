"""Camera tracking: optimise one frame's pose against the fixed map (paper Eq. 4-5).

The pose is parameterised as a small rigid increment on top of the initial guess (usually the
constant-velocity prediction), applied in the camera frame:

    T_cam_world = Delta(q, tau) @ T_cam_world_guess,   Delta = [R(q) | tau],
    R(q) = rotation of the unit quaternion normalise(1, qx, qy, qz),

with (qx, qy, qz) and tau starting at zero. Near zero, 2 (qx, qy, qz) is the rotation vector, so
the Adam learning rates act like SplaTAM's on the world-to-camera quaternion and translation.
They may decay geometrically over the iterations (`TrackingConfig.lr_final_fraction`).
The Gaussians are rendered from detached tensors: only the six pose numbers get gradients.
Those six numbers, their gradient (from dL/dT_cam_world by `pose_gradient`) and Adam's
update (`PoseAdam`) live in numpy, not in torch's autograd and optimizer.
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

from gscompress.camera import Intrinsics, invert_transform, quat_to_rotmat
from gscompress.errors import DivergenceError
from gscompress.render import render
from gscompress.slam.config import TrackingConfig
from gscompress.slam.losses import tracking_loss
from gscompress.slam.params import RenderInputs, decay_per_step

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
    """

    T_world_cam: np.ndarray
    loss: float
    first_loss: float
    iters: int
    pixels: int


def pose_increment(x: np.ndarray) -> np.ndarray:
    """[4, 4] rigid transform [R(q) | tau] of the pose vector x = (qx, qy, qz, tau)."""
    out = np.eye(4)
    out[:3, :3] = quat_to_rotmat(np.concatenate([[1.0], x[:3]]))
    out[:3, 3] = x[3:]
    return out


def rotation_jacobian(q_xyz: np.ndarray) -> np.ndarray:
    """dR/dq_xyz [3 (q), 3, 3] of R = the rotation of the unit quaternion normalise(1, q_xyz).

    The tracker's six pose numbers live in numpy with this closed-form Jacobian: as torch
    tensors with autograd, the pose and its gradient took about 90 small operations per tracking
    iteration, 1.6 ms, more than a tenth of the iteration.
    """
    u = np.concatenate([[1.0], q_xyz])
    norm = np.linalg.norm(u)
    w, x, y, z = unit = u / norm
    # dR / d(w, x, y, z) of the unit-quaternion formula (camera.quat_to_rotmat), [4, 3, 3]
    d_wxyz = 2 * np.array(
        [
            [[0, -z, y], [z, 0, -x], [-y, x, 0]],
            [[0, y, z], [y, -2 * x, -w], [z, w, -2 * x]],
            [[-2 * y, x, w], [x, 0, z], [-w, z, -2 * y]],
            [[-2 * z, -w, x], [w, -2 * z, y], [x, y, 0]],
        ]
    )
    d_unit = (np.eye(4) - np.outer(unit, unit)) / norm  # d(u / |u|) / du, [4, 4]
    return np.einsum("kij,kl->lij", d_wxyz, d_unit)[1:]


def pose_gradient(x: np.ndarray, T0: np.ndarray, g_T: np.ndarray) -> np.ndarray:
    """dL/dx [6] from dL/dT [4, 4], where T = pose_increment(x) @ T0."""
    g_delta = g_T @ T0.T
    g_q = np.einsum("kij,ij->k", rotation_jacobian(x[:3]), g_delta[:3, :3])
    return np.concatenate([g_q, g_delta[:3, 3]])


class PoseAdam:
    """torch.optim.Adam's update (default betas and eps) on one vector, in numpy, with the
    learning rates decaying by `gamma` per step (torch's ExponentialLR)."""

    betas = (0.9, 0.999)
    eps = 1e-8

    def __init__(self, lr: np.ndarray, gamma: float) -> None:
        self.lr = np.asarray(lr, dtype=np.float64)
        self.gamma = gamma
        self.m = np.zeros_like(self.lr)
        self.v = np.zeros_like(self.lr)
        self.t = 0

    def step(self, x: np.ndarray, grad: np.ndarray) -> np.ndarray:
        """x after one step along `grad`."""
        b1, b2 = self.betas
        self.t += 1
        self.m = b1 * self.m + (1 - b1) * grad
        self.v = b2 * self.v + (1 - b2) * grad * grad
        denom = np.sqrt(self.v) / np.sqrt(1 - b2**self.t) + self.eps
        out = x - (self.lr / (1 - b1**self.t)) * self.m / denom
        self.lr = self.lr * self.gamma
        return out


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
    T0 = invert_transform(T_world_cam_guess)
    x = np.zeros(6)  # (qx, qy, qz, tau)
    gamma = decay_per_step(config.lr_final_fraction, config.iters)
    adam = PoseAdam(np.repeat([config.lr_rotation, config.lr_translation], 3), gamma)
    first_loss = last_loss = float("nan")
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
    )
