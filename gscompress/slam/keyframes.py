"""Keyframes and the mapping window (SplaTAM's overlap-based selection).

Every `every`-th frame is kept as a keyframe with its observed colour and depth and the pose
estimated when it was tracked; with `PoseConfig` on, the mapping refines that pose later
(`View.pose`). The mapping window of a frame is
the current frame plus the keyframes that see most of what it sees: pixels of the current
depth map are back-projected with the current pose estimate and projected into each keyframe;
the fraction that lands inside the keyframe's image in front of its camera is its overlap (no
occlusion test, as in SplaTAM). The most recent keyframe is always in the window.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import torch

from gscompress.camera import Intrinsics, invert_transform, transform_points
from gscompress.slam.config import KeyframeConfig
from gscompress.slam.losses import depth_edges
from gscompress.slam.poses import PoseVariable


def frame_tensors(frame: Any, device: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """A sequence `Frame`'s colour [H, W, 3] and depth [H, W] as float32 tensors on `device`."""
    color = torch.from_numpy(np.ascontiguousarray(frame.color, np.float32)).to(device)
    depth = torch.from_numpy(np.ascontiguousarray(frame.depth, np.float32)).to(device)
    return color, depth


class ImageSource(NamedTuple):
    """Where a released view's colour and depth are read again, and what it holds meanwhile.

    Attributes:
        read: the view's (colour, depth) tensors, read and decoded again.
        empty: the empty (colour, depth) pair a released view holds: one pair for all of a
            run's views, so that a release allocates nothing.
    """

    read: Callable[[], tuple[torch.Tensor, torch.Tensor]]
    empty: tuple[torch.Tensor, torch.Tensor]


