"""Robot recordings as RGB-D sequences: ROS 2 bags (MCAP or sqlite), ROS 1 bags, Foxglove MCAP.

`open_recording(path, ...)` returns a `RecordingSequence`, an `RGBDSequence` like a dataset
folder's: frames are decoded when the run reaches them (`frame(i)` reads two messages), so memory
does not grow with the recording's length; opening reads each chosen topic's messages once for
their stamps (a few dozen bytes kept per message).

Containers. A ROS 2 bag (a folder with `metadata.yaml`, or one `.mcap` / `.db3` file) and a
ROS 1 `.bag` are read with `rosbags` (pure Python, Apache-2.0), imported when a recording is
opened. An MCAP file whose header profile is not `ros2` is read as a Foxglove recording (schemas
`foxglove.RawImage`, `foxglove.CompressedImage`, `foxglove.CameraCalibration`,
`foxglove.FrameTransform(s)` in protobuf) through the project's bounded MCAP reader. Every MCAP
file is first checked as a log is (a summary, every chunk's declared size within
`MAX_CHUNK_RATIO` times its compressed size and `MAX_CHUNK_BYTES`), and a ROS 1 bag's chunks are
inflated within the same bounds; ROS 2 bags compressed per file or per message are refused.

Messages. Colour: `sensor_msgs/Image` rgb8, bgr8, rgba8, bgra8, mono8 (alpha dropped, grey
repeated), `CompressedImage` JPEG or PNG, and the Foxglove equivalents. Depth: 16UC1
(millimetres; 0 and 65535 read as no depth), 32FC1 (metres; 0, negative and non-finite read as no
depth), `compressedDepth` PNG (image_transport's 12-byte header, then a 16-bit PNG of
millimetres, or of quantised inverse depth for 32FC1) and a 16-bit PNG `foxglove.
CompressedImage` (millimetres). Intrinsics come from the colour camera's `CameraInfo` /
`CameraCalibration` (its `K`); images are used as recorded, so a distortion model with any
non-zero coefficient is refused (plumb_bob, rational_polynomial, equidistant or none with all
coefficients zero are fine): record rectified images (`image_rect_color`).

Topics. Taken from the options when given, else chosen when unambiguous: a known pair of a
RealSense, Azure Kinect, OpenNI, TUM RGB-D or Foxglove-style recording, else the only colour
and the only depth topic (a topic whose name says `depth` holds depth). image_transport's
`/compressed` and `/compressedDepth` topics stand for their base topic when it was not recorded.
Depth must be registered to colour: a topic named as aligned (`aligned_depth_to_color`,
`depth_to_rgb`, `depth_registered`, TUM's `/camera/depth/image`) or of the same frame id and size.

Pairing. Colour and depth are paired by their header stamps (the log time where a stamp is 0)
within `max_dt` by `gscompress.datasets.stamps.associate`, the TUM reader's rule; a frame without
a partner is skipped and counted. Ground truth: a TUM file (`gt`), or `/tf` and `/tf_static`
(`gt_frames` = (world, camera)), the chain between the two frames composed, each moving link
interpolated at the colour stamp (quaternion slerp, translation linear) between its two nearest
samples; a frame outside the samples of a link has no pose.
"""

from __future__ import annotations

import bz2
import io
import logging
import math
import struct
import threading
import weakref
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from gscompress.camera import (
    Intrinsics,
    interpolate_pose,
    invert_transform,
    make_transform,
    quat_to_rotmat,
)
from gscompress.datasets.base import (
    DEFAULT_INVALID_DEPTH,
    MAX_SIDE,
    Frame,
    FrameSelection,
    color_from_uint8,
    depth_from_units,
    iter_frames,
    resize_color,
    resize_depth,
)
from gscompress.datasets.stamps import associate
from gscompress.errors import DatasetError, GscError, MissingDependencyError, OptionError, clipped

log = logging.getLogger(__name__)

DEFAULT_MAX_DT = 0.02
"""Colour/depth pairing tolerance in seconds (TUM associate.py's default)."""
MAX_DT_GT = 0.02
"""A TUM ground-truth file's pose is a frame's when within this many seconds of its stamp."""
MM_PER_METRE = 1000.0
RECORDING_SUFFIXES = (".bag", ".mcap", ".db3")
MAX_COMPRESSED_RATIO = 2.0
"""A compressed image may hold at most this many times the bytes of its raw pixels (plus
`_COMPRESSED_SLACK`): PNG of noise is a little larger than raw, JPEG far smaller."""
_COMPRESSED_SLACK = 1 << 20
_COMPRESSED_DEPTH_HEADER = 12  # image_transport's ConfigHeader: int32 format, float32[2]

KNOWN_PAIRS: tuple[tuple[str, str, str], ...] = (
    # (source, colour, depth registered to it)
    ("RealSense", "/camera/color/image_raw", "/camera/aligned_depth_to_color/image_raw"),
    ("RealSense", "/camera/camera/color/image_raw",
     "/camera/camera/aligned_depth_to_color/image_raw"),
    ("Azure Kinect", "/rgb/image_raw", "/depth_to_rgb/image_raw"),
    ("OpenNI", "/camera/rgb/image_color", "/camera/depth_registered/image_raw"),
    ("OpenNI", "/camera/rgb/image_rect_color", "/camera/depth_registered/image_raw"),
    ("TUM RGB-D", "/camera/rgb/image_color", "/camera/depth/image"),
    ("Foxglove", "/camera/color", "/camera/depth"),
    ("Foxglove", "/camera/image", "/camera/depth"),
)  # fmt: skip
"""Topic pairs chosen by name when both are in a recording (the first that is, in this order)."""
REGISTERED_MARKS = ("aligned_depth_to_color", "depth_to_rgb", "depth_registered")
"""A depth topic whose name holds one of these is registered to colour by its driver."""
_TRANSPORTS = ("/compressed", "/compressedDepth")

