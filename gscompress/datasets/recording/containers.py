"""The containers of a recording: ROS 1 and ROS 2 bags through rosbags' AnyReader, and
Foxglove-schema MCAP through the project's bounded MCAP reader. A container lists its topics,
reads some topics' messages in one pass, and reads one message again by its locator. Every MCAP
file is checked by the bounded reader before rosbags reads it, and rosbags' chunk inflates are
bounded (`gscompress.datasets.recording.bounds`)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from gscompress.datasets.recording.bounds import (
    ChunkRefused,
    bound_mcap_inflates,
    bound_ros1_chunks,
)
from gscompress.datasets.recording.messages import (
    KINDS,
    TopicInfo,
    from_foxglove,
    from_ros,
)
from gscompress.errors import DatasetError, GscError, MissingDependencyError, clipped

Locator = tuple[Any, ...]
"""Where one message is, for a container to read it again (its own terms)."""


class Container:
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


class RosbagsContainer(Container):
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
        bound_mcap_inflates()
        with _bag_errors(path):
            self._reader = AnyReader([path])
            self._reader.open()
        try:
            with _bag_errors(path):
                bound_ros1_chunks(self._reader)
                self._connections = {c.topic: c for c in self._reader.connections}
                self.topics = sorted(
                    (
                        TopicInfo(c.topic, c.msgtype, KINDS.get(c.msgtype, ""), int(c.msgcount))
                        for c in self._reader.connections
                    ),
                    key=lambda t: t.name,
                )
        except BaseException:
            self.close()
            raise

    def _decode(self, topic: str, log_time: int, raw: bytes) -> Any:
        connection = self._connections[topic]
        with _bag_errors(self.path):
            msg = self._reader.deserialize(raw, connection.msgtype)
        return from_ros(KINDS[connection.msgtype], msg, log_time, topic == "/tf_static")

    def scan(self, topics: Sequence[str]) -> Iterator[tuple[str, int, Locator, Any]]:
        """Every message of `topics`; a locator is (topic, log time, its place among the
        topic's messages of that log time, its place among all the topic's messages)."""
        connections = [self._connections[t] for t in topics if t in self._connections]
        if not connections:
            return
        seen: dict[tuple[str, int], int] = {}
        count: dict[str, int] = {}
        with _bag_errors(self.path):
            for connection, log_time, raw in self._reader.messages(connections=connections):
                key = (connection.topic, log_time)
                nth = seen[key] = seen.get(key, -1) + 1
                position = count[connection.topic] = count.get(connection.topic, -1) + 1
                yield (
                    connection.topic,
                    log_time,
                    (connection.topic, log_time, nth, position),
                    self._decode(connection.topic, log_time, raw),
                )

    def fetch(self, locator: Locator) -> Any:
        topic, log_time, nth, position = locator
        connection = self._connections[topic]
        with _bag_errors(self.path):
            if hasattr(connection.owner, "indexes"):  # a ROS 1 bag
                raw = _ros1_message(connection, position, log_time)
                if raw is not None:
                    return self._decode(topic, log_time, raw)
            else:  # (rosbags finds a ROS 2 message by its time in the storage's own index)
                found = self._reader.messages(
                    connections=[connection], start=log_time, stop=log_time + 1
                )
                for k, (_connection, _time, raw) in enumerate(found):
                    if k == nth:
                        return self._decode(topic, log_time, raw)
        raise DatasetError(f"{self.path}: a {topic} message at {log_time} ns is gone")

    def close(self) -> None:
        reader = getattr(self, "_reader", None)
        if reader is not None and reader.stack is not None:
            reader.close()


def _ros1_message(connection: Any, position: int, log_time: int) -> bytes | None:
    """The raw message at `position` among a ROS 1 connection's messages (None when its index
    has no such message at `log_time`), read through rosbags' own reader.

    rosbags finds a ROS 1 message by time only by walking the connection's index from its start
    (quadratic over a bag read frame by frame); the index is a list in message order, so the
    reader is shown a view of it holding that one entry for the one read (the container's
    reads are serialised by the sequence)."""
    reader = connection.owner
    index = reader.indexes[connection.id]
    if not 0 <= position < len(index) or index[position].time != log_time:
        return None
    reader.indexes[connection.id] = index[position : position + 1]
    try:
        for _connection, _time, raw in reader.messages(connections=[connection]):
            return raw
    finally:
        reader.indexes[connection.id] = index
    return None


class FoxgloveContainer(Container):
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
            TopicInfo(c.topic, c.schema, KINDS.get(c.schema, ""), c.messages)
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
            return from_foxglove(schema, data, log_time, topic == "/tf_static")
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
                yield (
                    channel.topic,
                    message.log_time,
                    (offset, channel.topic, nth),
                    self._decode(channel.topic, message.log_time, message.data),
                )

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
    except ChunkRefused as exc:
        raise DatasetError(f"{path}: {exc}") from None
    except GscError:
        raise
    except MemoryError:
        raise DatasetError(f"{path}: a record asks for more memory than there is") from None
    except Exception as exc:
        if isinstance(exc, KeyboardInterrupt):  # pragma: no cover
            raise
        text = " ".join(str(a) for a in exc.args) or type(exc).__name__
        raise DatasetError(f"{path}: not a readable recording ({clipped(text, 160)})") from None


def open_container(path: Path) -> Container:
    """The container of a recording, checked before any message is read (see the module
    docstring): an MCAP file is opened with the bounded reader first, and stays with it when
    it is not a ROS 2 bag."""
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            raise DatasetError(f"{path} is not a ROS 2 bag folder: it has no metadata.yaml")
        _check_bag_folder(path)
        for part in sorted(path.glob("*.mcap")):
            _checked_mcap(part).close()
        return RosbagsContainer(path)
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
            return RosbagsContainer(path)
        if _is_gsc_log(reader):
            reader.close()
            raise DatasetError(
                f"{path} is a gscompress log, not a recording: `gsc info` shows what it holds"
            )
        try:
            return FoxgloveContainer(path, reader)
        except BaseException:
            reader.close()
            raise
    return RosbagsContainer(path)


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
