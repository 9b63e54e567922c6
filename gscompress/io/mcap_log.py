"""The gscompress MCAP log profile: writer and reader.

One profile serves SLAM logs, pruned logs and shares:

- `/gaussians`: foxglove.PointCloud, one message per map snapshot; the last one is "the map".
  Packed little-endian fields named as in 3DGS PLY (see `gscompress.io.columns`), plus the PWAS
  score `importance`, its sums and the uint32 `id`; float32, or at precision fp16 (profile 1.1)
  the bounded attributes as uint16 `<name>_f16` fields holding float16 bit patterns.
- `/camera/pose`, `/camera/pose_gt`: foxglove.PoseInFrame (camera-to-world, frame "world").
- `/tf`: foxglove.FrameTransform world -> camera for the estimated pose.
- `/camera/calibration`: foxglove.CameraCalibration.
- `/slam/stats`: JSON per frame, schema `schemas/slam_stats.v1.schema.json`.
- Metadata record `gscompress`: profile version, tool version, command line, config, sequence,
  frame subset, provenance chain and operation results (`LogMetadata`).

Files are chunked and zstd-compressed (a log without chunks shows no messages in the TypeScript
reader), always carry the metadata record, and are written to a temporary file that is renamed
into place only when complete. Readers treat every file as untrusted.
"""

from __future__ import annotations

import functools
import heapq
import itertools
import json
import os
import re
import struct
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from google.protobuf.message import DecodeError, Message
from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Metadata, Schema
from mcap.records import Message as McapMessage
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_protobuf.schema import build_file_descriptor_set
from zstandard import ZstdError

from gscompress import __version__
from gscompress.camera import (
    Intrinsics,
    is_zero_quaternion,
    make_transform,
    quat_to_rotmat,
    rotmat_to_quat,
)
from gscompress.errors import GscError, LogFormatError, MapError, led_by
from gscompress.gaussians import GaussianMap
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
from gscompress.io.files import AtomicFile, MemoryFile, check_input, check_output, sha256
from gscompress.io.mcap_bounds import (
    BoundedStream,
    chunk_records,
    decompress_chunk,
    file_records,
    read_chunk_header,
    read_record_at,
)
from gscompress_schemas import PROFILE, PROFILE_VERSION, schema_bytes

TOPIC_GAUSSIANS = "/gaussians"
TOPIC_POSE = "/camera/pose"
TOPIC_POSE_GT = "/camera/pose_gt"
TOPIC_TF = "/tf"
TOPIC_CALIBRATION = "/camera/calibration"
TOPIC_STATS = "/slam/stats"


def seconds_to_ns(seconds: float) -> int:
    """Integer nanoseconds (log times) from seconds."""
    return round(float(seconds) * 1e9)


METADATA_NAME = "gscompress"
WORLD_FRAME = "world"
CAMERA_FRAME = "camera"
STATS_SCHEMA = "slam_stats.v1.schema.json"

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

_READ_ERRORS = (
    McapError, DecodeError, struct.error, EOFError, ValueError, KeyError, IndexError, OSError,
    ZstdError, RecursionError,
)  # fmt: skip
"""What reading a damaged MCAP file raises (an OSError: a seek before the start; a
RecursionError: JSON nested deeper than Python's stack)."""


def is_read_error(exc: BaseException) -> bool:
    """Whether `exc` is what a damaged or truncated MCAP file raises while it is read.

    Besides `_READ_ERRORS`, the lz4 package (which `mcap` uses for lz4-compressed chunks, as
    other tools may write) raises a bare RuntimeError whose message starts with "LZ4".
    """
    if isinstance(exc, GscError):
        return False
    return isinstance(exc, _READ_ERRORS) or (
        isinstance(exc, RuntimeError) and str(exc).startswith("LZ4")
    )


MAGIC = b"\x89MCAP0\r\n"
"""The 8 bytes an MCAP file starts and, when closed properly, ends with."""


def closed_properly(stream: IO[bytes]) -> bool:
    """Whether the MCAP file open in `stream` ends with its magic (its writer closed it)."""
    size = stream.seek(0, os.SEEK_END)
    stream.seek(max(size - len(MAGIC), 0))
    return stream.read() == MAGIC


