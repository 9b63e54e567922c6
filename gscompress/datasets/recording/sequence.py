"""A recording as an `RGBDSequence`: its topics chosen, its colour and depth paired by stamp,
ground truth attached, and frames decoded when the run reaches them (`open_recording`); and what
`gsc info` shows of a recording (`describe_recording`)."""

from __future__ import annotations

import logging
import threading
import weakref
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.camera import Intrinsics
from gscompress.datasets.base import Frame, FrameSelection, iter_frames, resize_color, resize_depth
from gscompress.datasets.recording.containers import Container, Locator, open_container
from gscompress.datasets.recording.decode import decode_color, decode_depth, intrinsics_of
from gscompress.datasets.recording.messages import (
    CAMERA_INFO,
    COMPRESSED,
    IMAGE,
    TF,
    CameraMessage,
    ImageMessage,
    TransformMessage,
    ns_to_seconds,
)
from gscompress.datasets.recording.options import MAX_DT_GT, RecordingOptions
from gscompress.datasets.recording.tf import tf_poses
from gscompress.datasets.recording.topics import TopicChoice, choose_topics, registered
from gscompress.datasets.stamps import associate
from gscompress.errors import DatasetError, GscError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class _Pair:
    """One frame: colour and depth message locators, and the colour stamp."""

    stamp_ns: int
    color: Locator
    depth: Locator


class RecordingSequence:
    """An `RGBDSequence` over a recording; frames are decoded on demand (see
    `gscompress.datasets.recording`). `skipped` counts the colour and depth messages left
    without a partner."""

    def __init__(
        self,
        path: Path,
        container: Container,
        choice: TopicChoice,
        pairs: Sequence[_Pair],
        native: Intrinsics,
        poses: Sequence[np.ndarray | None],
        selection: FrameSelection,
        size: tuple[int, int] | None,
        skipped: dict[str, int],
    ) -> None:
        self.path = path
        self.choice = choice
        self.skipped = skipped
        self._container = container
        self._pairs = list(pairs)
        self._poses = list(poses)
        self._native = native
        self._lock = threading.Lock()  # (frames may be read from several threads)
        # the files close with the sequence, which the commands drop rather than close
        self._finalizer = weakref.finalize(self, container.close)
        self._indices = selection.apply(len(self._pairs))
        if len(self._indices) == 0:
            raise DatasetError(
                f"{self.name}: frame subset {selection} selects none of {len(self._pairs)} frames"
            )
        w, h = size if size is not None else (native.width, native.height)
        self._intrinsics = native.scaled(w, h)

    @property
    def name(self) -> str:
        return self.path.stem if self.path.is_file() else self.path.resolve().name

    @property
    def intrinsics(self) -> Intrinsics:
        return self._intrinsics

    @property
    def native_intrinsics(self) -> Intrinsics:
        """Intrinsics at the recorded image size."""
        return self._native

    @property
    def indices(self) -> np.ndarray:
        return self._indices.copy()

    @property
    def timestamps(self) -> np.ndarray:
        return np.array([ns_to_seconds(self._pairs[i].stamp_ns) for i in self._indices])

    @property
    def has_ground_truth(self) -> bool:
        return any(self._poses[i] is not None for i in self._indices)

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray]:
        kept = [i for i in self._indices if self._poses[i] is not None]
        stamps = np.array([ns_to_seconds(self._pairs[i].stamp_ns) for i in kept])
        poses = np.array([self._poses[i] for i in kept], dtype=np.float64).reshape(-1, 4, 4)
        return stamps, poses

    def __len__(self) -> int:
        return len(self._indices)

    def __iter__(self) -> Iterator[Frame]:
        return iter_frames(self)

    def frame(self, i: int) -> Frame:
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame {i} out of range for {len(self)} frames")
        index = int(self._indices[i])
        pair = self._pairs[index]
        with self._lock:
            color_msg = self._container.fetch(pair.color)
            depth_msg = self._container.fetch(pair.depth)
        expected = (self._native.width, self._native.height)
        color = decode_color(color_msg, expected, f"{self.path}: {self.choice.rgb} frame {index}")
        depth = decode_depth(depth_msg, expected, f"{self.path}: {self.choice.depth} frame {index}")
        k = self._intrinsics
        pose = self._poses[index]
        return Frame(
            index=index,
            timestamp=ns_to_seconds(pair.stamp_ns),
            color=resize_color(color, k.width, k.height),
            depth=resize_depth(depth, k.width, k.height),
            T_world_cam=None if pose is None else pose.copy(),
        )

    def close(self) -> None:
        """Close the recording's files."""
        self._finalizer()