# message kinds, from ROS type names and Foxglove schema names
IMAGE, COMPRESSED, CAMERA_INFO, TF = "image", "compressed", "camera_info", "tf"
_KINDS = {
    "sensor_msgs/msg/Image": IMAGE,
    "sensor_msgs/msg/CompressedImage": COMPRESSED,
    "sensor_msgs/msg/CameraInfo": CAMERA_INFO,
    "tf2_msgs/msg/TFMessage": TF,
    "tf/msg/tfMessage": TF,
    "foxglove.RawImage": IMAGE,
    "foxglove.CompressedImage": COMPRESSED,
    "foxglove.CameraCalibration": CAMERA_INFO,
    "foxglove.FrameTransforms": TF,
    "foxglove.FrameTransform": TF,
}

COLOR_ENCODINGS = {"rgb8": (3, (0, 1, 2)), "bgr8": (3, (2, 1, 0)), "rgba8": (4, (0, 1, 2)),
                   "bgra8": (4, (2, 1, 0)), "mono8": (1, (0, 0, 0))}  # fmt: skip
"""Raw colour encodings: channels per pixel and which give R, G, B."""
DEPTH_ENCODINGS: dict[str, np.dtype[Any]] = {
    "16UC1": np.dtype("u2"),
    "mono16": np.dtype("u2"),
    "32FC1": np.dtype("f4"),
}
"""Raw depth encodings: 16UC1 / mono16 in millimetres, 32FC1 in metres."""
UNDISTORTED_MODELS = ("", "none", "plumb_bob", "rational_polynomial", "equidistant",
                      "kannala_brandt")  # fmt: skip
"""Distortion models accepted when every coefficient is zero (images used as they are)."""


# ---------------------------------------------------------------------------------------------
# Options


@dataclass(frozen=True)
class RecordingOptions:
    """How a recording becomes a sequence: topics, pairing tolerance and ground truth.

    Attributes:
        rgb: the colour topic (None: chosen, see the module docstring).
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
            raise OptionError(f"--max-dt must be a number of seconds, got {clipped(self.max_dt)}")
        if not 0 < self.max_dt <= 1.0:
            raise OptionError(f"--max-dt must be above 0 and at most 1 s, got {self.max_dt}")
        for name in ("rgb", "depth", "camera_info"):
            topic = getattr(self, name)
            if topic is not None and not (isinstance(topic, str) and topic.strip()):
                raise OptionError(f"--{name.replace('_', '-')} must name a topic")
        if self.gt is not None and self.gt_frames is not None:
            raise OptionError("ground truth from --gt or from --gt-frames, not both")

    @property
    def is_default(self) -> bool:
        """True when nothing was asked for (every field its default)."""
        return self == RecordingOptions()

    def record(self) -> dict[str, Any]:
        """The options as JSON values (what a log records of its run)."""
        return {
            "rgb": self.rgb, "depth": self.depth, "camera_info": self.camera_info,
            "max_dt": self.max_dt, "gt": None if self.gt is None else str(self.gt.resolve()),
            "gt_frames": None if self.gt_frames is None else list(self.gt_frames),
        }  # fmt: skip

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


# ---------------------------------------------------------------------------------------------
# Messages, as every container gives them


@dataclass(frozen=True)
class ImageMessage:
    """A colour or depth image message, not yet decoded.

    Attributes:
        stamp_ns: its header stamp (the log time where the stamp is 0).
        frame_id: its camera frame.
        encoding: a raw image's encoding ("rgb8", "16UC1", ...); for a compressed one, its
            format string ("jpeg", "png", "16UC1; compressedDepth png", ...).
        compressed: a CompressedImage (its size is known only from its header).
        width, height: a raw image's size (0 for a compressed one).
        step: a raw image's bytes per row.
        big_endian: a raw image's byte order.
        data: the bytes.
    """

    stamp_ns: int
    frame_id: str
    encoding: str
    compressed: bool
    width: int = 0
    height: int = 0
    step: int = 0
    big_endian: bool = False
    data: Any = b""


@dataclass(frozen=True)
class CameraMessage:
    """A CameraInfo / CameraCalibration message: size, K (row-major 9), distortion."""

    frame_id: str
    width: int
    height: int
    K: tuple[float, ...]
    model: str
    D: tuple[float, ...]


@dataclass(frozen=True)
class TransformMessage:
    """One stamped transform of /tf: child frame to parent frame, as T_parent_child."""

    stamp_ns: int
    parent: str
    child: str
    T_parent_child: np.ndarray
    static: bool


@dataclass(frozen=True)
class TopicInfo:
    """A topic of a recording: name, message type (ROS type or Foxglove schema), kind
    (`IMAGE`, `COMPRESSED`, `CAMERA_INFO`, `TF` or "" for others) and message count."""

    name: str
    msgtype: str
    kind: str
    count: int


def _ns(sec: int, nanosec: int) -> int:
    """Integer nanoseconds of a (sec, nanosec) stamp."""
    return int(sec) * 1_000_000_000 + int(nanosec)


def ns_to_seconds(ns: int) -> float:
    """Seconds as a float, correctly rounded (a stamp written from a 6-decimal TUM time reads
    back as the same float)."""
    return float(Fraction(int(ns), 1_000_000_000))


def seconds_to_stamp_ns(seconds: float) -> int:
    """Integer nanoseconds of a time in seconds, from its shortest decimal form (so that
    `ns_to_seconds` gives the same float back for any time of at most 9 decimals)."""
    return round(Fraction(repr(float(seconds))) * 1_000_000_000)


def _ros_stamp(header: Any, log_time_ns: int) -> int:
    stamp = _ns(header.stamp.sec, header.stamp.nanosec)
    return stamp if stamp > 0 else log_time_ns


def _from_ros(kind: str, msg: Any, log_time_ns: int, static: bool) -> Any:
    """The message of a rosbags-deserialised ROS message."""
    if kind == IMAGE:
        return ImageMessage(
            _ros_stamp(msg.header, log_time_ns), str(msg.header.frame_id), str(msg.encoding),
            False, int(msg.width), int(msg.height), int(msg.step), bool(msg.is_bigendian),
            msg.data,
        )  # fmt: skip
    if kind == COMPRESSED:
        return ImageMessage(
            _ros_stamp(msg.header, log_time_ns), str(msg.header.frame_id), str(msg.format),
            True, data=msg.data,
        )  # fmt: skip
    if kind == CAMERA_INFO:
        K = msg.k if hasattr(msg, "k") else msg.K
        D = msg.d if hasattr(msg, "d") else msg.D
        return CameraMessage(
            str(msg.header.frame_id), int(msg.width), int(msg.height),
            tuple(float(v) for v in K), str(msg.distortion_model), tuple(float(v) for v in D),
        )  # fmt: skip
    transforms = []
    for t in msg.transforms:
        r, p = t.transform.rotation, t.transform.translation
        transforms.append(
            TransformMessage(
                _ros_stamp(t.header, log_time_ns), str(t.header.frame_id).lstrip("/"),
                str(t.child_frame_id).lstrip("/"),
                _transform([p.x, p.y, p.z], [r.w, r.x, r.y, r.z]), static,
            )
        )  # fmt: skip
    return transforms


def _transform(translation: Sequence[float], q_wxyz: Sequence[float]) -> np.ndarray:
    """[4, 4] from a translation and a (not necessarily unit) quaternion w, x, y, z."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not (math.isfinite(norm) and norm > 1e-6) or not np.all(np.isfinite(translation)):
        raise DatasetError("a /tf transform has a zero or non-finite rotation or translation")
    return make_transform(quat_to_rotmat(q / norm), np.asarray(translation, dtype=np.float64))


