"""The profile's messages: a map as a `/gaussians` message (foxglove.PointCloud, or the compact
message of `gscompress.io.codec`) and back, and poses as foxglove.PoseInFrame and back.

Decoding treats every message as untrusted: layouts, sizes and values are checked before a map
is built.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from google.protobuf.message import DecodeError, Message
from mcap.records import Message as McapMessage
from mcap.records import Schema

from gscompress.camera import is_zero_quaternion, make_transform, quat_to_rotmat, rotmat_to_quat
from gscompress.errors import LogFormatError, MapError, led_by
from gscompress.gaussians import SH_REST_COUNTS, GaussianMap
from gscompress.io.codec import (
    COMPACT_DEFAULTS,
    COMPACT_SCHEMA,
    CompactGaussians,
    CompactOptions,
    check_codec,
    decode_compact,
    encode_compact,
)
from gscompress.io.columns import (
    column_dtypes,
    columns_precision,
    decode_columns,
    encode_columns,
    map_from_columns,
    map_to_columns,
    pack_records,
)
from gscompress.io.decode_budget import DecodeBudget
from gscompress.io.mcap_log.metadata import TOPIC_GAUSSIANS, WORLD_FRAME

# foxglove.PackedElementField.NumericType values and their numpy equivalents
_NUMERIC_TYPES: dict[int, np.dtype] = {
    1: np.dtype("u1"),
    2: np.dtype("i1"),
    3: np.dtype("<u2"),
    4: np.dtype("<i2"),
    5: np.dtype("<u4"),
    6: np.dtype("<i4"),
    7: np.dtype("<f4"),
    8: np.dtype("<f8"),
}
_NUMERIC_CODES = {dtype: code for code, dtype in _NUMERIC_TYPES.items()}


def gaussians_to_pointcloud(
    gaussians: GaussianMap, timestamp_ns: int = 0, precision: str = "fp32"
) -> PointCloud:
    """A foxglove.PointCloud holding every field of a map as packed little-endian records.

    Args:
        gaussians: the map.
        timestamp_ns: the cloud's timestamp.
        precision: "fp32", or "fp16" to store the bounded attributes as float16 (positions,
            scores and sums stay float32; see `gscompress.io.columns`).

    Raises:
        MapError: at fp16, a value beyond the float16 range.
    """
    cols = encode_columns(map_to_columns(gaussians), precision)
    records = pack_records(cols, column_dtypes(cols))
    layout: dict[str, Any] = dict(records.dtype.fields or {})
    fields = [
        PackedElementField(name=name, offset=spec[1], type=_NUMERIC_CODES[spec[0]])  # type: ignore[arg-type]
        for name, spec in layout.items()
    ]
    msg = PointCloud(
        frame_id=WORLD_FRAME,
        point_stride=records.dtype.itemsize,
        fields=fields,
        data=records.tobytes(),
    )
    msg.timestamp.FromNanoseconds(timestamp_ns)
    msg.pose.orientation.w = 1.0
    return msg


def record_size(gaussians: GaussianMap, precision: str = "fp32") -> int:
    """Bytes per Gaussian in a `/gaussians` PointCloud of this map (its point_stride)."""
    cols = encode_columns(map_to_columns(gaussians.select(slice(0, 0))), precision)
    return sum(dtype.itemsize for dtype in column_dtypes(cols).values())


def pointcloud_bytes(
    gaussians: GaussianMap, precision: str = "fp32", timestamp_ns: int = 0
) -> Callable[[int], int]:
    """Exact serialized size of the `/gaussians` message holding K Gaussians of this map's layout.

    The message is a header that depends only on the layout (fields, stride, frame, pose,
    timestamp) plus the `data` bytes field: its tag, the varint of its length, and K records.

    Returns:
        A function K -> bytes of `gaussians_to_pointcloud(m, timestamp_ns, precision)` for any
        map m of K Gaussians with this layout (SH degree, score columns).
    """
    header = gaussians_to_pointcloud(gaussians.select(slice(0, 0)), timestamp_ns, precision)
    header_bytes = header.ByteSize()  # proto3 leaves an empty `data` out
    stride = header.point_stride
    tag_bytes = _varint_size(PointCloud.DESCRIPTOR.fields_by_name["data"].number << 3 | 2)

    def size(count: int) -> int:
        n = count * stride
        return header_bytes + (tag_bytes + _varint_size(n) + n if n else 0)

    return size


def _varint_size(value: int) -> int:
    return max(1, (value.bit_length() + 6) // 7)


def encode_map(
    gaussians: GaussianMap,
    codec: str = "fp32",
    timestamp_ns: int = 0,
    options: CompactOptions = COMPACT_DEFAULTS,
) -> Message:
    """The `/gaussians` message of a map in `codec`: a foxglove.PointCloud (fp32, fp16) or a
    gscompress.CompactGaussians (compact, with `options`).

    Raises:
        InputError: an unknown codec.
        MapError: at fp16, a value beyond the float16 range.
    """
    if check_codec(codec) == "compact":
        return encode_compact(gaussians, options, timestamp_ns=timestamp_ns, frame_id=WORLD_FRAME)
    return gaussians_to_pointcloud(gaussians, timestamp_ns, codec)


def decoded_map(gaussians: GaussianMap, codec: str = "fp32", *, sums: bool = True) -> GaussianMap:
    """The map a receiver decodes from `gaussians` sent in `codec` (with or without the PWAS
    sums at compact): what a share's picture is judged by."""
    if codec == "fp32":
        return gaussians
    message = encode_map(gaussians, codec, 0, CompactOptions(sums=sums))
    return decode_map_message(message.SerializeToString(), codec == "compact")[0]