# ---------------------------------------------------------------------- metadata

POSES_ESTIMATED = "estimated"
POSES_GROUND_TRUTH = "ground-truth"
"""What `LogMetadata.pose_origin` says of a log's poses (or a trajectory file's name)."""


@dataclass
class LogMetadata:
    """The `gscompress` metadata record of a log.

    Attributes:
        profile_version: log profile version the file was written with ("major.minor").
        tool_version: gscompress version that wrote the file.
        command: the command line that produced the file.
        config: full configuration of the run (JSON-serialisable).
        sequence: name of the recorded sequence, if any.
        frames: frame subset of the sequence ("all", "odd", "even", "A:B:C").
        world_frame: what the map's world frame is anchored to, so that maps of two agents
            are only merged when their frames agree: "ground-truth:<sequence>" (first frame at
            its ground-truth pose), "first-camera:<sequence>:<frame>" (first camera at the
            identity), or "" when unknown (e.g. a PLY from another tool).
        provenance: oldest first, one entry per derivation step: {"operation", "parent",
            "parent_sha256", ...parameters}.
        results: what the operation that wrote this file reports (e.g. selected / total counts).
    """

    profile_version: str = PROFILE_VERSION
    tool_version: str = __version__
    command: str = ""
    config: dict[str, Any] = field(default_factory=dict)
    sequence: str = ""
    frames: str = ""
    world_frame: str = ""
    provenance: list[dict[str, Any]] = field(default_factory=list)
    results: dict[str, Any] = field(default_factory=dict)

    _JSON_FIELDS = ("config", "provenance", "results")

    def to_record(self) -> dict[str, str]:
        """The MCAP metadata map (string -> string; structured values as JSON)."""
        return {
            key: json.dumps(value, sort_keys=True) if key in self._JSON_FIELDS else str(value)
            for key, value in asdict(self).items()
        }

    @classmethod
    def from_record(cls, record: dict[str, str], source: str = "log") -> LogMetadata:
        """Parse a metadata map, refusing profile versions newer than this reader's major."""
        version = record.get("profile_version", "")
        if not re.fullmatch(r"[0-9]+\.[0-9]+", version):  # (ASCII digits: str.isdigit is wider)
            raise LogFormatError(f"{source}: bad profile_version {version!r}")
        major = int(version.split(".")[0])
        if major > int(PROFILE_VERSION.split(".")[0]):
            raise LogFormatError(
                f"{source} was written with log profile {version}, newer than this gscompress "
                f"({__version__}, profile {PROFILE_VERSION}); upgrade gscompress to read it"
            )
        values: dict[str, Any] = {}
        for key in (
            "profile_version",
            "tool_version",
            "command",
            "sequence",
            "frames",
            "world_frame",
        ):
            values[key] = record.get(key, "")
        try:
            for key in cls._JSON_FIELDS:
                if key in record:
                    values[key] = json.loads(record[key])
        except json.JSONDecodeError as exc:
            raise LogFormatError(f"{source}: metadata field is not JSON ({exc})") from None
        except RecursionError:
            raise LogFormatError(f"{source}: metadata field is JSON nested too deep") from None
        steps = values.get("provenance", [])
        well_formed = isinstance(steps, list) and all(
            isinstance(step, dict)
            and isinstance(step.get("operation"), dict)
            and isinstance(step.get("parent"), str)
            and isinstance(step.get("parent_sha256"), str)
            for step in steps
        )
        if not well_formed or not all(
            isinstance(values.get(key, {}), dict) for key in ("config", "results")
        ):
            raise LogFormatError(
                f"{source}: metadata config and results must be JSON objects, provenance a list "
                "of steps {operation, parent, parent_sha256}"
            )
        return cls(**values)

    def pose_origin(self) -> str:
        """Where the log's `/camera/pose` messages came from: "ground-truth" (the sequence's,
        as `gsc score` of a PLY or a SLAM run with `tracking.use_ground_truth` writes them),
        "estimated" (tracked), or the name of the trajectory file they were read from.

        Said by `results["poses"]`, else by the newest provenance step that names its poses
        (`gsc score`'s), else by the SLAM config the log carries.
        """
        said = self.results.get("poses")
        if said is None:
            steps = (step["operation"] for step in reversed(self.provenance))
            said = next((op["poses"] for op in steps if "poses" in op), None)
        if isinstance(said, str) and said:
            return said
        tracking = self.config.get("tracking")
        if isinstance(tracking, dict) and tracking.get("use_ground_truth") is True:
            return POSES_GROUND_TRUTH
        return POSES_ESTIMATED

    def derive(
        self, operation: dict[str, Any], parent: str | Path, command: str | None = None
    ) -> LogMetadata:
        """Metadata for a file derived from `parent` by `operation`, run as `command` (None:
        this metadata's): the sequence, config and world frame carried over, the provenance
        step appended."""
        parent = Path(parent)
        step = {"operation": operation, "parent": parent.name, "parent_sha256": sha256(parent)}
        return LogMetadata(
            command=self.command if command is None else command,
            config=self.config,
            sequence=self.sequence,
            frames=self.frames,
            world_frame=self.world_frame,
            provenance=[*self.provenance, step],
        )