def _from_foxglove(schema: str, data: bytes, log_time_ns: int, static: bool) -> Any:
    """The message of a protobuf-encoded Foxglove message."""
    from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
    from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    def stamp(m: Any) -> int:
        value = _ns(m.timestamp.seconds, m.timestamp.nanos)
        return value if value > 0 else log_time_ns

    kind = {"foxglove.RawImage": RawImage, "foxglove.CompressedImage": CompressedImage,
            "foxglove.CameraCalibration": CameraCalibration,
            "foxglove.FrameTransforms": FrameTransforms,
            "foxglove.FrameTransform": FrameTransform}[schema]  # fmt: skip
    m = kind()
    m.ParseFromString(data)
    if isinstance(m, RawImage):
        return ImageMessage(stamp(m), m.frame_id, m.encoding, False, m.width, m.height, m.step,
                            False, m.data)  # fmt: skip
    if isinstance(m, CompressedImage):
        return ImageMessage(stamp(m), m.frame_id, m.format, True, data=m.data)
    if isinstance(m, CameraCalibration):
        return CameraMessage(m.frame_id, m.width, m.height, tuple(m.K), m.distortion_model,
                             tuple(m.D))  # fmt: skip
    items = list(m.transforms) if isinstance(m, FrameTransforms) else [m]
    return [
        TransformMessage(
            stamp(t), t.parent_frame_id.lstrip("/"), t.child_frame_id.lstrip("/"),
            _transform([t.translation.x, t.translation.y, t.translation.z],
                       [t.rotation.w, t.rotation.x, t.rotation.y, t.rotation.z]),
            static,
        )
        for t in items
    ]  # fmt: skip


# ---------------------------------------------------------------------------------------------
# Containers


Locator = tuple[Any, ...]
"""Where one message is, for a container to read it again (its own terms)."""


class _Container:
    """What the sequence needs of a recording file: its topics, one pass over some topics'
    messages, and one message again by its locator."""

    kind: str
    topics: list[TopicInfo]

    def scan(self, topics: Sequence[str]) -> Iterator[tuple[str, int, Locator, Any]]:
        """(topic, log time ns, locator, message) of every message of `topics`."""
        raise NotImplementedError

    def fetch(self, locator: Locator) -> Any:
        """The message at `locator`."""
        raise NotImplementedError

    def close(self) -> None:
        """Release the files."""


