"""How a recording becomes a sequence: `RecordingOptions` (topics, pairing tolerance, ground
truth), and which paths are recordings."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gscompress.errors import GscError, OptionError, clipped

DEFAULT_MAX_DT = 0.02
"""Colour/depth pairing tolerance in seconds (TUM associate.py's default)."""
MAX_DT_GT = 0.02
"""A TUM ground-truth file's pose is a frame's when within this many seconds of its stamp."""
RECORDING_SUFFIXES = (".bag", ".mcap", ".db3")


@dataclass(frozen=True)
class RecordingOptions:
    """How a recording becomes a sequence: topics, pairing tolerance and ground truth.

    Attributes:
        rgb: the colour topic (None: chosen, see `gscompress.datasets.recording`).
        depth: the depth topic (None: chosen).
        camera_info: the colour camera's CameraInfo / CameraCalibration topic (None: chosen).
        max_dt: colour/depth pairing tolerance in seconds.
        gt: a TUM trajectory file (camera-to-world) to take ground truth from.
        gt_frames: (world frame, camera frame) of `/tf` to take ground truth from.
    """

    rgb: str | None = None
    depth: str | None = None
    camera_info: str | None = None
    max_dt: float = DEFAULT_MAX_DT
    gt: Path | None = None
    gt_frames: tuple[str, str] | None = None

    def __post_init__(self) -> None:
        if not (isinstance(self.max_dt, int | float) and math.isfinite(self.max_dt)):
            raise OptionError(
                f"`max_dt` must be a number of seconds, got {clipped(self.max_dt)}",
                options=("max_dt",),
            )
        if not 0 < self.max_dt <= 1.0:
            raise OptionError(
                f"`max_dt` must be above 0 and at most 1 s, got {self.max_dt}",
                options=("max_dt",),
            )
        for name in ("rgb", "depth", "camera_info"):
            topic = getattr(self, name)
            if topic is not None and not (isinstance(topic, str) and topic.strip()):
                raise OptionError(f"`{name}` must name a topic", options=(name,))
        if self.gt is not None and self.gt_frames is not None:
            raise OptionError(
                "ground truth from `gt` or from `gt_frames`, not both", options=("gt", "gt_frames")
            )

    @property
    def is_default(self) -> bool:
        """True when nothing was asked for (every field its default)."""
        return self == RecordingOptions()

    def record(self) -> dict[str, Any]:
        """The options as JSON values (what a log records of its run)."""
        return {
            "rgb": self.rgb,
            "depth": self.depth,
            "camera_info": self.camera_info,
            "max_dt": self.max_dt,
            "gt": None if self.gt is None else str(self.gt.resolve()),
            "gt_frames": None if self.gt_frames is None else list(self.gt_frames),
        }

    @classmethod
    def from_record(cls, value: object) -> RecordingOptions | None:
        """The options a log recorded (`record`), or None when it recorded none or garbage."""
        if not isinstance(value, dict):
            return None
        try:
            frames = value.get("gt_frames")
            return cls(
                rgb=value.get("rgb"),
                depth=value.get("depth"),
                camera_info=value.get("camera_info"),
                max_dt=value.get("max_dt", DEFAULT_MAX_DT),
                gt=None if value.get("gt") is None else Path(str(value["gt"])),
                gt_frames=None if frames is None else (str(frames[0]), str(frames[1])),
            )
        except (GscError, TypeError, IndexError, KeyError):
            return None


def is_recording(path: Path) -> bool:
    """True when `path` is a recording: a ROS 2 bag folder (metadata.yaml), or a `.bag`,
    `.mcap` or `.db3` file."""
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix.lower() in RECORDING_SUFFIXES