def open_recording(
    path: Path,
    selection: FrameSelection,
    size: tuple[int, int] | None = None,
    intrinsics: Intrinsics | None = None,
    options: RecordingOptions | None = None,
) -> RecordingSequence:
    """Open a recording as a sequence (see `gscompress.datasets.recording`).

    Args:
        path: a ROS 2 bag folder, or a `.bag`, `.mcap` or `.db3` file.
        selection: frame subset, on the 0-based index of the paired frames.
        size: working size (W, H), or None for the recorded size.
        intrinsics: explicit intrinsics instead of the camera info's.
        options: topics, pairing tolerance and ground truth.

    Raises:
        DatasetError: an unreadable or hostile recording, an ambiguous or missing topic,
            depth not registered to colour, no pairs, a bad camera info.
    """
    options = options or RecordingOptions()
    container = open_container(path)
    try:
        return _build(path, container, selection, size, intrinsics, options)
    except BaseException:
        container.close()
        raise


def _build(
    path: Path,
    container: Container,
    selection: FrameSelection,
    size: tuple[int, int] | None,
    intrinsics: Intrinsics | None,
    options: RecordingOptions,
) -> RecordingSequence:
    """The steps of `open_recording`: choose topics, scan stamps, check registration and
    intrinsics, pair, attach ground truth."""
    choice = choose_topics(container.topics, options, str(path))
    scanned = _scan(container, choice)
    colors, depths, info = scanned["rgb"], scanned["depth"], scanned["info"]
    if not colors or not depths:
        empty = choice.rgb if not colors else choice.depth
        raise DatasetError(f"{path}: {empty} holds no message (declared counts without data?)")
    if info is None:
        raise DatasetError(f"{path}: {choice.camera_info} holds no camera info message")
    native = intrinsics or intrinsics_of(info, choice.camera_info)
    first_color, first_depth = colors[0][2], depths[0][2]
    depth_size = None if first_depth.compressed else (first_depth.width, first_depth.height)
    if not registered(choice.depth, first_depth, first_color, depth_size):
        raise DatasetError(
            f"{path}: depth {choice.depth} (frame {first_depth.frame_id!r}) is not registered to "
            f"colour {choice.rgb} (frame {first_color.frame_id!r}): record an aligned depth topic "
            "(RealSense align_depth, Azure Kinect depth_to_rgb, OpenNI depth_registered)"
        )
    pairs_ij = associate(
        np.array([ns_to_seconds(s) for s, _, _ in colors]),
        np.array([ns_to_seconds(s) for s, _, _ in depths]),
        options.max_dt,
    )
    if not pairs_ij:
        raise DatasetError(
            f"{path}: no colour/depth pair within {options.max_dt} s ({choice.rgb}, "
            f"{choice.depth}); `max_dt` widens it",
            options=("max_dt",),
        )
    pairs = [_Pair(colors[i][0], colors[i][1], depths[j][1]) for i, j in pairs_ij]
    skipped = {"rgb": len(colors) - len(pairs), "depth": len(depths) - len(pairs)}
    if skipped["rgb"] or skipped["depth"]:
        log.info(
            "%s: %d frames paired; skipped %d colour and %d depth messages without a partner "
            "within %g s",
            path,
            len(pairs),
            skipped["rgb"],
            skipped["depth"],
            options.max_dt,
        )
    stamps = [p.stamp_ns for p in pairs]
    poses = _ground_truth(container, options, stamps, str(path))
    return RecordingSequence(
        path, container, choice, pairs, native, poses, selection, size, skipped
    )


def _scan(container: Container, choice: TopicChoice) -> dict[str, Any]:
    """One pass over the chosen topics: (stamp, locator, first message) of colour and depth,
    sorted by stamp, and the first camera info."""
    found: dict[str, Any] = {"rgb": [], "depth": [], "info": None}
    keys = {choice.rgb: "rgb", choice.depth: "depth"}
    for topic, _log_time, locator, msg in container.scan(
        [choice.rgb, choice.depth, choice.camera_info]
    ):
        key = keys.get(topic)
        if key is not None:
            if not isinstance(msg, ImageMessage):  # pragma: no cover - checked by kind
                raise DatasetError(f"{topic} holds no image")
            first = msg if not found[key] else None
            found[key].append((msg.stamp_ns, locator, first))
        elif found["info"] is None:
            found["info"] = msg
    for key in ("rgb", "depth"):
        rows = found[key]
        if rows:
            first = rows[0][2]
            rows = sorted(((s, loc, None) for s, loc, _ in rows), key=lambda r: r[0])
            rows[0] = (rows[0][0], rows[0][1], first)
            found[key] = rows
    return found