class _RosbagsContainer(_Container):
    """ROS 1 and ROS 2 bags through rosbags' AnyReader."""

    def __init__(self, path: Path) -> None:
        try:
            from rosbags.highlevel import AnyReader
        except ImportError:  # pragma: no cover - a dependency of the package
            raise MissingDependencyError(
                "reading ROS bags needs rosbags: pip install rosbags"
            ) from None
        self.path = path
        self.kind = _ros_kind(path)
        with _bag_errors(path):
            self._reader = AnyReader([path])
            self._reader.open()
        try:
            with _bag_errors(path):
                _bound_ros1_chunks(self._reader)
                self._connections = {c.topic: c for c in self._reader.connections}
                self.topics = sorted(
                    (TopicInfo(c.topic, c.msgtype, _KINDS.get(c.msgtype, ""), int(c.msgcount))
                     for c in self._reader.connections),
                    key=lambda t: t.name,
                )  # fmt: skip
        except BaseException:
            self.close()
            raise

    def _decode(self, topic: str, log_time: int, raw: bytes) -> Any:
        connection = self._connections[topic]
        with _bag_errors(self.path):
            msg = self._reader.deserialize(raw, connection.msgtype)
        return _from_ros(_KINDS[connection.msgtype], msg, log_time, topic == "/tf_static")

    def scan(self, topics: Sequence[str]) -> Iterator[tuple[str, int, Locator, Any]]:
        connections = [self._connections[t] for t in topics if t in self._connections]
        if not connections:
            return
        seen: dict[tuple[str, int], int] = {}
        with _bag_errors(self.path):
            for connection, log_time, raw in self._reader.messages(connections=connections):
                key = (connection.topic, log_time)
                nth = seen[key] = seen.get(key, -1) + 1
                yield (connection.topic, log_time, (connection.topic, log_time, nth),
                       self._decode(connection.topic, log_time, raw))  # fmt: skip

    def fetch(self, locator: Locator) -> Any:
        topic, log_time, nth = locator
        with _bag_errors(self.path):
            found = self._reader.messages(
                connections=[self._connections[topic]], start=log_time, stop=log_time + 1
            )
            for k, (_connection, _time, raw) in enumerate(found):
                if k == nth:
                    return self._decode(topic, log_time, raw)
        raise DatasetError(f"{self.path}: a {topic} message at {log_time} ns is gone")

    def close(self) -> None:
        reader = getattr(self, "_reader", None)
        if reader is not None and reader.stack is not None:
            reader.close()


class _FoxgloveContainer(_Container):
    """A Foxglove-schema MCAP through the project's bounded MCAP reader; a message's locator
    is its chunk and its place among the chunk's messages of its topic."""

    kind = "Foxglove recording (MCAP)"

    def __init__(self, path: Path, reader: Any) -> None:
        self.path = path
        self._reader = reader
        if not reader.chunk_offsets and any(c.messages for c in reader.channels):
            raise DatasetError(
                f"{path}: a Foxglove MCAP without chunk indexes cannot be read frame by frame; "
                "`mcap recover` writes an indexed copy"
            )
        self._schemas = {c.topic: (c.schema, c.encoding) for c in reader.channels}
        self.topics = [
            TopicInfo(c.topic, c.schema, _KINDS.get(c.schema, ""), c.messages)
            for c in reader.channels
        ]

    def _decode(self, topic: str, log_time: int, data: bytes) -> Any:
        schema, encoding = self._schemas[topic]
        if encoding != "protobuf":
            raise DatasetError(
                f"{self.path}: {topic} is {schema} in {encoding!r}; Foxglove messages are read "
                "in protobuf"
            )
        try:
            return _from_foxglove(schema, data, log_time, topic == "/tf_static")
        except DatasetError:
            raise
        except Exception as exc:  # protobuf's DecodeError and its kin, on hostile bytes
            raise DatasetError(f"{self.path}: a {topic} message is not {schema}: {exc}") from None

    def scan(self, topics: Sequence[str]) -> Iterator[tuple[str, int, Locator, Any]]:
        wanted = [t for t in topics if t in self._schemas]
        if not wanted:
            return
        for offset in self._reader.chunk_offsets:
            counts: dict[str, int] = {}
            for _schema, channel, message in self._chunk(offset, wanted):
                nth = counts[channel.topic] = counts.get(channel.topic, -1) + 1
                yield (channel.topic, message.log_time, (offset, channel.topic, nth),
                       self._decode(channel.topic, message.log_time, message.data))  # fmt: skip

    def _chunk(self, offset: int, topics: Sequence[str]) -> list[Any]:
        try:
            return list(self._reader.chunk_messages(offset, topics))
        except GscError as exc:
            raise DatasetError(str(exc)) from None

    def fetch(self, locator: Locator) -> Any:
        offset, topic, nth = locator
        found = self._chunk(offset, [topic])
        if nth >= len(found):
            raise DatasetError(f"{self.path}: a {topic} message is gone from its chunk")
        message = found[nth][2]
        return self._decode(topic, message.log_time, message.data)

    def close(self) -> None:
        self._reader.close()


def _ros_kind(path: Path) -> str:
    """What a rosbags-read path is, in words."""
    if path.is_dir():
        storage = "MCAP" if any(path.glob("*.mcap")) else "sqlite"
        return f"ROS 2 bag ({storage})"
    return {".bag": "ROS 1 bag", ".db3": "ROS 2 bag (sqlite)"}.get(
        path.suffix.lower(), "ROS 2 bag (MCAP)"
    )


@contextmanager
def _bag_errors(path: Path) -> Iterator[None]:
    """Turn what a damaged or hostile bag makes rosbags (or what it calls) raise into one
    DatasetError line naming the file."""
    try:
        yield
    except GscError:
        raise
    except MemoryError:
        raise DatasetError(f"{path}: a record asks for more memory than there is") from None
    except Exception as exc:
        if isinstance(exc, KeyboardInterrupt):  # pragma: no cover
            raise
        text = " ".join(str(a) for a in exc.args) or type(exc).__name__
        raise DatasetError(f"{path}: not a readable recording ({clipped(text, 160)})") from None


def _open_container(path: Path) -> _Container:
    """The container of a recording, checked before any message is read (see the module
    docstring): an MCAP file is opened with the bounded reader first, and stays with it when
    it is not a ROS 2 bag."""
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            raise DatasetError(f"{path} is not a ROS 2 bag folder: it has no metadata.yaml")
        _check_bag_folder(path)
        for part in sorted(path.glob("*.mcap")):
            _checked_mcap(part).close()
        return _RosbagsContainer(path)
    if not path.is_file():
        raise DatasetError(f"recording not found: {path}")
    if path.suffix.lower() == ".mcap":
        reader = _checked_mcap(path)
        try:
            profile = reader.profile
        except GscError as exc:
            reader.close()
            raise DatasetError(str(exc)) from None
        if profile == "ros2":
            reader.close()
            return _RosbagsContainer(path)
        if _is_gsc_log(reader):
            reader.close()
            raise DatasetError(
                f"{path} is a gscompress log, not a recording: `gsc info` shows what it holds"
            )
        try:
            return _FoxgloveContainer(path, reader)
        except BaseException:
            reader.close()
            raise
    return _RosbagsContainer(path)


