"""A procedurally textured indoor RGB-D sequence with exact depth and ground-truth poses.

The scene is a 6 m x 5 m x 2.7 m room (world z up, floor at z = 0) with textured walls, floor and
ceiling and seven boxes (two rotated about z, one stacked on another). Every surface carries a
texture (planks, bricks, checkers, stripes, marble-like noise, gradients) plus fine noise, so
there are image gradients everywhere for photometric tracking. Each pixel's centre ray is
intersected analytically with the room and the boxes in vectorised numpy (float64), so depth is
exact: the z-distance along the optical axis to the first surface. Colour is one sample at the
pixel centre by default (`supersample=2` averages 2x2 sub-pixel samples, for anti-aliased
full-resolution images at twice the cost), shaded by one fixed directional light
(view-independent, so colour is consistent between frames).

The camera follows a smooth closed path around the room centre (one loop every 20 s at 30 fps),
looking across the room at a moving target, with a small roll oscillation; 60 frames cover about
a tenth of the loop (~1 m and ~40 degrees of yaw).

`synthetic_sequence(...)` returns the sequence in memory (frames rendered on demand);
`write_synthetic_sequence(...)` writes it in TUM layout (what `gsc synth` does). A seed fixes the
colours, noise and box placement; the output bytes are identical for identical arguments.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gscompress.camera import Intrinsics, make_transform
from gscompress.datasets.base import Frame, check_size
from gscompress.datasets.tum import TUM_ENTRIES, read_file_list, write_tum_sequence
from gscompress.errors import DatasetError, InputError, OptionError, OutputError
from gscompress.io.files import check_only_entries, some_names
from gscompress.seeds import check_seed
from gscompress.threads import cpu_threads

FPS = 30.0
LOOP_SECONDS = 20.0
ROOM_MIN = np.array([-3.0, -2.5, 0.0])
ROOM_MAX = np.array([3.0, 2.5, 2.7])
_LIGHT = np.array([0.45, 0.3, 0.84]) / np.linalg.norm([0.45, 0.3, 0.84])
_NOISE_SIZE = 256
SURFACE_NONE = -1
# Surface ids 0..5 are the room: floor, ceiling, wall x-, wall x+, wall y-, wall y+;
# box k has ids 6 + 6k .. 6 + 6k + 5 (faces -x, +x, -y, +y, -z, +z in the box frame).
FLOOR, CEILING = 0, 1


@dataclass(frozen=True)
class Material:
    """A procedural texture: `kind` in {planks, bricks, checker, stripes, marble, gradient}."""

    kind: str
    colors: np.ndarray  # [3, 3] rgb in [0, 1]
    period: float  # metres
    angle: float  # radians, stripe direction
    offset: np.ndarray  # [2] noise-space offset, so surfaces sharing a kind differ


@dataclass(frozen=True)
class Box:
    """A box standing in the room, rotated by `yaw` about the world z axis."""

    center: np.ndarray  # [3]
    half: np.ndarray  # [3] half extents in its own frame
    yaw: float
    material: Material


@dataclass(frozen=True)
class Scene:
    """The room, its boxes and the noise lattice used by the textures."""

    room_materials: tuple[Material, ...]  # 6: floor, ceiling, x-, x+, y-, y+
    boxes: tuple[Box, ...]
    noise: np.ndarray  # [_NOISE_SIZE + 1, _NOISE_SIZE + 1] float32 in [0, 1], wrapped


def make_scene(seed: int = 0) -> Scene:
    """The room for `seed`: the layout is fixed, colours, noise and box jitter vary."""
    rng = np.random.default_rng(seed)

    def palette(base: tuple[float, float, float], spread: float = 0.18) -> np.ndarray:
        b = np.asarray(base)
        cols = [b + rng.uniform(-0.08, 0.08, 3)]
        cols.append(b * rng.uniform(0.55, 0.7) + rng.uniform(-spread, spread, 3) * 0.5)
        cols.append(rng.uniform(0.15, 0.95, 3))
        return np.clip(np.array(cols), 0.04, 0.96)

    def material(kind: str, base: tuple[float, float, float], period: float) -> Material:
        return Material(
            kind=kind,
            colors=palette(base),
            period=period * rng.uniform(0.85, 1.15),
            angle=float(rng.uniform(0.0, np.pi)),
            offset=rng.uniform(0.0, _NOISE_SIZE, 2),
        )

    room = (
        material("planks", (0.62, 0.44, 0.26), 0.18),  # floor
        material("gradient", (0.85, 0.85, 0.80), 0.6),  # ceiling
        material("bricks", (0.70, 0.35, 0.25), 0.25),  # wall x-
        material("stripes", (0.35, 0.55, 0.70), 0.22),  # wall x+
        material("marble", (0.75, 0.72, 0.55), 0.5),  # wall y-
        material("checker", (0.45, 0.62, 0.40), 0.4),  # wall y+
    )
    layout = [
        # center (x, y), half extents, yaw (rad), material kind, base colour, period
        ((0.0, 0.0), (0.35, 0.3, 0.4), 0.35, "checker", (0.85, 0.75, 0.2), 0.12),
        ((-2.35, 1.75), (0.45, 0.5, 0.55), 0.0, "stripes", (0.8, 0.3, 0.3), 0.08),
        ((2.4, -1.8), (0.45, 0.45, 0.35), 0.0, "marble", (0.3, 0.4, 0.8), 0.3),
        ((-2.3, -1.7), (0.5, 0.55, 0.3), -0.4, "gradient", (0.4, 0.8, 0.5), 0.5),
        ((2.5, 1.2), (0.3, 0.9, 1.0), 0.0, "bricks", (0.6, 0.6, 0.65), 0.15),
        ((0.6, 2.15), (0.6, 0.25, 0.45), 0.0, "checker", (0.7, 0.4, 0.75), 0.1),
    ]
    boxes: list[Box] = []
    for (cx, cy), half, yaw, kind, base, period in layout:
        jitter = rng.uniform(-0.08, 0.08, 2)
        h = np.asarray(half, dtype=np.float64)
        center = np.array([cx + jitter[0], cy + jitter[1], h[2]])
        boxes.append(
            Box(center, h, yaw + float(rng.uniform(-0.1, 0.1)), material(kind, base, period))
        )
    # A small box stacked on the one in the corner at x-, y+.
    under = boxes[1]
    top_half = np.array([0.2, 0.22, 0.18])
    boxes.append(
        Box(
            np.array(
                [under.center[0] + 0.1, under.center[1] - 0.1, 2 * under.half[2] + top_half[2]]
            ),
            top_half,
            0.6,
            material("stripes", (0.2, 0.6, 0.65), 0.05),
        )
    )
    noise = rng.random((_NOISE_SIZE, _NOISE_SIZE), dtype=np.float32)
    noise = np.pad(noise, ((0, 1), (0, 1)), mode="wrap")
    return Scene(room, tuple(boxes), noise)


# ---------------------------------------------------------------------------------------------
# Camera path


def camera_pose(t: float) -> np.ndarray:
    """[4, 4] camera-to-world pose (OpenCV camera: x right, y down, z forward) at time t (s)."""
    th = 2.0 * np.pi * t / LOOP_SECONDS
    position = np.array([1.55 * np.cos(th), 1.15 * np.sin(th), 1.35 + 0.15 * np.sin(3.0 * th)])
    # look across the room, swinging +-0.6 rad either side of the room centre
    look = th + 0.6 * np.sin(3.0 * th)
    target = np.array([-1.3 * np.cos(look), -1.1 * np.sin(look), 0.7 + 0.2 * np.cos(2.0 * th)])
    forward = target - position
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    roll = np.deg2rad(6.0) * np.sin(5.0 * th)
    c, s = np.cos(roll), np.sin(roll)
    R = np.stack([c * right + s * down, -s * right + c * down, forward], axis=1)
    return make_transform(R, position)


def default_intrinsics(width: int, height: int) -> Intrinsics:
    """Square pixels, about 64 degrees horizontal field of view, centred principal point."""
    f = 0.8 * width
    return Intrinsics(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)


# ---------------------------------------------------------------------------------------------
# Ray casting


def _rays(K: Intrinsics, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray origin [3] and world directions [H*W, 3] (pixel centres, unit camera-z component)."""
    u, v = np.meshgrid(np.arange(K.width, dtype=np.float64), np.arange(K.height, dtype=np.float64))
    d_cam = np.stack(
        [(u.ravel() - K.cx) / K.fx, (v.ravel() - K.cy) / K.fy, np.ones(u.size)], axis=1
    )
    return T_world_cam[:3, 3].copy(), d_cam @ T_world_cam[:3, :3].T


