"""The log writer: a gscompress log written chunked and zstd-compressed, under a temporary
name renamed into place when complete, its metadata record always written."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from google.protobuf.message import Message
from mcap.records import Channel, Schema
from mcap.records import Message as McapMessage
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_protobuf.schema import build_file_descriptor_set

from gscompress import __version__
from gscompress.camera import Intrinsics, rotmat_to_quat
from gscompress.gaussians import GaussianMap
from gscompress.io.codec import DEFAULT_CODEC
from gscompress.io.compact import COMPACT_DEFAULTS, CompactOptions
from gscompress.io.files import AtomicFile, MemoryFile, check_output, safe_value
from gscompress.io.mcap_log.messages import (
    encode_map,
    pose_message,
    set_pose,
    trajectory_message,
)
from gscompress.io.mcap_log.metadata import (
    CAMERA_FRAME,
    METADATA_NAME,
    STATS_SCHEMA,
    TOPIC_CALIBRATION,
    TOPIC_GAUSSIANS,
    TOPIC_POSE,
    TOPIC_POSE_GT,
    TOPIC_POSE_REFINED,
    TOPIC_STATS,
    TOPIC_TF,
    WORLD_FRAME,
    LogMetadata,
)
from gscompress_schemas import PROFILE, schema_bytes


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
        # carry two schemas (a SLAM log's PointCloud snapshots and a compact one)
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
        data = json.dumps(safe_value(value), sort_keys=True, allow_nan=False).encode()
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
        codec: str = DEFAULT_CODEC,
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
            set_pose(tf.translation, tf.rotation, T[:3, 3], q)
            self.write_protobuf(TOPIC_TF, tf, log_time_ns)

    def write_trajectory(self, T_world_cam: np.ndarray, log_time_ns: int) -> None:
        """Write the refined trajectory: the camera-to-world poses [N, 4, 4] of the first N
        frames (those of the first N `/camera/pose` messages), as one foxglove.PosesInFrame on
        `/camera/pose_refined`; a later message supersedes an earlier one."""
        self.write_protobuf(
            TOPIC_POSE_REFINED, trajectory_message(T_world_cam, log_time_ns), log_time_ns
        )

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