def _checked_mcap(path: Path) -> Any:
    """The bounded MCAP reader of `path` (summary and every chunk header checked)."""
    from gscompress.io.mcap_log import LogReader

    try:
        return LogReader(path)
    except GscError as exc:
        if "truncated" in str(exc):
            raise DatasetError(
                f"{path}: MCAP file is truncated (no footer: cut short or still being "
                "written); `mcap recover` writes a readable copy"
            ) from None
        raise DatasetError(
            str(exc).replace("not a readable MCAP log", "not a readable MCAP")
        ) from None


def _is_gsc_log(reader: Any) -> bool:
    """True when an MCAP holds a gscompress metadata record (a log, not a recording)."""
    return bool(reader.metadata.profile_version)


def _check_bag_folder(path: Path) -> None:
    """Refuse a ROS 2 bag folder that rosbags would inflate whole: compressed per file (into a
    temporary copy) or per message (without a bound)."""
    import yaml

    meta = path / "metadata.yaml"
    if meta.stat().st_size > 16 << 20:
        raise DatasetError(f"{meta}: {meta.stat().st_size} bytes is too large for bag metadata")
    try:
        data = yaml.safe_load(meta.read_text(encoding="utf-8", errors="replace"))
        info = data["rosbag2_bagfile_information"]
        mode = str(info.get("compression_mode", "") or "").lower()
    except (yaml.YAMLError, TypeError, KeyError, AttributeError) as exc:
        raise DatasetError(f"{meta}: not ROS 2 bag metadata ({clipped(str(exc), 80)})") from None
    if mode not in ("", "none"):
        raise DatasetError(
            f"{path} is compressed per {mode}; decompress it first (`ros2 bag convert` to an "
            "uncompressed bag)"
        )


def _bound_ros1_chunks(reader: Any) -> None:
    """Give each chunk of a ROS 1 bag a decompressor bounded by the chunk's declared size,
    itself checked against the chunk's compressed size (`check_chunk_size`) before anything
    is inflated. rosbags inflates a chunk whole; a bomb would otherwise be inflated first."""
    from rosbags.rosbag1.reader import Header, RecordType
    from rosbags.rosbag1.reader import Reader as Reader1

    for sub in reader.readers:
        bio = sub.bio if isinstance(sub, Reader1) else None
        if bio is None:
            continue
        for info in sub.chunk_infos:
            bio.seek(info.pos)
            header = Header.read(bio, RecordType.CHUNK)
            size, compression = header.get_uint32("size"), header.get_string("compression")
            chunk = sub.chunks[info.pos]
            check_chunk_size(size, chunk.datasize, compression, str(sub.path))
            sub.chunks[info.pos] = chunk._replace(
                decompressor=_bounded_inflate(compression, size, str(sub.path))
            )


def check_chunk_size(size: int, compressed: int, compression: str, source: str) -> None:
    """Refuse a ROS 1 chunk that declares more than the decode budget of an MCAP chunk allows
    (`gscompress.io.decode_budget`, format `mcap-chunk`), before it is inflated."""
    from gscompress.io.decode_budget import DecodeBudget
    from gscompress.io.mcap_bounds import MAX_CHUNK_BYTES

    if compression == "none" and size != compressed:
        raise DatasetError(f"{source}: a chunk of {compressed} bytes claims {size} uncompressed")
    if size > MAX_CHUNK_BYTES:
        raise DatasetError(
            f"{source}: a chunk of {compressed} bytes claims {size} bytes uncompressed, more "
            f"than the {MAX_CHUNK_BYTES >> 30} GiB a chunk may hold"
        )
    budget = DecodeBudget("mcap-chunk", compressed, source, DatasetError)
    budget.check(size, f"a chunk of {compressed} bytes claims {size} bytes uncompressed")


def _bounded_inflate(compression: str, size: int, source: str) -> Callable[[bytes], bytes]:
    """A decompressor that stops at `size` + 1 bytes and refuses anything but `size`."""

    def inflate(data: bytes) -> bytes:
        if compression == "none":
            out = bytes(data)
        elif compression == "bz2":
            d = bz2.BZ2Decompressor()
            try:
                out = d.decompress(data, max_length=size + 1)
            except (OSError, ValueError) as exc:
                raise DatasetError(f"{source}: a chunk's bz2 data is corrupt ({exc})") from None
        elif compression == "lz4":
            from gscompress.io.decode_budget import inflate_lz4

            out = inflate_lz4(data, size, f"{source}: a chunk's lz4 data", DatasetError)
        else:
            raise DatasetError(f"{source}: a chunk is compressed with unknown {compression!r}")
        if len(out) != size:
            raise DatasetError(f"{source}: a chunk inflates to other than its declared {size} B")
        return out

    return inflate


# ---------------------------------------------------------------------------------------------
# Decoding, bounded: sizes and headers checked before pixels