def _yaw_matrix(yaw: float) -> np.ndarray:
    """Rotation about world z by `yaw`."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def cast(
    scene: Scene,
    origin: np.ndarray,
    dirs: np.ndarray,
    candidates: list[np.ndarray | None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameter t [N] and surface id [N] of the first hit for rays o + t d.

    With directions whose camera-z component is 1, t is the depth along the optical axis.
    `candidates[k]`, when given and not None, lists the only rays that may hit box k.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
        # Inside the room: the exit distance is the nearest wall along each axis.
        t_axes = np.where(dirs > 0, (ROOM_MAX - origin) * inv, (ROOM_MIN - origin) * inv)
        t_axes = np.where(dirs == 0, np.inf, t_axes)
        axis = np.argmin(t_axes, axis=1)
        t = t_axes[np.arange(len(dirs)), axis]
        positive = dirs[np.arange(len(dirs)), axis] > 0
        # axis 2 (z): going down hits the floor (0), up the ceiling (1); x: 2/3, y: 4/5
        surface = np.where(
            axis == 2, np.where(positive, CEILING, FLOOR), 2 + 2 * axis + positive.astype(np.int64)
        )
        for k, box in enumerate(scene.boxes):
            idx = None if candidates is None else candidates[k]
            if idx is not None and len(idx) == 0:
                continue
            R = _yaw_matrix(box.yaw)
            o = (origin - box.center) @ R
            d = (dirs if idx is None else dirs[idx]) @ R
            rows = np.arange(len(d))
            inv_d = 1.0 / d
            t0 = (-box.half - o) * inv_d
            t1 = (box.half - o) * inv_d
            inside = np.abs(o) <= box.half
            t_near = np.where(d == 0, np.where(inside, -np.inf, np.inf), np.minimum(t0, t1))
            t_far = np.where(d == 0, np.where(inside, np.inf, -np.inf), np.maximum(t0, t1))
            face_axis = np.argmax(t_near, axis=1)
            t_in = t_near[rows, face_axis]
            t_out = np.min(t_far, axis=1)
            t_cur = t if idx is None else t[idx]
            hit = (t_in <= t_out) & (t_in > 1e-9) & (t_in < t_cur)
            # the entry face is the one facing the ray: the -axis side when d > 0
            face = 2 * face_axis + (d[rows, face_axis] < 0)
            if idx is None:
                t = np.where(hit, t_in, t)
                surface = np.where(hit, 6 + 6 * k + face, surface)
            else:
                t[idx[hit]] = t_in[hit]
                surface[idx[hit]] = 6 + 6 * k + face[hit]
    return t, surface


# ---------------------------------------------------------------------------------------------
# Textures


def _value_noise(noise: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Smooth value noise in [0, 1] at lattice coordinates (x, y), periodic over the lattice.

    `noise` is the [n + 1, n + 1] lattice with its first row and column repeated at the end
    (n a power of two), so the four corners of a cell are plain offsets into the flat array.
    """
    n = noise.shape[0] - 1
    stride = n + 1
    xf, yf = np.floor(x), np.floor(y)
    fx, fy = x - xf, y - yf
    fx = fx * fx * (3 - 2 * fx)
    fy = fy * fy * (3 - 2 * fy)
    i00 = (yf.astype(np.int64) & (n - 1)) * stride + (xf.astype(np.int64) & (n - 1))
    flat = noise.ravel()
    top = flat[i00] + (flat[i00 + 1] - flat[i00]) * fx
    bottom = flat[i00 + stride] + (flat[i00 + stride + 1] - flat[i00 + stride]) * fx
    return top + (bottom - top) * fy


