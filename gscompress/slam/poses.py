"""Camera poses as six numbers optimised in numpy: the tracker's and the mapping's.

A pose is a small rigid increment on a starting pose, applied in the camera frame:

    T_cam_world = Delta(x) @ T_cam_world_start,   Delta(x) = [R(q) | tau],  x = (q, tau),
    R(q) = rotation of the unit quaternion normalise(1, qx, qy, qz),

with x starting at zero. Near zero, 2 q is the rotation vector, so Adam's learning rates act
like SplaTAM's on the world-to-camera quaternion and translation. The gradient of x comes from
dL/dT_cam_world (the renderer's, `pose_gradient`) and Adam's update runs in numpy (`PoseAdam`):
as torch tensors with autograd, the pose and its gradient took many small operations per
iteration (docs/design-experiments.md, "The tracker's pose update").

The tracker optimises one frame's pose with the map fixed (`gscompress.slam.tracker`); the
mapping optimises keyframe poses together with the map (`PoseVariable`, one per refined view;
`gscompress.slam.mapper`); `gscompress.ops.align_views` refines a transform on frames the same
way.
"""

from __future__ import annotations

import numpy as np

from gscompress.camera import invert_transform, quat_to_rotmat


def pose_increment(x: np.ndarray) -> np.ndarray:
    """[4, 4] rigid transform [R(q) | tau] of the pose vector x = (qx, qy, qz, tau)."""
    out = np.eye(4)
    out[:3, :3] = quat_to_rotmat(np.concatenate([[1.0], x[:3]]))
    out[:3, 3] = x[3:]
    return out


def rotation_jacobian(q_xyz: np.ndarray) -> np.ndarray:
    """dR/dq_xyz [3 (q), 3, 3] of R = the rotation of the unit quaternion normalise(1, q_xyz).

    The tracker's six pose numbers live in numpy with this closed-form Jacobian: as torch
    tensors with autograd, the pose and its gradient took many small operations per tracking
    iteration, a sizeable share of its time (measured in docs/design-experiments.md, "The
    tracker's pose update").
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

    def step(self, x: np.ndarray, grad: np.ndarray, rate: float = 1.0) -> np.ndarray:
        """x after one step along `grad`, the learning rates times `rate` for this step."""
        b1, b2 = self.betas
        self.t += 1
        self.m = b1 * self.m + (1 - b1) * grad
        self.v = b2 * self.v + (1 - b2) * grad * grad
        denom = np.sqrt(self.v) / np.sqrt(1 - b2**self.t) + self.eps
        out = x - (rate * self.lr / (1 - b1**self.t)) * self.m / denom
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


class PoseVariable:
    """A view's camera pose refined by the mapping, with its own Adam state.

    Args:
        T_world_cam: [4, 4] the pose to start from (camera-to-world).
        lr: [6] Adam learning rates of (q, tau) (`PoseConfig`).
    """

    def __init__(self, T_world_cam: np.ndarray, lr: np.ndarray) -> None:
        self.start = invert_transform(np.asarray(T_world_cam, dtype=np.float64))  # T_cam_world
        self.x = np.zeros(6)
        self.adam = PoseAdam(lr, 1.0)

    @property
    def T_world_cam(self) -> np.ndarray:
        """[4, 4] the refined camera-to-world pose."""
        return orthonormalize(invert_transform(pose_increment(self.x) @ self.start))

    def step(self, g_T_cam_world: np.ndarray, rate: float = 1.0) -> np.ndarray:
        """Step along dL/dT_cam_world [4, 4] (learning rates times `rate`); the new
        camera-to-world pose."""
        self.x = self.adam.step(self.x, pose_gradient(self.x, self.start, g_T_cam_world), rate)
        return self.T_world_cam


class PoseStore:
    """[4, 4] float64 arrays for poses a run keeps to its end (one per frame), taken from blocks
    of `block` made at once.

    A pose array made when its frame is done is a small block of the heap (its values and its
    shape) that lives to the end of the run, placed wherever the allocator had a small free
    chunk: in the middle of the space the frame's large working tensors had just freed, which
    it then splits for good. Over a long run those splits left the heap in more and smaller
    holes than the frames' working tensors fit, and each frame's peak grew with the frames
    (docs/recordings.md, "Streaming and memory"). Arrays made a block at a time sit together.
    """

    def __init__(self, block: int = 256) -> None:
        self.block = block
        self._free: list[np.ndarray] = []

    def keep(self, T: np.ndarray) -> np.ndarray:
        """A kept array holding the values of `T` (its float64 copy)."""
        if not self._free:
            self._free = list(np.empty((self.block, 4, 4)))[::-1]
        out = self._free.pop()
        out[...] = T
        return out