def _raw_pixels(msg: ImageMessage, dtype: np.dtype, channels: int, what: str) -> np.ndarray:
    """[H, W, C] of a raw image, its size, step and byte count checked first."""
    w, h = msg.width, msg.height
    check_image_size(w, h, what)
    row = w * channels * dtype.itemsize
    data = memoryview(msg.data).cast("B") if not isinstance(msg.data, np.ndarray) else msg.data
    if msg.step < row or len(data) < msg.step * (h - 1) + row:
        raise DatasetError(
            f"{what}: a {w}x{h} {msg.encoding} image with step {msg.step} holds {len(data)} bytes"
        )
    buf = np.frombuffer(data, dtype=np.uint8, count=msg.step * (h - 1) + row)
    rows = np.lib.stride_tricks.as_strided(buf, (h, row), (msg.step, 1))
    if dtype.itemsize > 1:
        dtype = dtype.newbyteorder(">" if msg.big_endian else "<")
    pixels = np.ascontiguousarray(rows).view(dtype)
    return pixels.reshape(h, w, channels)


def check_image_size(width: int, height: int, what: str) -> None:
    """Refuse an image size of zero or beyond `MAX_SIDE` (before its pixels are touched)."""
    if not (0 < width <= MAX_SIDE and 0 < height <= MAX_SIDE):
        raise DatasetError(f"{what}: image size {width}x{height} is outside 1..{MAX_SIDE}")


def check_compressed_payload(data: Any, width: int, height: int, what: str) -> None:
    """Refuse a compressed image of more bytes than `MAX_COMPRESSED_RATIO` times its raw
    pixels at the expected size (a later call into the shared decode budget)."""
    limit = MAX_COMPRESSED_RATIO * width * height * 4 + _COMPRESSED_SLACK
    if len(data) > limit:
        raise DatasetError(f"{what}: a compressed image of {len(data)} bytes for {width}x{height}")


def open_image_header(data: Any, expected: tuple[int, int], what: str) -> Image.Image:
    """A PNG or JPEG opened lazily, its header's size checked against `expected` (W, H)
    before any pixel is decoded; the caller loads it."""
    check_compressed_payload(data, *expected, what)
    try:
        img = Image.open(io.BytesIO(bytes(data)), formats=["PNG", "JPEG"])
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise DatasetError(f"{what}: not a PNG or JPEG image ({clipped(str(exc), 80)})") from None
    if img.size != expected:
        raise DatasetError(
            f"{what}: image is {img.size[0]}x{img.size[1]} but the camera info says "
            f"{expected[0]}x{expected[1]}"
        )
    return img


def _load(img: Image.Image, what: str) -> Image.Image:
    try:
        img.load()
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise DatasetError(f"{what}: cannot decode the image ({clipped(str(exc), 80)})") from None
    return img


def decode_color(msg: ImageMessage, expected: tuple[int, int], what: str) -> np.ndarray:
    """[H, W, 3] float32 in [0, 1] of a colour message of size `expected` (W, H)."""
    if msg.compressed:
        if "compresseddepth" in msg.encoding.lower():
            raise DatasetError(f"{what}: a compressedDepth image on the colour topic")
        with open_image_header(msg.data, expected, what) as img:
            _load(img, what)
            if img.mode != "RGB":
                if img.mode not in ("L", "P", "RGBA", "LA", "CMYK", "YCbCr"):
                    raise DatasetError(f"{what}: colour image of mode {img.mode}")
                img = img.convert("RGB")
            rgb8 = np.asarray(img, dtype=np.uint8)
        return color_from_uint8(rgb8)
    found = COLOR_ENCODINGS.get(msg.encoding)
    if found is None:
        raise DatasetError(
            f"{what}: colour encoding {clipped(msg.encoding)} is not one of "
            f"{', '.join(COLOR_ENCODINGS)} (or JPEG / PNG)"
        )
    _check_expected(msg, expected, what)
    channels, pick = found
    pixels = _raw_pixels(msg, np.dtype("u1"), channels, what)
    return color_from_uint8(np.ascontiguousarray(pixels[..., list(pick)]))


def _check_expected(msg: ImageMessage, expected: tuple[int, int], what: str) -> None:
    if (msg.width, msg.height) != expected:
        raise DatasetError(
            f"{what}: image is {msg.width}x{msg.height} but the camera info says "
            f"{expected[0]}x{expected[1]}"
        )


def decode_depth(msg: ImageMessage, expected: tuple[int, int], what: str) -> np.ndarray:
    """[H, W] float32 metres (0 = no depth) of a depth message of size `expected` (W, H)."""
    if msg.compressed:
        return _decode_compressed_depth(msg, expected, what)
    dtype = DEPTH_ENCODINGS.get(msg.encoding)
    if dtype is None:
        raise DatasetError(
            f"{what}: depth encoding {clipped(msg.encoding)} is not 16UC1 (millimetres) or "
            "32FC1 (metres)"
        )
    _check_expected(msg, expected, what)
    raw = _raw_pixels(msg, dtype, 1, what)[..., 0]
    if dtype.kind == "u":
        return depth_from_units(raw.astype(np.uint16), MM_PER_METRE, DEFAULT_INVALID_DEPTH)
    return metres_depth(raw)


def metres_depth(raw: np.ndarray) -> np.ndarray:
    """float32 metres with 0, negative and non-finite values read as no depth (0)."""
    depth = raw.astype(np.float32)
    depth[~(np.isfinite(depth) & (depth > 0))] = 0.0
    return depth


