"""Pinhole intrinsics, rigid transforms and quaternion helpers (numpy).

Conventions: `T_world_cam` maps camera points to world points (camera-to-world) as a 4x4 matrix;
`T_cam_world` is its inverse. Quaternions are (w, x, y, z) everywhere except at the TUM text
boundary, which stores (x, y, z, w).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gscompress.errors import InputError


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole camera intrinsics in pixels for an image of `width` x `height`."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        """The 3x3 calibration matrix (float64)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def backproject(
        self, u: np.ndarray, v: np.ndarray, z: np.ndarray, T_world_cam: np.ndarray
    ) -> np.ndarray:
        """[M, 3] world points (float64) of pixels (u, v) [M] at depths z [M] (metres along the
        optical axis), seen by the camera at camera-to-world pose T_world_cam."""
        z = np.asarray(z, dtype=np.float64)
        cam = np.stack([(u - self.cx) / self.fx * z, (v - self.cy) / self.fy * z, z], axis=1)
        return transform_points(np.asarray(T_world_cam, dtype=np.float64), cam)

    def scaled(self, width: int, height: int) -> Intrinsics:
        """Intrinsics for the same camera with the image resized to `width` x `height`.

        Uses the pixel-area convention: pixel centres sit at integer + 0.5, so a principal point
        `c` maps to `(c + 0.5) * s - 0.5`.
        """
        if width <= 0 or height <= 0:
            raise InputError(f"image size must be positive, got {width}x{height}")
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
            width=width,
            height=height,
        )


MIN_QUATERNION_NORM = 1e-6
"""A written quaternion shorter than this is taken for zero, not a rotation: poses and transforms
store unit quaternions, so one this short is a corrupt or mistyped row, whatever its direction."""


def is_zero_quaternion(q: Sequence[float] | np.ndarray) -> bool:
    """Whether finite quaternion components (any order) are too short to be a rotation."""
    return bool(np.hypot.reduce(np.asarray(q, dtype=np.float64)) < MIN_QUATERNION_NORM)


def quat_to_rotmat(q_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrices from (possibly unnormalised) quaternions.

    Args:
        q_wxyz: [..., 4] quaternions (w, x, y, z).

    Returns:
        [..., 3, 3] rotation matrices (float64).
    """
    q = np.asarray(q_wxyz, dtype=np.float64)
    q = q / np.abs(q).max(axis=-1, keepdims=True)  # (so that the norm cannot overflow)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    R = np.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return R.reshape((*q.shape[:-1], 3, 3))


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) with w >= 0 from rotation matrices [..., 3, 3]."""
    R = np.asarray(R, dtype=np.float64)
    m = R.reshape(-1, 3, 3)
    tr = np.trace(m, axis1=1, axis2=2)
    # Shepperd's method: pick the numerically largest of 4w^2, 4x^2, 4y^2, 4z^2.
    diag = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    k = np.argmax(diag, axis=1)
    q = np.empty((m.shape[0], 4))
    for case in range(4):
        s = k == case
        if not np.any(s):
            continue
        r = m[s]
        if case == 0:
            t = np.sqrt(1.0 + tr[s]) * 2
            q[s] = np.stack(
                [
                    0.25 * t,
                    (r[:, 2, 1] - r[:, 1, 2]) / t,
                    (r[:, 0, 2] - r[:, 2, 0]) / t,
                    (r[:, 1, 0] - r[:, 0, 1]) / t,
                ],
                axis=1,
            )
        else:
            i = case - 1
            j, m2 = (i + 1) % 3, (i + 2) % 3
            t = np.sqrt(1.0 + r[:, i, i] - r[:, j, j] - r[:, m2, m2]) * 2
            qi = np.empty((r.shape[0], 4))
            qi[:, 0] = (r[:, m2, j] - r[:, j, m2]) / t
            qi[:, 1 + i] = 0.25 * t
            qi[:, 1 + j] = (r[:, j, i] + r[:, i, j]) / t
            qi[:, 1 + m2] = (r[:, m2, i] + r[:, i, m2]) / t
            q[s] = qi
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape((*R.shape[:-2], 4))


def interpolate_pose(T_a: np.ndarray, T_b: np.ndarray, t: float) -> np.ndarray:
    """The 4x4 pose a fraction `t` in [0, 1] of the way from `T_a` to `T_b`: rotation by
    spherical linear interpolation of the quaternions (the shorter arc), translation linearly."""
    q_a, q_b = rotmat_to_quat(np.stack([T_a[:3, :3], T_b[:3, :3]]))
    if np.dot(q_a, q_b) < 0:
        q_b = -q_b
    angle = np.arccos(np.clip(np.dot(q_a, q_b), -1.0, 1.0))
    if angle < 1e-9:
        q = q_a
    else:
        q = (np.sin((1 - t) * angle) * q_a + np.sin(t * angle) * q_b) / np.sin(angle)
    translation = (1 - t) * np.asarray(T_a)[:3, 3] + t * np.asarray(T_b)[:3, 3]
    return make_transform(quat_to_rotmat(q), translation)


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 rigid transform(s) from rotation [..., 3, 3] and translation [..., 3]."""
    R = np.asarray(R, dtype=np.float64)
    T = np.zeros((*R.shape[:-2], 4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """`points` [N, 3] moved by the rigid [4, 4] `T`."""
    return points @ T[:3, :3].T + T[:3, 3]


def rotation_angle_deg(R: np.ndarray) -> float:
    """The angle in degrees of the rotation [3, 3] `R` (about its axis)."""
    cos = (np.trace(np.asarray(R, np.float64)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transform(s) [..., 4, 4] without a general matrix inverse."""
    T = np.asarray(T, dtype=np.float64)
    R_inv = np.swapaxes(T[..., :3, :3], -1, -2)
    return make_transform(R_inv, -(R_inv @ T[..., :3, 3:4])[..., 0])


def pose_from_tum(txyz_qxyzw: np.ndarray) -> np.ndarray:
    """4x4 transforms from TUM rows `tx ty tz qx qy qz qw` ([..., 7])."""
    v = np.asarray(txyz_qxyzw, dtype=np.float64)
    q_wxyz = np.concatenate([v[..., 6:7], v[..., 3:6]], axis=-1)
    return make_transform(quat_to_rotmat(q_wxyz), v[..., :3])


def pose_to_tum(T: np.ndarray) -> np.ndarray:
    """TUM rows `tx ty tz qx qy qz qw` ([..., 7]) from 4x4 transforms."""
    T = np.asarray(T, dtype=np.float64)
    q = rotmat_to_quat(T[..., :3, :3])
    return np.concatenate([T[..., :3, 3], q[..., 1:4], q[..., 0:1]], axis=-1)