# ---------------------------------------------------------------------- writer


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


class LogWriter:
    """Writes a gscompress log; use as a context manager.

    The file appears under its final name only when the writer closes without an exception; on
    an exception the temporary file is removed. `metadata` may be changed until then.

    Example:
        with LogWriter("map.mcap", LogMetadata(command="...")) as log:
            log.write_gaussians(gaussians, log_time_ns=0)
    """

    def __init__(
        self,
        path: str | Path | None,
        metadata: LogMetadata,
        *,
        inputs: Sequence[str | Path] = (),
        force: bool = False,
        chunk_size: int = 1 << 20,
    ):
        self.path = None if path is None else check_output(path, inputs, force, suffix=".mcap")
        self.metadata = metadata
        self._file: AtomicFile | MemoryFile = (
            MemoryFile() if self.path is None else AtomicFile(self.path)
        )
        self._mcap = McapWriter(
            self._file.file, chunk_size=chunk_size, compression=CompressionType.ZSTD
        )
        self._mcap.start(profile=PROFILE, library=f"gscompress {__version__}")
        self._schemas: dict[tuple[str, str, bytes], int] = {}
        self._channels: dict[tuple[str, int], int] = {}  # (topic, schema id): a topic may
        # carry two schemas (a SLAM log's fp32 snapshots and a compact one)
        self._closed = False

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    # -- channels

    def _schema_id(self, name: str, encoding: str, data: bytes) -> int:
        key = (name, encoding, data)
        if key not in self._schemas:
            self._schemas[key] = self._mcap.register_schema(name, encoding, data)
        return self._schemas[key]

    def _channel_id(
        self, topic: str, encoding: str, schema_id: int, metadata: dict[str, str] | None = None
    ) -> int:
        if (topic, schema_id) not in self._channels:
            self._channels[topic, schema_id] = self._mcap.register_channel(
                topic, encoding, schema_id, metadata or {}
            )
        return self._channels[topic, schema_id]

    def write_protobuf(self, topic: str, message: Message, log_time_ns: int) -> int:
        """Write a protobuf message (its schema registered on first use); returns its bytes."""
        descriptor = message.DESCRIPTOR
        schema_id = self._schema_id(
            descriptor.full_name,
            "protobuf",
            build_file_descriptor_set(type(message)).SerializeToString(),
        )
        channel_id = self._channel_id(topic, "protobuf", schema_id)
        data = message.SerializeToString()
        self._mcap.add_message(channel_id, log_time_ns, data, log_time_ns)
        return len(data)

    def write_json(
        self, topic: str, value: dict[str, Any], log_time_ns: int, schema_file: str
    ) -> None:
        """Write a JSON message whose jsonschema is `schema_file` from gscompress_schemas."""
        schema_id = self._schema_id(
            schema_file.split(".")[0], "jsonschema", schema_bytes(schema_file)
        )
        channel_id = self._channel_id(topic, "json", schema_id)
        data = json.dumps(value, sort_keys=True, allow_nan=False).encode()
        self._mcap.add_message(channel_id, log_time_ns, data, log_time_ns)

    def copy_message(self, schema: Schema | None, channel: Channel, message: McapMessage) -> None:
        """Pass a message of another log through unchanged (schema, channel and bytes)."""
        schema_id = (
            0 if schema is None else self._schema_id(schema.name, schema.encoding, schema.data)
        )
        channel_id = self._channel_id(
            channel.topic, channel.message_encoding, schema_id, dict(channel.metadata)
        )
        self._mcap.add_message(
            channel_id, message.log_time, message.data, message.publish_time, message.sequence
        )

    # -- the profile's messages

    def write_gaussians(
        self,
        gaussians: GaussianMap,
        log_time_ns: int,
        codec: str = "fp32",
        options: CompactOptions = COMPACT_DEFAULTS,
    ) -> int:
        """Write one map snapshot to `/gaussians` in `codec` (`gscompress.io.codec.CODECS`;
        `options` for compact); returns the bytes of the serialized message.

        Raises:
            MapError: at fp16, a value beyond the float16 range.
        """
        message = encode_map(gaussians, codec, log_time_ns, options)
        return self.write_protobuf(TOPIC_GAUSSIANS, message, log_time_ns)

    def write_pose(
        self, T_world_cam: np.ndarray, log_time_ns: int, ground_truth: bool = False
    ) -> None:
        """Write a camera-to-world pose; estimated poses also go to `/tf` (world -> camera)."""
        T = np.asarray(T_world_cam, dtype=np.float64)
        q = rotmat_to_quat(T[:3, :3])
        msg = pose_message(T, log_time_ns)
        self.write_protobuf(TOPIC_POSE_GT if ground_truth else TOPIC_POSE, msg, log_time_ns)
        if not ground_truth:
            tf = FrameTransform(parent_frame_id=WORLD_FRAME, child_frame_id=CAMERA_FRAME)
            tf.timestamp.FromNanoseconds(log_time_ns)
            _set_pose(tf.translation, tf.rotation, T[:3, 3], q)
            self.write_protobuf(TOPIC_TF, tf, log_time_ns)

    def write_calibration(self, intrinsics: Intrinsics, log_time_ns: int) -> None:
        """Write the pinhole calibration of the camera frame."""
        fx, fy, cx, cy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
        msg = CameraCalibration(
            frame_id=CAMERA_FRAME,
            width=intrinsics.width,
            height=intrinsics.height,
            distortion_model="plumb_bob",
            D=[0.0] * 5,
            K=[fx, 0, cx, 0, fy, cy, 0, 0, 1],
            R=[1, 0, 0, 0, 1, 0, 0, 0, 1],
            P=[fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0],
        )
        msg.timestamp.FromNanoseconds(log_time_ns)
        self.write_protobuf(TOPIC_CALIBRATION, msg, log_time_ns)

    def write_stats(self, stats: dict[str, Any], log_time_ns: int) -> None:
        """Write one `/slam/stats` record (see slam_stats.v1.schema.json)."""
        self.write_json(TOPIC_STATS, stats, log_time_ns, STATS_SCHEMA)

    def write_metadata(self) -> None:
        """Write the metadata record now as well as at close.

        A run that may be killed writes it at the start, so that even its unfinished file
        (see `gscompress.io.recover`) says what produced it; readers take the last record.
        """
        self._mcap.add_metadata(METADATA_NAME, self.metadata.to_record())

    def flush(self) -> None:
        """Close the current chunk and push it to disk (a crash keeps what was flushed)."""
        self._mcap.flush()

    # -- finishing

    def close(self) -> Path | None:
        """Write the metadata record and the summary, then move the file into place (None for
        a log written in memory: its bytes are `data`)."""
        if not self._closed:
            self._closed = True
            try:
                self._mcap.add_metadata(METADATA_NAME, self.metadata.to_record())
                self._mcap.finish()
                self._file.commit()
            except BaseException:
                self._file.discard()
                raise
        return self.path

    @property
    def data(self) -> bytes:
        """The whole file of a log written in memory (`path` None), once closed."""
        if not isinstance(self._file, MemoryFile) or not self._closed:
            raise ValueError("only a closed in-memory log has its bytes here")
        return self._file.data

    def abort(self) -> None:
        """Drop the output: nothing appears under the final name."""
        if not self._closed:
            self._closed = True
            self._file.discard()


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