def _decode_compressed_depth(msg: ImageMessage, expected: tuple[int, int], what: str) -> np.ndarray:
    """compressedDepth (header + PNG) or a plain 16-bit PNG of millimetres."""
    fmt = msg.encoding.lower()
    data = bytes(msg.data)
    inverse: tuple[float, float] | None = None
    if "compresseddepth" in fmt:
        if "rvl" in fmt:
            raise DatasetError(f"{what}: compressedDepth RVL is not read; record it as PNG")
        if len(data) < _COMPRESSED_DEPTH_HEADER:
            raise DatasetError(f"{what}: a compressedDepth message of {len(data)} bytes")
        _fmt, quant_a, quant_b = struct.unpack_from("<iff", data)
        data = data[_COMPRESSED_DEPTH_HEADER:]
        if fmt.split(";")[0].strip().upper() == "32FC1":
            inverse = (quant_a, quant_b)
    elif "png" not in fmt:
        raise DatasetError(f"{what}: compressed depth of format {clipped(msg.encoding)}: PNG only")
    with open_image_header(data, expected, what) as img:
        if img.format != "PNG" or img.mode not in ("I;16", "I;16B", "I;16L", "I"):
            raise DatasetError(f"{what}: compressed depth must be a 16-bit PNG, got {img.mode}")
        raw = np.asarray(_load(img, what))
    if raw.min(initial=0) < 0 or raw.max(initial=0) > 65535:
        raise DatasetError(f"{what}: depth values outside 0..65535")
    raw16 = raw.astype(np.uint16)
    if inverse is None:
        return depth_from_units(raw16, MM_PER_METRE, DEFAULT_INVALID_DEPTH)
    # image_transport's quantised inverse depth: depth = A / (v - B), v = 0 for none
    a, b = inverse
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.float32(a) / (raw16.astype(np.float32) - np.float32(b))
    depth[raw16 == 0] = 0.0
    return metres_depth(depth)


def intrinsics_of(info: CameraMessage, topic: str) -> Intrinsics:
    """Pinhole intrinsics of a camera info, refusing a distortion this reader does not undo."""
    what = f"camera info {topic}"
    check_image_size(info.width, info.height, what)
    if len(info.K) != 9 or not all(math.isfinite(v) for v in info.K):
        raise DatasetError(f"{what}: K must be 9 finite numbers")
    fx, _, cx, _, fy, cy, *_ = info.K
    if min(fx, fy) < 1:
        raise DatasetError(f"{what}: fx and fy must be at least 1 pixel, got {fx}, {fy}")
    model = info.model.strip().lower()
    if any(v != 0 for v in info.D) or model not in UNDISTORTED_MODELS:
        raise DatasetError(
            f"{what}: distortion {clipped(info.model)} with coefficients {clipped(list(info.D))} "
            "is not undone here; record rectified images (zero coefficients are fine)"
        )
    return Intrinsics(float(fx), float(fy), float(cx), float(cy), info.width, info.height)


# ---------------------------------------------------------------------------------------------
# Topic choice


@dataclass(frozen=True)
class TopicChoice:
    """The topics a sequence is read from, and why (`reason`)."""

    rgb: str
    depth: str
    camera_info: str
    reason: str


def _base(topic: str) -> str:
    """A topic without image_transport's suffix."""
    for suffix in _TRANSPORTS:
        if topic.endswith(suffix):
            return topic[: -len(suffix)]
    return topic


def _is_depth_name(topic: str) -> bool:
    return "depth" in topic.lower()


def image_topics(topics: Sequence[TopicInfo]) -> dict[str, str]:
    """{base topic: the topic read for it} of the image topics, raw preferred to compressed."""
    chosen: dict[str, str] = {}
    for t in sorted(topics, key=lambda t: (t.kind != IMAGE, t.name)):
        if t.kind in (IMAGE, COMPRESSED) and t.count > 0:
            chosen.setdefault(_base(t.name), t.name)
    return chosen


def choose_topics(
    topics: Sequence[TopicInfo], options: RecordingOptions, source: str
) -> TopicChoice:
    """The colour, depth and camera-info topics (see the module docstring).

    Raises:
        DatasetError: a named topic is missing, or the choice is ambiguous (the message names
            the candidates and the flags that settle it).
    """
    by_name = {t.name: t for t in topics}
    for flag, topic in (("--rgb", options.rgb), ("--depth", options.depth),
                        ("--camera-info", options.camera_info)):  # fmt: skip
        if topic is not None and topic not in by_name:
            raise DatasetError(f"{source} has no topic {clipped(topic)} ({flag})")
    images = image_topics(topics)
    colours = sorted(v for k, v in images.items() if not _is_depth_name(k))
    depths = sorted(v for k, v in images.items() if _is_depth_name(k))
    rgb, depth, reason = options.rgb, options.depth, "given"
    if rgb is None or depth is None:
        known = [(name, c, d) for name, c, d in KNOWN_PAIRS
                 if c in images and d in images and rgb in (None, images[c])
                 and depth in (None, images[d])]  # fmt: skip
        if known:
            name, c, d = known[0]
            rgb, depth, reason = images[c], images[d], f"{name} topic names"
        else:
            rgb = rgb or _only(colours, "colour", "--rgb", source)
            depth = depth or _only(depths, "depth", "--depth", source)
            reason = "the only colour and depth topics"
    infos = sorted(t.name for t in topics if t.kind == CAMERA_INFO and t.count > 0)
    info = options.camera_info
    if info is None:
        namespace = _base(rgb).rsplit("/", 1)[0]
        siblings = [t for t in infos if t.rsplit("/", 1)[0] == namespace]
        if len(siblings) == 1:
            info = siblings[0]
        elif len(infos) == 1:
            info = infos[0]
        elif not infos:
            raise DatasetError(
                f"{source} has no camera info (CameraInfo / CameraCalibration) for {rgb}: the "
                "intrinsics are unknown"
            )
        else:
            info = _only([], "camera info", "--camera-info", source, infos)
    for topic, kind in ((rgb, "colour"), (depth, "depth")):
        if by_name[topic].kind not in (IMAGE, COMPRESSED):
            raise DatasetError(f"{source}: {topic} is {by_name[topic].msgtype}, not a {kind} image")
    if by_name[info].kind != CAMERA_INFO:
        raise DatasetError(f"{source}: {info} is {by_name[info].msgtype}, not a camera info")
    return TopicChoice(rgb, depth, info, reason)


