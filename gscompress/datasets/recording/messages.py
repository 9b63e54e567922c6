"""The messages of a recording as every container gives them: images not yet decoded, camera
infos, /tf transforms and topics, made from rosbags' ROS messages or Foxglove protobuf; stamps
in integer nanoseconds."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import numpy as np

from gscompress.camera import make_transform, quat_to_rotmat
from gscompress.errors import DatasetError

# message kinds, from ROS type names and Foxglove schema names
IMAGE, COMPRESSED, CAMERA_INFO, TF = "image", "compressed", "camera_info", "tf"
KINDS = {
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
"""The kind of each message type read (ROS type or Foxglove schema)."""


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


def from_ros(kind: str, msg: Any, log_time_ns: int, static: bool) -> Any:
    """The message of a rosbags-deserialised ROS message of `kind` (a list of transforms for
    /tf)."""
    if kind == IMAGE:
        return ImageMessage(
            _ros_stamp(msg.header, log_time_ns),
            str(msg.header.frame_id),
            str(msg.encoding),
            False,
            int(msg.width),
            int(msg.height),
            int(msg.step),
            bool(msg.is_bigendian),
            msg.data,
        )
    if kind == COMPRESSED:
        return ImageMessage(
            _ros_stamp(msg.header, log_time_ns),
            str(msg.header.frame_id),
            str(msg.format),
            True,
            data=msg.data,
        )
    if kind == CAMERA_INFO:
        K = msg.k if hasattr(msg, "k") else msg.K
        D = msg.d if hasattr(msg, "d") else msg.D
        return CameraMessage(
            str(msg.header.frame_id),
            int(msg.width),
            int(msg.height),
            tuple(float(v) for v in K),
            str(msg.distortion_model),
            tuple(float(v) for v in D),
        )
    transforms = []
    for t in msg.transforms:
        r, p = t.transform.rotation, t.transform.translation
        transforms.append(
            TransformMessage(
                _ros_stamp(t.header, log_time_ns),
                str(t.header.frame_id).lstrip("/"),
                str(t.child_frame_id).lstrip("/"),
                _transform([p.x, p.y, p.z], [r.w, r.x, r.y, r.z]),
                static,
            )
        )
    return transforms


def _transform(translation: Sequence[float], q_wxyz: Sequence[float]) -> np.ndarray:
    """[4, 4] from a translation and a (not necessarily unit) quaternion w, x, y, z."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not (math.isfinite(norm) and norm > 1e-6) or not np.all(np.isfinite(translation)):
        raise DatasetError("a /tf transform has a zero or non-finite rotation or translation")
    return make_transform(quat_to_rotmat(q / norm), np.asarray(translation, dtype=np.float64))


def from_foxglove(schema: str, data: bytes, log_time_ns: int, static: bool) -> Any:
    """The message of a protobuf-encoded Foxglove message of `schema` (a list of transforms
    for a FrameTransform(s))."""
    from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
    from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    def stamp(m: Any) -> int:
        value = _ns(m.timestamp.seconds, m.timestamp.nanos)
        return value if value > 0 else log_time_ns

    kind = {
        "foxglove.RawImage": RawImage,
        "foxglove.CompressedImage": CompressedImage,
        "foxglove.CameraCalibration": CameraCalibration,
        "foxglove.FrameTransforms": FrameTransforms,
        "foxglove.FrameTransform": FrameTransform,
    }[schema]
    m = kind()
    m.ParseFromString(data)
    if isinstance(m, RawImage):
        return ImageMessage(
            stamp(m), m.frame_id, m.encoding, False, m.width, m.height, m.step, False, m.data
        )
    if isinstance(m, CompressedImage):
        return ImageMessage(stamp(m), m.frame_id, m.format, True, data=m.data)
    if isinstance(m, CameraCalibration):
        return CameraMessage(
            m.frame_id, m.width, m.height, tuple(m.K), m.distortion_model, tuple(m.D)
        )
    items = list(m.transforms) if isinstance(m, FrameTransforms) else [m]
    return [
        TransformMessage(
            stamp(t),
            t.parent_frame_id.lstrip("/"),
            t.child_frame_id.lstrip("/"),
            _transform(
                [t.translation.x, t.translation.y, t.translation.z],
                [t.rotation.w, t.rotation.x, t.rotation.y, t.rotation.z],
            ),
            static,
        )
        for t in items
    ]