def decode_map_message(
    data: bytes, compact: bool, source: str = "map", budget: DecodeBudget | None = None
) -> tuple[GaussianMap, str]:
    """The validated map of a serialized `/gaussians` message (a CompactGaussians if `compact`,
    else a PointCloud) and the codec it was stored in.

    Args:
        budget: what the file holding the message may decode to (None: the message's own
            bounds only); the map its header declares is checked against it before decoding.

    Raises:
        DecodeError: not such a protobuf message.
        MapError: a malformed map, or one over `budget`.
    """
    if compact:
        message = CompactGaussians.FromString(data)
        if budget is not None:
            budget.check_map(int(message.count), int(message.sh_degree))
        return decode_compact(message, len(data), source), "compact"
    cloud = PointCloud.FromString(data)
    if budget is not None and cloud.point_stride > 0:
        rest = sum(f.name.startswith("f_rest_") for f in cloud.fields) // 3
        degree = next((d for d, k in SH_REST_COUNTS.items() if k >= rest), 3)
        budget.check_map(len(cloud.data) // cloud.point_stride, degree)
    return pointcloud_to_gaussians(cloud, source), columns_precision(f.name for f in cloud.fields)


def encoded_size(
    gaussians: GaussianMap, codec: str = "fp32", options: CompactOptions = COMPACT_DEFAULTS
) -> int:
    """Bytes of the `/gaussians` message of a map in `codec` (see `encode_map`)."""
    return encode_map(gaussians, codec, 0, options).ByteSize()


_MAP_SCHEMAS = {"foxglove.PointCloud", COMPACT_SCHEMA}


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
    if schema is None or schema.name not in _MAP_SCHEMAS or schema.encoding != "protobuf":
        name = schema.name if schema else "no schema"
        raise LogFormatError(
            f"{source}: {TOPIC_GAUSSIANS} is {name}, not foxglove.PointCloud or {COMPACT_SCHEMA}"
        )
    try:
        compact = schema.name == COMPACT_SCHEMA
        gaussians, codec = decode_map_message(message.data, compact, source, budget)
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
        codec: how it was stored: "fp32", "fp16" (some PointCloud fields float16) or "compact".
    """

    gaussians: GaussianMap
    log_time_ns: int
    message_bytes: int
    codec: str

    @property
    def bytes_per_gaussian(self) -> float | None:
        """Message bytes per Gaussian (None for an empty map)."""
        return self.message_bytes / len(self.gaussians) if len(self.gaussians) else None


def pointcloud_to_gaussians(cloud: PointCloud, source: str = "point cloud") -> GaussianMap:
    """Decode a PointCloud written by `gaussians_to_pointcloud` (or any compatible writer).

    Checks the stride (the packed fields' span), every field's type and extent, that no two
    fields overlap, and the data length before reading, and
    the decoded map's finiteness and id uniqueness. Fields `<name>_f16` (uint16 float16 bit
    patterns) are returned as float32 `<name>`.

    Raises:
        MapError: inconsistent layout or invalid values.
    """
    stride = cloud.point_stride
    data = cloud.data
    if stride <= 0:
        raise MapError(f"{source}: point_stride is {stride}")
    if len(data) % stride:
        raise MapError(
            f"{source}: data length {len(data)} is not a multiple of point_stride {stride}"
        )
    names: list[str] = []
    formats: list[np.dtype] = []
    offsets: list[int] = []
    for f in cloud.fields:
        dtype = _NUMERIC_TYPES.get(f.type)
        if dtype is None:
            raise MapError(f"{source}: field {f.name!r} has unknown numeric type {f.type}")
        if f.offset < 0 or f.offset + dtype.itemsize > stride:
            raise MapError(f"{source}: field {f.name!r} lies outside the {stride}-byte stride")
        if f.name in names:
            raise MapError(f"{source}: field {f.name!r} appears twice")
        names.append(f.name)
        formats.append(dtype)
        offsets.append(f.offset)
    spans = sorted(
        (offset, offset + dtype.itemsize, name)
        for name, dtype, offset in zip(names, formats, offsets, strict=True)
    )
    for (_start, end, name), (start, _end, other) in itertools.pairwise(spans):
        if start < end:
            raise MapError(f"{source}: fields {name!r} and {other!r} overlap")
    span = max((end for _start, end, _name in spans), default=0)
    if stride != span:
        raise MapError(
            f"{source}: point_stride {stride} is not the {span} bytes its fields span "
            "(the records are packed)"
        )
    records = np.frombuffer(
        data,
        dtype=np.dtype(
            {"names": names, "formats": formats, "offsets": offsets, "itemsize": stride}
        ),
    )
    cols = decode_columns({name: records[name] for name in names}, source)
    return map_from_columns(cols, source).validate()