def _only(
    candidates: Sequence[str], what: str, flag: str, source: str, listed: Sequence[str] = ()
) -> str:
    """The one candidate; else a DatasetError naming them (or saying there are none)."""
    if len(candidates) == 1:
        return candidates[0]
    shown = list(listed or candidates)
    if not shown:
        raise DatasetError(f"{source} has no {what} image topic")
    raise DatasetError(
        f"{source}: which {what} topic? candidates: {', '.join(shown)}; pass {flag} TOPIC"
    )


def registered(depth_topic: str, depth: ImageMessage, color: ImageMessage,
               size: tuple[int, int] | None) -> bool:  # fmt: skip
    """Whether depth is registered to colour: by its topic's name, or by the same frame id
    and size (`size` the depth image's, None when compressed and not yet known)."""
    if any(mark in depth_topic for mark in REGISTERED_MARKS) or _base(depth_topic) in (
        d for _, _, d in KNOWN_PAIRS
    ):
        return True
    same_size = size is None or color.compressed or size == (color.width, color.height)
    return bool(depth.frame_id) and depth.frame_id == color.frame_id and same_size


# ---------------------------------------------------------------------------------------------
# Ground truth from /tf


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
    """T_world_camera at each stamp from tf samples (see the module docstring), None where a
    link of the chain has no sample on both sides of the stamp.

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


# ---------------------------------------------------------------------------------------------
# The sequence


@dataclass(frozen=True)
class _Pair:
    """One frame: colour and depth message locators, and the colour stamp."""

    stamp_ns: int
    color: Locator
    depth: Locator


class RecordingSequence:
    """An `RGBDSequence` over a recording; frames are decoded on demand (see the module
    docstring). `skipped` counts the colour and depth messages left without a partner."""

    def __init__(
        self,
        path: Path,
        container: _Container,
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
    """Open a recording as a sequence (see the module docstring).

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
    container = _open_container(path)
    try:
        return _build(path, container, selection, size, intrinsics, options)
    except BaseException:
        container.close()
        raise


def _build(
    path: Path,
    container: _Container,
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
            f"{choice.depth}); --max-dt widens it"
        )
    pairs = [_Pair(colors[i][0], colors[i][1], depths[j][1]) for i, j in pairs_ij]
    skipped = {"rgb": len(colors) - len(pairs), "depth": len(depths) - len(pairs)}
    if skipped["rgb"] or skipped["depth"]:
        log.info(
            "%s: %d frames paired; skipped %d colour and %d depth messages without a partner "
            "within %g s", path, len(pairs), skipped["rgb"], skipped["depth"], options.max_dt,
        )  # fmt: skip
    stamps = [p.stamp_ns for p in pairs]
    poses = _ground_truth(container, options, stamps, str(path))
    return RecordingSequence(path, container, choice, pairs, native, poses, selection, size,
                             skipped)  # fmt: skip


def _scan(container: _Container, choice: TopicChoice) -> dict[str, Any]:
    """One pass over the chosen topics: (stamp, locator, first message) of colour and depth,
    sorted by stamp, and the first camera info."""
    found: dict[str, Any] = {"rgb": [], "depth": [], "info": None}
    keys = {choice.rgb: "rgb", choice.depth: "depth"}
    for topic, _log_time, locator, msg in container.scan([choice.rgb, choice.depth,
                                                          choice.camera_info]):  # fmt: skip
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
    container: _Container, options: RecordingOptions, stamps_ns: Sequence[int], source: str
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
            raise DatasetError(f"{source} has no /tf message for --gt-frames")
        return tf_poses(transforms, *options.gt_frames, stamps_ns)
    return [None] * len(stamps_ns)


# ---------------------------------------------------------------------------------------------
# What a recording holds (gsc info)


def describe_recording(path: Path, options: RecordingOptions | None = None) -> dict[str, Any]:
    """What `gsc info` shows of a recording: its kind, every topic with its count, and for
    image and camera-info topics the size, encoding and rate; the pair `gsc slam` would take
    (or why it would take none). Reads the image topics once."""
    options = options or RecordingOptions()
    container = _open_container(path)
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
            row: dict[str, Any] = {"topic": t.name, "type": t.msgtype, "kind": t.kind or "other",
                                   "messages": t.count}  # fmt: skip
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
            result["why_not"] = str(exc)
        else:
            c = sequence.choice
            result["slam_would_read"] = {
                "rgb": c.rgb, "depth": c.depth, "camera_info": c.camera_info,
                "chosen_by": c.reason, "frames": len(sequence._pairs),
                "skipped": sequence.skipped, "max_dt": options.max_dt,
                "size": [sequence.native_intrinsics.width, sequence.native_intrinsics.height],
            }  # fmt: skip
        return result
    finally:
        container.close()


def _sample_fields(msg: Any) -> dict[str, Any]:
    """Size and encoding of a topic's first message, for `describe_recording`."""
    if isinstance(msg, ImageMessage):
        if msg.compressed:
            return {"encoding": msg.encoding, "size": None, "frame_id": msg.frame_id}
        return {"encoding": msg.encoding, "size": [msg.width, msg.height],
                "frame_id": msg.frame_id}  # fmt: skip
    if isinstance(msg, CameraMessage):
        return {"size": [msg.width, msg.height], "frame_id": msg.frame_id,
                "distortion": msg.model}  # fmt: skip
    return {}


def with_topics(options: RecordingOptions, choice: TopicChoice) -> RecordingOptions:
    """`options` with the topics a sequence was read from (what a log records of its run)."""
    return replace(options, rgb=choice.rgb, depth=choice.depth, camera_info=choice.camera_info)
