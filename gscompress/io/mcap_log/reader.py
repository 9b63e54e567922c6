"""The log reader: a gscompress log (or another writer's MCAP) read as untrusted, every length
and chunk bounded before it is read (`gscompress.io.mcap_bounds`), maps decoded on demand."""

from __future__ import annotations

import functools
import heapq
import itertools
import os
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from google.protobuf.message import DecodeError
from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Metadata, Schema
from mcap.records import Message as McapMessage
from zstandard import ZstdError

from gscompress.camera import Intrinsics
from gscompress.errors import GscError, LogFormatError
from gscompress.gaussians import GaussianMap
from gscompress.io.decode_budget import DecodeBudget
from gscompress.io.files import check_input
from gscompress.io.mcap_bounds import (
    BoundedStream,
    chunk_records,
    decompress_chunk,
    file_records,
    read_chunk_header,
    read_record_at,
)
from gscompress.io.mcap_log.messages import (
    Snapshot,
    decode_pose,
    decode_snapshot,
    decode_trajectory,
)
from gscompress.io.mcap_log.metadata import (
    METADATA_NAME,
    TOPIC_CALIBRATION,
    TOPIC_GAUSSIANS,
    TOPIC_POSE,
    TOPIC_POSE_REFINED,
    LogMetadata,
)

_READ_ERRORS = (
    McapError,
    DecodeError,
    struct.error,
    EOFError,
    ValueError,
    KeyError,
    IndexError,
    OSError,
    ZstdError,
    RecursionError,
)
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


@dataclass(frozen=True)
class ChannelInfo:
    """One channel of a log: topic, schema name, encoding and message count."""

    topic: str
    schema: str
    encoding: str
    messages: int


@dataclass(frozen=True)
class Trajectory:
    """A log's camera poses (`LogReader.read_trajectory`).

    Attributes:
        times_ns: [N] log times of the frames (those of `/camera/pose`).
        T_world_cam: [N, 4, 4] camera-to-world poses.
        refined: how many of the first poses are the mapping's refined ones (the rest as
            tracked); 0 for a log without `/camera/pose_refined`.
    """

    times_ns: np.ndarray
    T_world_cam: np.ndarray
    refined: int

    @property
    def source(self) -> str:
        """ "refined", "tracked" or "refined, then tracked" (for messages and records)."""
        if self.refined == 0:
            return "tracked"
        return "refined" if self.refined == len(self.times_ns) else "refined, then tracked"


class LogReader:
    """Reads a gscompress log; use as a context manager.

    Opening reads the summary, each chunk record's header (see `_check_chunks`) and the
    metadata record; maps are decoded on demand, each within `budget` (what the file's bytes may
    decode to: `gscompress.io.decode_budget`). Files from other MCAP writers are read too:
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
        self.budget = DecodeBudget("log", size, str(self.path), LogFormatError)
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
                cid
                for cid, channel in summary.channels.items()
                if wanted is None or channel.topic in wanted
            }
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

    def read_trajectory(self) -> Trajectory:
        """The camera's trajectory: each frame's pose as the mapping last refined it where the
        log has a refined trajectory (`/camera/pose_refined`, its last message, covering the
        first frames of a run that was interrupted), else as tracked (`/camera/pose`).

        Raises:
            LogFormatError: a message that is not a PoseInFrame / PosesInFrame, a non-finite or
                zero-length pose, or a refined trajectory longer than the tracked one.
        """
        times, poses = self.read_poses(TOPIC_POSE)
        last = None
        for record in self.iter_messages([TOPIC_POSE_REFINED], reverse=True):
            last = record
            break
        if last is None:
            return Trajectory(times, poses, 0)
        refined = decode_trajectory(last[0], last[2], str(self.path))
        if len(refined) > len(poses):
            raise LogFormatError(
                f"{self.path}: its refined trajectory has {len(refined)} poses, its "
                f"{TOPIC_POSE} {len(poses)}"
            )
        poses = poses.copy()
        poses[: len(refined)] = refined
        return Trajectory(times, poses, len(refined))

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
            found = Intrinsics(
                float(k[0]), float(k[4]), float(k[2]), float(k[5]), int(msg.width), int(msg.height)
            )
        return found

    def decode_map(self, schema: Schema | None, message: McapMessage) -> GaussianMap:
        """Decode one `/gaussians` message into a validated map."""
        return self.decode_snapshot(schema, message).gaussians

    def decode_snapshot(self, schema: Schema | None, message: McapMessage) -> Snapshot:
        """Decode one `/gaussians` message into a validated map and how it was stored."""
        return decode_snapshot(schema, message, str(self.path), self.budget)


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