def decode_map_message(data: bytes, compact: bool, source: str = "map") -> tuple[GaussianMap, str]:
    """The validated map of a serialized `/gaussians` message (a CompactGaussians if `compact`,
    else a PointCloud) and the codec it was stored in.

    Raises:
        DecodeError: not such a protobuf message.
        MapError: a malformed map.
    """
    if compact:
        return decode_compact(CompactGaussians.FromString(data), len(data), source), "compact"
    cloud = PointCloud.FromString(data)
    return pointcloud_to_gaussians(cloud, source), columns_precision(f.name for f in cloud.fields)


def encoded_size(
    gaussians: GaussianMap, codec: str = "fp32", options: CompactOptions = COMPACT_DEFAULTS
) -> int:
    """Bytes of the `/gaussians` message of a map in `codec` (see `encode_map`)."""
    return encode_map(gaussians, codec, 0, options).ByteSize()


_MAP_SCHEMAS = {"foxglove.PointCloud", COMPACT_SCHEMA}


def decode_snapshot(schema: Schema | None, message: McapMessage, source: str = "log") -> Snapshot:
    """Decode one `/gaussians` message (a record of any reader) into a validated map.

    Raises:
        LogFormatError: not a protobuf foxglove.PointCloud or gscompress.CompactGaussians,
            corrupt, or a malformed map.
    """
    if schema is None or schema.name not in _MAP_SCHEMAS or schema.encoding != "protobuf":
        name = schema.name if schema else "no schema"
        raise LogFormatError(
            f"{source}: {TOPIC_GAUSSIANS} is {name}, not foxglove.PointCloud or {COMPACT_SCHEMA}"
        )
    try:
        gaussians, codec = decode_map_message(message.data, schema.name == COMPACT_SCHEMA, source)
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
    _set_pose(msg.pose.position, msg.pose.orientation, T[:3, 3], rotmat_to_quat(T[:3, :3]))
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


