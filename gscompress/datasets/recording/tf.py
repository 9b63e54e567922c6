"""Ground truth from /tf: the pose of one frame in another at given stamps, through the chain of
links between them, each moving link interpolated between its two nearest samples."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from gscompress.camera import interpolate_pose, invert_transform
from gscompress.datasets.recording.messages import TransformMessage
from gscompress.errors import DatasetError, clipped


@dataclass
class _Link:
    """One parent -> child link of the tf tree: its stamped samples."""

    static: bool
    stamps: list[int] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)
    _order: np.ndarray | None = None  # (sorted once, on the first look-up)
    _sorted: np.ndarray | None = None

    def at(self, stamp: int) -> np.ndarray | None:
        """T_parent_child at `stamp`, interpolated; None outside its samples."""
        if self.static:
            return self.poses[-1]
        order, stamps = self._order, self._sorted
        if order is None or stamps is None:
            order = self._order = np.argsort(np.asarray(self.stamps, dtype=np.int64), kind="stable")
            stamps = self._sorted = np.asarray(self.stamps, dtype=np.int64)[order]
        k = int(np.searchsorted(stamps, stamp, side="left"))
        if k < len(stamps) and stamps[k] == stamp:
            return self.poses[int(order[k])]
        if k == 0 or k == len(stamps):
            return None
        t0, t1 = int(stamps[k - 1]), int(stamps[k])
        T0, T1 = self.poses[int(order[k - 1])], self.poses[int(order[k])]
        return interpolate_pose(T0, T1, (stamp - t0) / (t1 - t0))


def tf_poses(
    transforms: Sequence[TransformMessage], world: str, camera: str, stamps_ns: Sequence[int]
) -> list[np.ndarray | None]:
    """T_world_camera at each stamp from tf samples (see `gscompress.datasets.recording`), None
    where a link of the chain has no sample on both sides of the stamp.

    Raises:
        DatasetError: no chain of links joins `world` and `camera`.
    """
    links: dict[tuple[str, str], _Link] = {}
    for t in transforms:
        link = links.setdefault((t.parent, t.child), _Link(t.static))
        link.stamps.append(t.stamp_ns)
        link.poses.append(t.T_parent_child)
    chain = _chain(links, world.lstrip("/"), camera.lstrip("/"))
    out: list[np.ndarray | None] = []
    for stamp in stamps_ns:
        steps = [(links[link].at(stamp), forward) for link, forward in chain]
        T = np.eye(4)
        for step, forward in steps:
            if step is None:
                break
            T = T @ (step if forward else invert_transform(step))
        out.append(None if any(step is None for step, _ in steps) else T)
    return out


def _chain(
    links: dict[tuple[str, str], _Link], world: str, camera: str
) -> list[tuple[tuple[str, str], bool]]:
    """The links from `world` to `camera` (each with whether it is walked parent to child)."""
    neighbours: dict[str, list[tuple[str, tuple[str, str], bool]]] = {}
    for parent, child in links:
        neighbours.setdefault(parent, []).append((child, (parent, child), True))
        neighbours.setdefault(child, []).append((parent, (parent, child), False))
    paths: dict[str, list[tuple[tuple[str, str], bool]]] = {world: []}
    queue = [world]
    while queue:
        frame = queue.pop(0)
        for other, link, forward in neighbours.get(frame, []):
            if other not in paths:
                paths[other] = [*paths[frame], (link, forward)]
                queue.append(other)
    if camera not in paths or world not in neighbours:
        frames = sorted(neighbours)
        raise DatasetError(
            f"/tf joins no chain from {clipped(world)} to {clipped(camera)} (frames: "
            f"{', '.join(frames[:12]) or 'none'}{' ...' if len(frames) > 12 else ''})"
        )
    return paths[camera]