def _ground_truth(
    container: Container, options: RecordingOptions, stamps_ns: Sequence[int], source: str
) -> list[np.ndarray | None]:
    """Each frame's ground-truth pose (None where there is none)."""
    if options.gt is not None:
        from gscompress.errors import InputError
        from gscompress.io.trajectory import nearest_times, read_tum_trajectory

        try:
            gt = read_tum_trajectory(options.gt)
        except InputError as exc:
            raise DatasetError(str(exc)) from None
        seconds = np.array([ns_to_seconds(s) for s in stamps_ns])
        k = nearest_times(seconds, gt.timestamps, MAX_DT_GT, strict=True)
        return [gt.T_world_cam[j] if j >= 0 else None for j in k]
    if options.gt_frames is not None:
        names = {t.name for t in container.topics if t.kind == TF}
        transforms: list[TransformMessage] = []
        for _topic, _time, _loc, msg in container.scan(sorted(names)):
            transforms.extend(msg)
        if not transforms:
            raise DatasetError(
                f"{source} has no /tf message for `gt_frames`", options=("gt_frames",)
            )
        return tf_poses(transforms, *options.gt_frames, stamps_ns)
    return [None] * len(stamps_ns)


def describe_recording(
    path: Path,
    options: RecordingOptions | None = None,
    error_text: Callable[[GscError], str] = str,
) -> dict[str, Any]:
    """What `gsc info` shows of a recording: its kind, every topic with its count, and for
    image and camera-info topics the size, encoding and rate; the pair `gsc slam` would take
    (or why it would take none: the error as `error_text` says it). Reads the image topics
    once."""
    options = options or RecordingOptions()
    container = open_container(path)
    try:
        topics = []
        wanted = [t.name for t in container.topics if t.kind in (IMAGE, COMPRESSED, CAMERA_INFO)]
        seen: dict[str, dict[str, Any]] = {}
        for topic, log_time, _loc, msg in container.scan(wanted):
            entry = seen.setdefault(topic, {"first_ns": log_time, "last_ns": log_time, "n": 0})
            entry["n"] += 1
            entry["first_ns"] = min(entry["first_ns"], log_time)
            entry["last_ns"] = max(entry["last_ns"], log_time)
            if "sample" not in entry:
                entry["sample"] = msg
        for t in container.topics:
            row: dict[str, Any] = {
                "topic": t.name,
                "type": t.msgtype,
                "kind": t.kind or "other",
                "messages": t.count,
            }
            found = seen.get(t.name)
            if found is not None:
                row.update(_sample_fields(found["sample"]))
                span = (found["last_ns"] - found["first_ns"]) / 1e9
                row["rate_hz"] = round((found["n"] - 1) / span, 3) if span > 0 else None
            topics.append(row)
        result: dict[str, Any] = {"path": str(path), "kind": container.kind, "topics": topics}
        try:
            sequence = _build(path, container, FrameSelection(), None, None, options)
        except DatasetError as exc:
            result["slam_would_read"] = None
            result["why_not"] = error_text(exc)
        else:
            c = sequence.choice
            result["slam_would_read"] = {
                "rgb": c.rgb,
                "depth": c.depth,
                "camera_info": c.camera_info,
                "chosen_by": c.reason,
                "frames": len(sequence._pairs),
                "skipped": sequence.skipped,
                "max_dt": options.max_dt,
                "size": [sequence.native_intrinsics.width, sequence.native_intrinsics.height],
            }
        return result
    finally:
        container.close()


def _sample_fields(msg: Any) -> dict[str, Any]:
    """Size and encoding of a topic's first message, for `describe_recording`."""
    if isinstance(msg, ImageMessage):
        if msg.compressed:
            return {"encoding": msg.encoding, "size": None, "frame_id": msg.frame_id}
        return {"encoding": msg.encoding, "size": [msg.width, msg.height], "frame_id": msg.frame_id}
    if isinstance(msg, CameraMessage):
        return {"size": [msg.width, msg.height], "frame_id": msg.frame_id, "distortion": msg.model}
    return {}


def with_topics(options: RecordingOptions, choice: TopicChoice) -> RecordingOptions:
    """`options` with the topics a sequence was read from (what a log records of its run)."""
    return replace(options, rgb=choice.rgb, depth=choice.depth, camera_info=choice.camera_info)