def _set_pose(position: Any, orientation: Any, t: np.ndarray, q_wxyz: np.ndarray) -> None:
    position.x, position.y, position.z = (float(v) for v in t)
    orientation.w, orientation.x, orientation.y, orientation.z = (float(v) for v in q_wxyz)


# ---------------------------------------------------------------------- reader


@dataclass(frozen=True)
class ChannelInfo:
    """One channel of a log: topic, schema name, encoding and message count."""

    topic: str
    schema: str
    encoding: str
    messages: int


class LogReader:
    """Reads a gscompress log; use as a context manager.

    Opening reads the summary, each chunk record's header (see `_check_chunks`) and the
    metadata record; maps are decoded on demand. Files from other MCAP writers are read too:
    without statistics, chunk indexes (read forwards) or chunking.

    Raises:
        LogFormatError: the file is not a readable MCAP, is truncated (no summary), has a
            hostile size field, or was written by a newer major profile version.
    """

    def __init__(self, path: str | Path):
        self.path = check_input(path, LogFormatError)
        self._stream: IO[bytes] = open(self.path, "rb")
        try:
            self._open()
        except Exception as exc:
            self._stream.close()
            if not (is_read_error(exc) or isinstance(exc, LogFormatError)):
                raise
            with open(self.path, "rb") as f:
                head = f.read(len(MAGIC))
            if not head:
                why = "the file is empty"
            elif head.startswith(b"ply\n"):
                why = "it is a PLY file; `gsc import-ply` makes a log of it"
            elif head.startswith((b"NGSP", b"\x1f\x8b")):
                why = "it looks like an SPZ file; `gsc import-ply` makes a log of it"
            elif head != MAGIC:
                why = "it does not begin as an MCAP file does"
            elif isinstance(exc, LogFormatError):
                raise
            else:
                why = _describe(exc)
            raise LogFormatError(f"{self.path}: not a readable MCAP log ({why})") from None

    def _open(self) -> None:
        if not closed_properly(self._stream):
            self._stream.seek(0)
            if self._stream.read(len(MAGIC)) == MAGIC:
                raise LogFormatError(
                    f"{self.path}: MCAP file is truncated (no footer: cut short or still being "
                    "written); `gsc slam --resume` continues a SLAM log, `mcap recover` saves "
                    "other logs' messages"
                )
        self._stream.seek(0)
        self._bounded = BoundedStream(self._stream, str(self.path))
        size = self._bounded.size
        self._reader = SeekingReader(
            self._bounded,  # type: ignore[arg-type]
            validate_crcs=True,
            record_size_limit=size,
        )
        summary = self._reader.get_summary()
        if summary is None:
            raise LogFormatError(
                f"{self.path}: MCAP has no summary (truncated or still being written); "
                "try `mcap recover` on it"
            )
        self._summary = summary
        self._check_chunks()
        found = (
            read_record_at(self._bounded, i.offset, Metadata) for i in summary.metadata_indexes
        )
        records = [record for record in found if record.name == METADATA_NAME]
        self.metadata = (
            LogMetadata.from_record(dict(records[-1].metadata), str(self.path))
            if records
            else LogMetadata(profile_version="", tool_version="")
        )

    def _check_chunks(self) -> None:
        """Refuse a chunk whose fields are inconsistent or whose decompressed size is
        implausible before any is decompressed (see `read_chunk_header`). Chunks are found
        through the summary's index, else (an unindexed file) by reading the file's records."""
        if self._summary.chunk_indexes:
            for index in self._summary.chunk_indexes:
                read_chunk_header(self._bounded, index.chunk_start_offset)
        else:
            for _record in file_records(self._bounded, open_chunks=False):
                pass
        self._stream.seek(0)

    def __enter__(self) -> LogReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the file."""
        self._stream.close()

    @functools.cached_property
    def _counts(self) -> dict[int, int]:
        """Messages per channel id: the summary's statistics, else (a file written without
        them, which MCAP allows) counted by reading the messages."""
        if self._summary.statistics is not None:
            return dict(self._summary.statistics.channel_message_counts)
        counts: dict[int, int] = {}
        for _schema, channel, _message in self.iter_messages():
            counts[channel.id] = counts.get(channel.id, 0) + 1
        return counts

    @property
    def channels(self) -> list[ChannelInfo]:
        """Every channel with its message count, in topic order."""
        counts = self._counts
        out = []
        for channel_id, channel in self._summary.channels.items():
            schema = self._summary.schemas.get(channel.schema_id)
            out.append(
                ChannelInfo(
                    topic=channel.topic,
                    schema=schema.name if schema else "",
                    encoding=channel.message_encoding,
                    messages=int(counts.get(channel_id, 0)),
                )
            )
        return sorted(out, key=lambda c: c.topic)

    @property
    def snapshot_count(self) -> int:
        """Number of `/gaussians` messages (map snapshots)."""
        return sum(c.messages for c in self.channels if c.topic == TOPIC_GAUSSIANS)

    def require_snapshots(self) -> int:
        """The number of map snapshots; LogFormatError when the log has none."""
        count = self.snapshot_count
        if count == 0:
            raise LogFormatError(
                f"{self.path} has no {TOPIC_GAUSSIANS} channel: not a gscompress map log"
            )
        return count

    def _guard(self) -> Any:
        return _ReadGuard(self.path)

    def iter_messages(
        self, topics: Sequence[str] | None = None, reverse: bool = False
    ) -> Iterator[tuple[Schema | None, Channel, McapMessage]]:
        """Raw (schema, channel, message) records in log-time order (or the reverse).

        Chunks are read one at a time, as the order needs them, each decompressed within the
        bounds `read_chunk_header` checked; ties keep the file's order.
        """
        with self._guard():
            summary = self._summary
            wanted = None if topics is None else set(topics)
            channels = {
                cid for cid, channel in summary.channels.items()
                if wanted is None or channel.topic in wanted
            }  # fmt: skip
            if not summary.chunk_indexes:  # no index to seek by: read the file forwards
                found = sorted(self._unindexed_messages(wanted), key=lambda m: m[2].log_time)
                yield from reversed(found) if reverse else found
                return
            # a merge by log time: a chunk is opened when its first message (its last, in
            # reverse) is due; keys (time, chunk before message, file position, arrival, item)
            sign = -1 if reverse else 1
            arrival = itertools.count()  # (ties of a hostile index never compare the items)
            queue: list[tuple[int, int, int, int, Any]] = []
            for index in summary.chunk_indexes:
                listed = set(index.message_index_offsets)  # (none listed: not known)
                if wanted is None or not listed or channels & listed:
                    first = index.message_end_time if reverse else index.message_start_time
                    position = sign * index.chunk_start_offset
                    heapq.heappush(queue, (sign * first, 0, position, next(arrival), index))
            while queue:
                _time, kind, position, _arrival, item = heapq.heappop(queue)
                if kind == 1:
                    yield item
                    continue
                records = self._chunk_records(item.chunk_start_offset, channels)
                if reverse:
                    records.reverse()
                for record in records:
                    if isinstance(record, McapMessage):
                        key = (sign * record.log_time, 1, position, next(arrival))
                        heapq.heappush(queue, (*key, self._resolve(record)))

    @property
    def profile(self) -> str:
        """The MCAP header's profile ("ros2" for a ROS 2 bag, "" for ours and Foxglove's)."""
        with self._guard():
            return str(self._reader.get_header().profile)

    @property
    def chunk_offsets(self) -> list[int]:
        """File offsets of the chunks the summary indexes, in the summary's order."""
        return [index.chunk_start_offset for index in self._summary.chunk_indexes]

    def chunk_messages(
        self, offset: int, topics: Sequence[str]
    ) -> list[tuple[Schema | None, Channel, McapMessage]]:
        """The (schema, channel, message) records of `topics` in the chunk at file offset
        `offset` (one of `chunk_offsets`), in the chunk's order, decompressed within the
        bounds `read_chunk_header` checks."""
        wanted = set(topics)
        channels = {cid for cid, c in self._summary.channels.items() if c.topic in wanted}
        with self._guard():
            records = self._chunk_records(offset, channels)
        return [self._resolve(r) for r in records if isinstance(r, McapMessage)]

    def _chunk_records(self, offset: int, channels: set[int] | None) -> list[Any]:
        """The records of the chunk at file offset `offset` (messages of `channels` only)."""
        header = read_chunk_header(self._bounded, offset)
        self._bounded.seek(header.data_offset)
        data = decompress_chunk(header, self._bounded.read(header.data_length), str(self.path))
        return chunk_records(data, str(self.path), channels)

    def _unindexed_messages(
        self, topics: set[str] | None
    ) -> Iterator[tuple[Schema | None, Channel, McapMessage]]:
        """Every message of `topics` (None: all) of a file without chunk indexes, in file
        order; schemas and channels come from the summary and from the records met."""
        schemas = dict(self._summary.schemas)
        channels = dict(self._summary.channels)
        for item in file_records(self._bounded):
            if isinstance(item, Schema):
                schemas.setdefault(item.id, item)
            elif isinstance(item, Channel):
                channels.setdefault(item.id, item)
            elif isinstance(item, McapMessage):
                channel = channels.get(item.channel_id)
                if channel is None:
                    raise LogFormatError(
                        f"{self.path}: a message on channel {item.channel_id}, which no "
                        "channel record defines"
                    )
                if topics is None or channel.topic in topics:
                    yield schemas.get(channel.schema_id), channel, item

    def _resolve(self, message: McapMessage) -> tuple[Schema | None, Channel, McapMessage]:
        """(schema, channel, message) of a message in an indexed file (channels listed in the
        summary, which `chunk_records` was told to keep)."""
        channel = self._summary.channels[message.channel_id]
        return self._summary.schemas.get(channel.schema_id), channel, message

    def read_map(self, snapshot: int = -1) -> GaussianMap:
        """Decode map snapshot `snapshot` (Python indexing: -1 is the last, "the map").

        Raises:
            LogFormatError: no `/gaussians` channel, index out of range, or a malformed cloud.
        """
        return self.read_snapshot(snapshot).gaussians

    def read_snapshot(self, snapshot: int = -1) -> Snapshot:
        """Decode map snapshot `snapshot` with how it was stored (see `read_map`)."""
        count = self.require_snapshots()
        if not -count <= snapshot < count:
            raise LogFormatError(f"{self.path} has {count} snapshot(s); no snapshot {snapshot}")
        index = snapshot % count
        reverse = index >= count // 2 + 1
        skip = count - 1 - index if reverse else index
        for i, (schema, _channel, message) in enumerate(
            self.iter_messages([TOPIC_GAUSSIANS], reverse=reverse)
        ):
            if i == skip:
                return self.decode_snapshot(schema, message)
        raise LogFormatError(f"{self.path}: snapshot {snapshot} could not be found")

    def read_poses(self, topic: str = TOPIC_POSE) -> tuple[np.ndarray, np.ndarray]:
        """The foxglove.PoseInFrame messages of `topic` (the estimated poses by default).

        Returns:
            (log times [N] int64 ns, camera-to-world poses [N, 4, 4] float64), in log-time order;
            empty arrays when the log has no such channel.

        Raises:
            LogFormatError: a message that is not a PoseInFrame, or a non-finite or zero-length
                pose.
        """
        times: list[int] = []
        poses: list[np.ndarray] = []
        for schema, _channel, message in self.iter_messages([topic]):
            poses.append(decode_pose(schema, message, str(self.path)))
            times.append(int(message.log_time))
        stamps = np.array(times, dtype=np.int64)
        order = np.argsort(stamps, kind="stable")
        return stamps[order], np.array(poses, dtype=np.float64).reshape(-1, 4, 4)[order]

    def read_intrinsics(self) -> Intrinsics | None:
        """The camera of the last `/camera/calibration` message (None when there is none).

        Raises:
            LogFormatError: a message that is not a CameraCalibration, or a camera whose size
                or focal lengths are not positive and finite (or its size above 2^16).
        """
        found: Intrinsics | None = None
        for schema, _channel, message in self.iter_messages([TOPIC_CALIBRATION]):
            where = f"{self.path}: {TOPIC_CALIBRATION} at {message.log_time} ns"
            if schema is None or schema.name != "foxglove.CameraCalibration":
                raise LogFormatError(f"{where} is not a foxglove.CameraCalibration")
            try:
                msg = CameraCalibration.FromString(message.data)
            except DecodeError:
                raise LogFormatError(f"{where} is corrupt") from None
            k = np.array(msg.K, dtype=np.float64)
            if (
                k.shape != (9,)
                or not np.all(np.isfinite(k))
                or min(k[0], k[4]) <= 0
                or not (0 < msg.width <= 1 << 16 and 0 < msg.height <= 1 << 16)
            ):
                raise LogFormatError(f"{where} is not a pinhole camera of positive size")
            found = Intrinsics(float(k[0]), float(k[4]), float(k[2]), float(k[5]),
                               int(msg.width), int(msg.height))  # fmt: skip
        return found

    def decode_map(self, schema: Schema | None, message: McapMessage) -> GaussianMap:
        """Decode one `/gaussians` message into a validated map."""
        return self.decode_snapshot(schema, message).gaussians

    def decode_snapshot(self, schema: Schema | None, message: McapMessage) -> Snapshot:
        """Decode one `/gaussians` message into a validated map and how it was stored."""
        return decode_snapshot(schema, message, str(self.path))


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


class _ReadGuard:
    """Turns the errors a malformed file raises inside mcap / protobuf into LogFormatError."""

    def __init__(self, path: Path):
        self.path = path

    def __enter__(self) -> None:
        return None

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object
    ) -> None:
        if exc is not None and is_read_error(exc):
            raise LogFormatError(f"{self.path}: corrupt MCAP data ({_describe(exc)})") from None


def _describe(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    if isinstance(exc, (KeyError, IndexError)):  # their text alone is a bare key or index
        text = f"{type(exc).__name__}: {text}"
    return text[:200]


def read_map(path: str | Path, snapshot: int = -1) -> GaussianMap:
    """The map (snapshot -1, the last) of a log."""
    with LogReader(path) as log:
        return log.read_map(snapshot)
