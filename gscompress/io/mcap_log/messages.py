"""The profile's messages: a map as a `/gaussians` message in a codec of `gscompress.io.codec`
(a foxglove.PointCloud, or the compact message) and back, and poses as foxglove.PoseInFrame and
back.

Decoding treats every message as untrusted: layouts, sizes and values are checked before a map
is built.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from google.protobuf.message import DecodeError, Message
from mcap.records import Message as McapMessage
from mcap.records import Schema

from gscompress.camera import is_zero_quaternion, make_transform, quat_to_rotmat, rotmat_to_quat
from gscompress.errors import LogFormatError, MapError, led_by
from gscompress.gaussians import GaussianMap
from gscompress.io.codec import (
    DEFAULT_CODEC,
    MAP_SCHEMAS,
    decoder,
    get_codec,
    pointcloud_half,
)
from gscompress.io.compact import COMPACT_DEFAULTS, CompactOptions
from gscompress.io.decode_budget import DecodeBudget
from gscompress.io.mcap_log.metadata import TOPIC_GAUSSIANS, WORLD_FRAME
from gscompress.io.pointcloud import (
    encode_pointcloud,
    pointcloud_size,
    record_bytes,
)


def gaussians_to_pointcloud(
    gaussians: GaussianMap, timestamp_ns: int = 0, precision: str = DEFAULT_CODEC
) -> PointCloud:
    """A map as the `/gaussians` foxglove.PointCloud of the codec `precision` (fp32, or fp16 to
    store the bounded attributes as float16; see `gscompress.io.pointcloud`).

    Raises:
        InputError: not a PointCloud codec.
        MapError: at fp16, a value beyond the float16 range.
    """
    return encode_pointcloud(gaussians, timestamp_ns, pointcloud_half(precision), WORLD_FRAME)


def record_size(gaussians: GaussianMap, precision: str = DEFAULT_CODEC) -> int:
    """Bytes per Gaussian in a `/gaussians` PointCloud of this map (its point_stride)."""
    return record_bytes(gaussians, pointcloud_half(precision))


def pointcloud_bytes(
    gaussians: GaussianMap, precision: str = DEFAULT_CODEC, timestamp_ns: int = 0
) -> Callable[[int], int]:
    """Exact serialized size of the `/gaussians` message holding K Gaussians of this map's layout.

    Returns:
        A function K -> bytes of `gaussians_to_pointcloud(m, timestamp_ns, precision)` for any
        map m of K Gaussians with this layout (SH degree, score columns).
    """
    return pointcloud_size(gaussians, pointcloud_half(precision), timestamp_ns, WORLD_FRAME)


def encode_map(
    gaussians: GaussianMap,
    codec: str = DEFAULT_CODEC,
    timestamp_ns: int = 0,
    options: CompactOptions = COMPACT_DEFAULTS,
) -> Message:
    """The `/gaussians` message of a map in `codec` (`gscompress.io.codec`; `options` for a
    codec that does not carry everything, compact).

    Raises:
        InputError: an unknown codec.
        MapError: at fp16, a value beyond the float16 range.
    """
    return get_codec(codec).encode(gaussians, timestamp_ns, options, WORLD_FRAME)


def decoded_map(
    gaussians: GaussianMap, codec: str = DEFAULT_CODEC, *, sums: bool = True
) -> GaussianMap:
    """The map a receiver decodes from `gaussians` sent in `codec` (with or without the PWAS
    sums at compact): what a share's picture is judged by."""
    if get_codec(codec).lossless:
        return gaussians
    message = encode_map(gaussians, codec, 0, CompactOptions(sums=sums))
    return decode_map_message(message.SerializeToString(), get_codec(codec).schema)[0]


def decode_map_message(
    data: bytes, schema: str, source: str = "map", budget: DecodeBudget | None = None
) -> tuple[GaussianMap, str]:
    """The validated map of a serialized `/gaussians` message of schema `schema` and the codec
    it was stored in.

    Args:
        budget: what the file holding the message may decode to (None: the message's own
            bounds only); the map its header declares is checked against it before decoding.

    Raises:
        DecodeError: not such a protobuf message.
        MapError: a schema no codec writes, a malformed map, or one over `budget`.
    """
    return decoder(schema, source)(data, source, budget)


def encoded_size(
    gaussians: GaussianMap, codec: str = DEFAULT_CODEC, options: CompactOptions = COMPACT_DEFAULTS
) -> int:
    """Bytes of the `/gaussians` message of a map in `codec` (see `encode_map`)."""
    return encode_map(gaussians, codec, 0, options).ByteSize()