@dataclass
class View:
    """An observed frame with a fixed pose, as the mapper uses it.

    Attributes:
        index: processing position of the frame (0 = first frame of the run).
        color: [H, W, 3] observed colour (tensor on the map's device).
        depth: [H, W] observed depth, 0 = invalid.
        T_world_cam: [4, 4] float64 camera-to-world pose estimate (refined in place of the
            tracked one when `pose` is set and the mapping steps it).
        pose: the pose's refinement state, when the mapping may refine it (None: fixed).
        source: where its colour and depth can be read again (None: they stay in memory);
            with one, `release` drops them and `load` reads them back.
    """

    index: int
    color: torch.Tensor
    depth: torch.Tensor
    T_world_cam: np.ndarray
    _edges: dict[float, torch.Tensor] = field(default_factory=dict, repr=False, compare=False)
    pose: PoseVariable | None = field(default=None, repr=False, compare=False)
    source: ImageSource | None = field(default=None, repr=False, compare=False)

    @classmethod
    def from_frame(cls, index: int, frame: Any, T_world_cam: np.ndarray, device: Any) -> View:
        """The view of a sequence `Frame` at processing position `index` with a given pose."""
        return cls(index, *frame_tensors(frame, device), np.asarray(T_world_cam, dtype=np.float64))

    def edges(self, sigma: float) -> torch.Tensor:
        """[H, W] `depth_edges` of the observed depth, computed once per sigma and kept with the
        view (the mapping loss needs it at every iteration; `depth` is never changed in place)."""
        if sigma not in self._edges:
            self._edges[sigma] = depth_edges(self.depth, sigma)
        return self._edges[sigma]

    def release(self) -> None:
        """Drop the colour, depth and edges of a view that has a `source` (kept otherwise).

        The view then holds its source's shared empty pair: a new pair per release would be
        small allocations that outlive the images they replace, placed by the allocator in the
        space those images just freed, so that the next view's images take fresh heap and the
        process grows by about a view's images for every view a final refinement visits
        (docs/recordings.md, "Streaming and memory").
        """
        if self.source is not None:
            self.color, self.depth = self.source.empty
            self._edges.clear()

    def load(self) -> View:
        """This view with its colour and depth in memory (read again from `source` when
        released)."""
        if self.source is not None and self.color.numel() == 0:
            self.color, self.depth = self.source.read()
        return self

    def refinable(self, lr: np.ndarray) -> View:
        """This view with its pose open to refinement at Adam rates `lr` [6] (kept if open)."""
        if self.pose is None:
            self.pose = PoseVariable(self.T_world_cam, lr)
        return self

    @property
    def refined(self) -> bool:
        """Whether the mapping has stepped this view's pose."""
        return self.pose is not None and self.pose.adam.t > 0

    def step_pose(self, g_T_cam_world: np.ndarray, rate: float = 1.0) -> None:
        """Move the pose one Adam step along dL/dT_cam_world [4, 4]."""
        assert self.pose is not None
        self.T_world_cam = self.pose.step(g_T_cam_world, rate)

    def T_cam_world(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """[4, 4] world-to-camera tensor on the view's device."""
        return torch.as_tensor(
            invert_transform(self.T_world_cam), dtype=dtype, device=self.color.device
        )


class HeldImages:
    """Which of a run's views hold their images.

    Views of frames the run can read again (`frames`: the frame at a processing position) get
    a `View.source`; of those, only the keyframes the mapping used last (`capacity`: a
    window's worth and the newest) keep their images between frames: the window mostly draws on
    recent keyframes, and any other view is read again when used.
    """

    def __init__(self, frames: Callable[[int], Any] | None, device: Any, capacity: int) -> None:
        self.frames, self.device, self.capacity = frames, device, capacity
        self.held: list[View] = []  # used last first
        self.empty = (torch.empty(0, device=device), torch.empty(0, device=device))
        """What every released view holds (`ImageSource.empty`)."""

    def sourced(self, view: View) -> View:
        """`view` with its `source` set when its frame can be read again."""
        frames, device = self.frames, self.device
        if frames is not None and view.index >= 0:
            position = view.index
            view.source = ImageSource(lambda: frame_tensors(frames(position), device), self.empty)
        return view

    def hold(self, used: list[View]) -> None:
        """Keep the images of `used` (used last), releasing those beyond `capacity`."""
        for view in used:
            self.held = [view, *(v for v in self.held if v is not view)]
        for view in self.held[self.capacity :]:
            view.release()
        del self.held[self.capacity :]


def carried_views(frames: list[Any], device: Any, first: int = -1) -> list[View]:
    """Views of another agent's keyframes (`gscompress.io.keyframes.CarriedFrame`s, at their
    poses), numbered down from `first` (negative: no frame position of this run)."""
    return [View.from_frame(first - k, f, f.T_world_cam, device) for k, f in enumerate(frames)]


def is_keyframe(position: int, config: KeyframeConfig) -> bool:
    """Whether the frame at this processing position becomes a keyframe."""
    return position % config.every == 0


def in_views(position: int, views: str, config: KeyframeConfig) -> bool:
    """Whether the frame at this processing position is one of `views` (`REFINE_VIEWS`: every
    frame, or the keyframes)."""
    return views == "frames" or is_keyframe(position, config)


def sample_points(
    depth: np.ndarray,
    intrinsics: Intrinsics,
    T_world_cam: np.ndarray,
    samples: int,
    rng: np.random.Generator,
) -> np.ndarray:
    """[M, 3] world points of up to `samples` random valid pixels of a depth map."""
    v, u = np.nonzero(depth > 0)
    if len(v) > samples:
        pick = rng.choice(len(v), size=samples, replace=False)
        v, u = v[pick], u[pick]
    return intrinsics.backproject(u, v, depth[v, u], T_world_cam)


def overlap_fraction(points: np.ndarray, intrinsics: Intrinsics, T_world_cam: np.ndarray) -> float:
    """Fraction of world points [M, 3] that project inside the image in front of the camera."""
    if len(points) == 0:
        return 0.0
    cam = transform_points(invert_transform(T_world_cam), points)
    z = cam[:, 2]
    front = z > 1e-6
    zs = np.where(front, z, 1.0)
    u = intrinsics.fx * cam[:, 0] / zs + intrinsics.cx
    v = intrinsics.fy * cam[:, 1] / zs + intrinsics.cy
    inside = (
        front
        & (u >= -0.5)
        & (u <= intrinsics.width - 0.5)
        & (v >= -0.5)
        & (v <= intrinsics.height - 0.5)
    )
    return float(inside.mean())


def select_window(
    keyframes: list[View],
    current: View,
    intrinsics: Intrinsics,
    config: KeyframeConfig,
    rng: np.random.Generator,
) -> list[View]:
    """The keyframes to map together with `current` (not including it).

    Up to `config.window` keyframes: the latest one, then those with the largest overlap with
    the current frame (ties: the more recent first); keyframes without overlap are left out.
    """
    if not keyframes or config.window == 0:
        return []
    depth = current.depth.detach().cpu().numpy()
    points = sample_points(depth, intrinsics, current.T_world_cam, config.overlap_samples, rng)
    latest = keyframes[-1]
    scored = [
        (overlap_fraction(points, intrinsics, kf.T_world_cam), kf.index, kf)
        for kf in keyframes[:-1]
        if kf.index != current.index
    ]
    scored = [s for s in scored if s[0] > 0.0]
    scored.sort(key=lambda s: (-s[0], -s[1]))
    chosen = [latest] if latest.index != current.index else []
    chosen += [kf for _, _, kf in scored[: config.window - len(chosen)]]
    return chosen