def _fbm(noise: np.ndarray, x: np.ndarray, y: np.ndarray, octaves: int = 3) -> np.ndarray:
    """Fractal sum of value noise, normalised to about [0, 1]."""
    total = np.zeros_like(x)
    amp, freq, norm = 1.0, 1.0, 0.0
    for o in range(octaves):
        total += amp * _value_noise(noise, x * freq + 17.0 * o, y * freq + 31.0 * o)
        norm += amp
        amp *= 0.5
        freq *= 2.0
    return total / norm


def _mix(colors: np.ndarray, w: np.ndarray, i: int = 0, j: int = 1) -> np.ndarray:
    """Blend colours i and j with weight w [N] -> [N, 3]."""
    return colors[i] * (1.0 - w[:, None]) + colors[j] * w[:, None]


def texture(scene: Scene, mat: Material, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Albedo [N, 3] of material `mat` at surface coordinates (u, v) in metres."""
    p = mat.period
    ox, oy = mat.offset
    grain = _fbm(scene.noise, u / 0.06 + ox, v / 0.06 + oy, octaves=2)  # ~6 cm detail
    if mat.kind == "planks":
        row = np.floor(v / p)
        plank = _value_noise(scene.noise, row * 7.3 + ox, row * 3.1 + oy)
        streak = _fbm(scene.noise, u / 0.5 + ox, v / 0.015 + oy)
        w = np.clip(0.6 * plank + 0.5 * streak - 0.05, 0, 1)
        base = _mix(mat.colors, w)
        seam = np.abs((v / p) - np.round(v / p)) * p < 0.006
        base = np.where(seam[:, None], base * 0.45, base)
    elif mat.kind == "bricks":
        bh = p * 0.5
        row = np.floor(v / bh)
        shifted = u / p + 0.5 * (row % 2)
        col = np.floor(shifted)
        tone = _value_noise(scene.noise, col * 5.7 + row * 13.1 + ox, row * 2.3 + oy)
        base = _mix(mat.colors, 0.7 * tone + 0.3 * grain)
        mortar = (np.abs(v / bh - np.round(v / bh)) * bh < 0.008) | (
            np.abs(shifted - np.round(shifted)) * p < 0.008
        )
        base = np.where(mortar[:, None], np.array([0.82, 0.8, 0.76]), base)
    elif mat.kind == "checker":
        s = np.sin(np.pi * u / p) * np.sin(np.pi * v / p)
        w = 0.5 + 0.5 * np.tanh(6.0 * s)
        base = _mix(mat.colors, w)
        dots = _fbm(scene.noise, u / (0.3 * p) + ox, v / (0.3 * p) + oy)
        base = base * (0.8 + 0.4 * dots[:, None])
    elif mat.kind == "stripes":
        c, s = np.cos(mat.angle), np.sin(mat.angle)
        phase = (u * c + v * s) / p
        w = 0.5 + 0.5 * np.sin(2 * np.pi * phase + 2.0 * _fbm(scene.noise, u + ox, v + oy))
        base = _mix(mat.colors, w)
        fine = 0.5 + 0.5 * np.sin(2 * np.pi * (u * -s + v * c) / (0.37 * p))
        base = base * (0.85 + 0.3 * fine[:, None])
    elif mat.kind == "marble":
        n = _fbm(scene.noise, u / p + ox, v / p + oy, octaves=4)
        w = 0.5 + 0.5 * np.sin(2 * np.pi * (u / p + 3.0 * n))
        base = _mix(mat.colors, w)
        veins = _fbm(scene.noise, u / (0.3 * p) + oy, v / (0.3 * p) + ox)[:, None]
        base = base * (1.0 - 0.35 * veins) + mat.colors[2] * 0.35 * veins
    elif mat.kind == "gradient":
        g = np.clip(0.5 + 0.25 * (u + v) / max(p, 1e-6) % 1.0, 0, 1)
        tri = 1.0 - np.abs(2.0 * g - 1.0)
        base = _mix(mat.colors, tri, 0, 2)
        blobs = _fbm(scene.noise, u / 0.25 + ox, v / 0.25 + oy)
        base = base * (0.75 + 0.5 * blobs[:, None])
    else:  # pragma: no cover - materials are made in this module
        raise InputError(f"unknown material kind {mat.kind!r}")
    return np.clip(base * (0.82 + 0.36 * grain[:, None]), 0.0, 1.0)


_UV_AXES = {0: (1, 2), 1: (0, 2), 2: (0, 1)}  # normal axis -> the two in-plane axes


def _surface_frame(scene: Scene, sid: int) -> tuple[np.ndarray, Material, tuple[int, int]]:
    """World normal, material and in-plane (u, v) axes of surface `sid` (see `cast`)."""
    if sid < 6:
        axis, side = (2, sid) if sid < 2 else divmod(sid - 2, 2)
        normal = np.zeros(3)
        normal[axis] = 1.0 if side == 0 else -1.0  # the room's surfaces face inwards
        return normal, scene.room_materials[sid], _UV_AXES[axis]
    k, face = divmod(sid - 6, 6)
    box = scene.boxes[k]
    axis, side = divmod(face, 2)
    n_local = np.zeros(3)
    n_local[axis] = -1.0 if side == 0 else 1.0  # side 0 is entered by rays going +axis
    return _yaw_matrix(box.yaw) @ n_local, box.material, _UV_AXES[axis]


def shade(scene: Scene, points: np.ndarray, surface: np.ndarray) -> np.ndarray:
    """Colour [N, 3] of world points [N, 3] lying on surfaces `surface` [N]."""
    out = np.zeros((len(points), 3), dtype=points.dtype)
    order = np.argsort(surface, kind="stable")
    ids = surface[order]
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
    for start, stop in zip(starts, np.r_[starts[1:], len(ids)], strict=True):
        sid = int(ids[start])
        if sid == SURFACE_NONE:
            continue
        m = order[start:stop]
        normal, mat, (a, b) = _surface_frame(scene, sid)
        if sid < 6:
            local = points[m]
        else:
            box = scene.boxes[(sid - 6) // 6]
            local = (points[m] - box.center) @ _yaw_matrix(box.yaw).astype(points.dtype)
        # different faces of one object must not share a texture patch
        face_shift = 3.7 * (sid % 6)
        albedo = texture(scene, mat, local[:, a] + face_shift, local[:, b])
        lambert = 0.7 + 0.35 * max(0.0, float(normal @ _LIGHT))
        out[m] = albedo * lambert
    return out


def _box_candidates(scene: Scene, K: Intrinsics, T_world_cam: np.ndarray) -> list:
    """Per box, the flat pixel indices inside its projected bounding rectangle (None: all)."""
    R, o = T_world_cam[:3, :3], T_world_cam[:3, 3]
    signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
    out: list[np.ndarray | None] = []
    for box in scene.boxes:
        corners = box.center + (signs * box.half) @ _yaw_matrix(box.yaw).T
        cam = (corners - o) @ R
        if np.any(cam[:, 2] < 1e-3):
            out.append(None)  # straddles the image plane: test every ray
            continue
        u = K.fx * cam[:, 0] / cam[:, 2] + K.cx
        v = K.fy * cam[:, 1] / cam[:, 2] + K.cy
        c0, c1 = max(int(np.floor(u.min())) - 1, 0), min(int(np.ceil(u.max())) + 2, K.width)
        r0, r1 = max(int(np.floor(v.min())) - 1, 0), min(int(np.ceil(v.max())) + 2, K.height)
        if c0 >= c1 or r0 >= r1:
            out.append(np.zeros(0, dtype=np.int64))
            continue
        rr, cc = np.meshgrid(np.arange(r0, r1), np.arange(c0, c1), indexing="ij")
        out.append((rr * K.width + cc).ravel())
    return out


def _planes(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Plane of every surface id: normals [S, 3] and offsets [S] with n . x = c on it."""
    normals, offsets = [], []
    for sid in range(6 + 6 * len(scene.boxes)):
        n, _, _ = _surface_frame(scene, sid)
        if sid < 6:
            point = np.where(n > 0, ROOM_MIN, ROOM_MAX) * np.abs(n)
        else:
            box = scene.boxes[(sid - 6) // 6]
            R = _yaw_matrix(box.yaw)
            point = box.center + R @ ((R.T @ n) * box.half)
        normals.append(n)
        offsets.append(float(n @ point))
    return np.array(normals), np.array(offsets)


def render(
    scene: Scene, K: Intrinsics, T_world_cam: np.ndarray, supersample: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render one view.

    Depth and the surface id come from the pixel-centre ray. Colour averages supersample^2
    samples per pixel, each on the plane of the surface hit by the centre ray (an
    approximation only at silhouette edges), which keeps the cost at one ray cast per pixel.

    Returns:
        color [H, W, 3] float32 in [0, 1], depth [H, W] float32 metres (exact),
        surface [H, W] int64 surface id per pixel.
    """
    origin, dirs = _rays(K, T_world_cam)
    t, surface = cast(scene, origin, dirs, _box_candidates(scene, K, T_world_cam))
    normals, offsets = _planes(scene)
    n, c = normals[surface], offsets[surface]
    steps = (np.arange(supersample) + 0.5) / supersample - 0.5
    points = []
    for dv in steps:
        for du in steps:
            R = T_world_cam[:3, :3]
            d = dirs + (du / K.fx) * R[:, 0] + (dv / K.fy) * R[:, 1]
            denom = np.einsum("ij,ij->i", n, d)
            with np.errstate(divide="ignore", invalid="ignore"):
                ts = (c - n @ origin) / denom
            ts = np.where(np.isfinite(ts) & (ts > 0) & (ts < 2 * t), ts, t)
            points.append((origin + ts[:, None] * d).astype(np.float32))
    # texture maths in float32: colour needs no more, and it halves the cost
    samples = shade(scene, np.concatenate(points), np.tile(surface, len(points)))
    color = samples.reshape(len(points), -1, 3).mean(axis=0)
    return (
        color.reshape(K.height, K.width, 3).astype(np.float32),
        t.reshape(K.height, K.width).astype(np.float32),
        surface.reshape(K.height, K.width),
    )


# ---------------------------------------------------------------------------------------------
# The sequence


class SyntheticSequence:
    """An in-memory `RGBDSequence` of the synthetic room; frames are rendered on demand."""

    def __init__(
        self,
        frames: int = 60,
        size: tuple[int, int] = (320, 240),
        seed: int = 0,
        supersample: int = 1,
    ) -> None:
        if frames <= 0:
            raise OptionError(f"frames must be positive, got {frames}")
        w, h = size
        check_size(size)
        if w < 8 or h < 8:
            raise OptionError(f"size must be at least 8x8, got {w}x{h}")
        check_seed(seed)
        if not 1 <= supersample <= 4:
            raise OptionError(f"supersample must be 1 to 4, got {supersample}")
        self.supersample = int(supersample)
        self._n = int(frames)
        self._intrinsics = default_intrinsics(int(w), int(h))
        self.seed = int(seed)
        self.scene = make_scene(self.seed)

    @property
    def name(self) -> str:
        return f"synthetic_room_seed{self.seed}"

    @property
    def intrinsics(self) -> Intrinsics:
        return self._intrinsics

    @property
    def has_ground_truth(self) -> bool:
        return True

    @property
    def indices(self) -> np.ndarray:
        return np.arange(self._n, dtype=np.int64)

    @property
    def timestamps(self) -> np.ndarray:
        return np.arange(self._n, dtype=np.float64) / FPS

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray]:
        stamps = self.timestamps
        return stamps, np.array([camera_pose(t) for t in stamps])

    def __len__(self) -> int:
        return self._n

    def __iter__(self) -> Iterator[Frame]:
        for i in range(self._n):
            yield self.frame(i)

    def render_with_surfaces(self, i: int) -> tuple[Frame, np.ndarray]:
        """Frame i and the [H, W] surface id of each pixel (for tests and debugging)."""
        if not 0 <= i < self._n:
            raise IndexError(f"frame {i} out of range for {self._n} frames")
        t = i / FPS
        T = camera_pose(t)
        color, depth, surface = render(self.scene, self._intrinsics, T, self.supersample)
        return Frame(index=i, timestamp=t, color=color, depth=depth, T_world_cam=T), surface

    def frame(self, i: int) -> Frame:
        return self.render_with_surfaces(i)[0]


def synthetic_sequence(
    frames: int = 60, size: tuple[int, int] = (320, 240), seed: int = 0, supersample: int = 1
) -> SyntheticSequence:
    """The synthetic room sequence in memory (no files); see the module docstring."""
    return SyntheticSequence(frames, size, seed, supersample)


def writer_threads(limit: int = 4) -> int:
    """Frame-writing threads: `cpu_threads`, at most `limit`."""
    return cpu_threads(limit)


def _check_replaceable(out: Path) -> None:
    """Refuse to replace (`--force`) a folder holding anything a TUM sequence's listings do not
    name: files besides `TUM_ENTRIES` at the top, or in rgb/ and depth/ anything but the images
    that rgb.txt and depth.txt list (a user's notes or originals kept beside the frames)."""
    action = "not replacing it even with `force`"
    check_only_entries(out, TUM_ENTRIES, "a TUM sequence", action, ("force",))
    for images in ("rgb", "depth"):
        folder, listing = out / images, out / f"{images}.txt"
        if not folder.exists():
            continue
        try:
            listed = {name for _, name in read_file_list(listing)}
        except DatasetError:  # missing or unreadable: it names nothing
            listed = set()
        foreign = [
            p.name
            for p in folder.iterdir()
            if not p.is_file() or f"{images}/{p.name}" not in listed
        ]
        if foreign:
            raise OutputError(
                f"{folder} holds files that {listing.name} does not list "
                f"({some_names(foreign)}); {action}"
            )


def write_synthetic_sequence(
    out_dir: str | Path,
    frames: int = 60,
    size: tuple[int, int] = (320, 240),
    seed: int = 0,
    force: bool = False,
    progress: Callable[[int], None] | None = None,
    supersample: int = 1,
) -> Path:
    """Render the synthetic room and write it in TUM layout to `out_dir`.

    Files are written into a temporary folder beside `out_dir` and renamed into place when
    complete, so an interrupted run never leaves a half-written sequence.

    Args:
        out_dir: the output folder; must not exist or be empty unless `force`.
        frames: number of frames (30 per second of camera motion).
        size: image size (W, H).
        seed: fixes colours, noise and box placement.
        force: replace an existing non-empty `out_dir` that holds only a TUM sequence's
            entries (`TUM_ENTRIES`), as an earlier run wrote it.
        progress: called with 1 after each frame.
        supersample: colour samples per pixel along each axis (1: one centre sample, the
            default and fastest; 2: 2x2 anti-aliasing at about twice the cost).

    Returns:
        The output folder.

    Raises:
        OutputError: `out_dir` is a file, holds the current folder, is non-empty without
            `force`, or holds anything besides a sequence's entries.
    """
    out = Path(out_dir)
    if out.is_symlink():  # replacing it would leave the folder it points to as it was
        raise OutputError(f"{out} is a link: name the folder it points to")
    if out.exists() and not out.is_dir():
        raise OutputError(f"output path exists and is not a folder: {out}")
    if out.is_dir() and Path.cwd().resolve().is_relative_to(out.resolve()):
        raise OutputError(f"cannot replace {out}, which holds the current folder: name a new one")
    if out.is_dir() and any(out.iterdir()):
        if not force:
            raise OutputError(
                f"output folder is not empty: {out} (use `force` to replace it)", options=("force",)
            )
        _check_replaceable(out)
    sequence = SyntheticSequence(frames, size, seed, supersample)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    try:
        write_tum_sequence(
            sequence,
            tmp,
            extra={"generator": f"gscompress synth (seed {sequence.seed}, {frames} frames)"},
            progress=progress,
            workers=writer_threads(),
        )
        os.chmod(tmp, 0o755)
        if out.is_dir():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".old", dir=out.parent))
            os.rename(out, old / "x")
            os.rename(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