def decode_snapshot(
    schema: Schema | None,
    message: McapMessage,
    source: str = "log",
    budget: DecodeBudget | None = None,
) -> Snapshot:
    """Decode one `/gaussians` message (a record of any reader) into a validated map, within
    `budget` (what the file holding it may decode to; see `decode_map_message`).

    Raises:
        LogFormatError: not a protobuf foxglove.PointCloud or gscompress.CompactGaussians,
            corrupt, a malformed map, or one over budget.
    """
    if schema is None or schema.name not in MAP_SCHEMAS or schema.encoding != "protobuf":
        name = schema.name if schema else "no schema"
        raise LogFormatError(
            f"{source}: {TOPIC_GAUSSIANS} is {name}, not {' or '.join(MAP_SCHEMAS)}"
        )
    try:
        gaussians, codec = decode_map_message(message.data, schema.name, source, budget)
    except DecodeError:
        raise LogFormatError(f"{source}: a corrupt {TOPIC_GAUSSIANS} message") from None
    except MapError as exc:
        raise LogFormatError(led_by(source, str(exc))) from None
    return Snapshot(
        gaussians=gaussians,
        log_time_ns=message.log_time,
        message_bytes=len(message.data),
        codec=codec,
    )


def pose_message(T_world_cam: np.ndarray, log_time_ns: int) -> PoseInFrame:
    """A camera-to-world pose as a foxglove.PoseInFrame in the world frame."""
    T = np.asarray(T_world_cam, dtype=np.float64)
    msg = PoseInFrame(frame_id=WORLD_FRAME)
    msg.timestamp.FromNanoseconds(log_time_ns)
    set_pose(msg.pose.position, msg.pose.orientation, T[:3, 3], rotmat_to_quat(T[:3, :3]))
    return msg


def decode_pose(schema: Schema | None, message: McapMessage, source: str = "log") -> np.ndarray:
    """[4, 4] camera-to-world of a foxglove.PoseInFrame message.

    Raises:
        LogFormatError: not a PoseInFrame, corrupt, or a non-finite or zero-length pose.
    """
    where = f"{source}: message at {message.log_time} ns"
    if schema is None or schema.name != "foxglove.PoseInFrame":
        raise LogFormatError(f"{where} is {schema.name if schema else 'schemaless'}, not a pose")
    try:
        pose = PoseInFrame.FromString(message.data).pose
    except DecodeError:
        raise LogFormatError(f"{where} is a corrupt PoseInFrame") from None
    p, o = pose.position, pose.orientation
    q = np.array([o.w, o.x, o.y, o.z])
    t = np.array([p.x, p.y, p.z])
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t))) or is_zero_quaternion(q):
        raise LogFormatError(f"{where} has a non-finite or zero-length pose")
    return make_transform(quat_to_rotmat(q), t)


def trajectory_message(T_world_cam: np.ndarray, log_time_ns: int) -> PosesInFrame:
    """Camera-to-world poses [N, 4, 4] as one foxglove.PosesInFrame in the world frame (drawn
    as a path in Foxglove)."""
    msg = PosesInFrame(frame_id=WORLD_FRAME)
    msg.timestamp.FromNanoseconds(log_time_ns)
    for T in np.asarray(T_world_cam, dtype=np.float64).reshape(-1, 4, 4):
        pose = msg.poses.add()
        set_pose(pose.position, pose.orientation, T[:3, 3], rotmat_to_quat(T[:3, :3]))
    return msg


def decode_trajectory(
    schema: Schema | None, message: McapMessage, source: str = "log"
) -> np.ndarray:
    """[N, 4, 4] camera-to-world poses of a foxglove.PosesInFrame message.

    Raises:
        LogFormatError: not a PosesInFrame, corrupt, or a non-finite or zero-length pose.
    """
    where = f"{source}: message at {message.log_time} ns"
    if schema is None or schema.name != "foxglove.PosesInFrame":
        raise LogFormatError(f"{where} is {schema.name if schema else 'schemaless'}, not poses")
    try:
        poses = PosesInFrame.FromString(message.data).poses
    except DecodeError:
        raise LogFormatError(f"{where} is a corrupt PosesInFrame") from None
    out = np.empty((len(poses), 4, 4))
    for k, pose in enumerate(poses):
        p, o = pose.position, pose.orientation
        q, t = np.array([o.w, o.x, o.y, o.z]), np.array([p.x, p.y, p.z])
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t))) or is_zero_quaternion(q):
            raise LogFormatError(f"{where} has a non-finite or zero-length pose (its {k + 1}.)")
        out[k] = make_transform(quat_to_rotmat(q), t)
    return out


def set_pose(position: Any, orientation: Any, t: np.ndarray, q_wxyz: np.ndarray) -> None:
    position.x, position.y, position.z = (float(v) for v in t)
    orientation.w, orientation.x, orientation.y, orientation.z = (float(v) for v in q_wxyz)


@dataclass(frozen=True)
class Snapshot:
    """One decoded `/gaussians` message.

    Attributes:
        gaussians: the map (float32 whatever the codec).
        log_time_ns: the message's log time.
        message_bytes: bytes of the serialized message.
        codec: how it was stored (`gscompress.io.codec.CODECS`).
    """

    gaussians: GaussianMap
    log_time_ns: int
    message_bytes: int
    codec: str

    @property
    def bytes_per_gaussian(self) -> float | None:
        """Message bytes per Gaussian (None for an empty map)."""
        return self.message_bytes / len(self.gaussians) if len(self.gaussians) else None
