"""Reading what a killed writer left behind, for `gsc slam --resume`.

A `gsc slam` run flushes a complete chunk after every frame and writes its metadata record at
the start, into a temporary file beside the output (`.NAME.PID.tmp`) that is renamed only when
the log is closed. A run killed without a chance to close (SIGKILL, power loss, the OOM killer)
leaves that file: no summary, a truncated last record, but every flushed chunk intact.
`read_messages` reads such a file up to its last complete record, or a finished log whole.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Channel, Message, Metadata, Schema

from gscompress.errors import LogFormatError
from gscompress.io.files import abandoned_files, check_input
from gscompress.io.mcap_bounds import BoundedStream, file_records
from gscompress.io.mcap_log import (
    METADATA_NAME,
    TOPIC_GAUSSIANS,
    TOPIC_POSE,
    LogMetadata,
    LogReader,
    closed_properly,
    is_read_error,
)

Record = tuple[Schema | None, Channel, Message]


@dataclass
class LogContents:
    """Every message of a log with its last metadata record.

    Attributes:
        metadata: the last `gscompress` metadata record (defaults when there is none).
        messages: (schema, channel, message) in file order.
        finished: whether the file was closed properly (it has a summary).
    """

    metadata: LogMetadata
    messages: list[Record] = field(default_factory=list)
    finished: bool = True

    def map_frames(self) -> int:
        """How many of the logged poses the last map snapshot covers (0 without a snapshot):
        the frames a resume keeps."""
        maps = [m.log_time for _, c, m in self.messages if c.topic == TOPIC_GAUSSIANS]
        if not maps:
            return 0
        return sum(
            1 for _, c, m in self.messages if c.topic == TOPIC_POSE and m.log_time <= maps[-1]
        )


def unfinished_files(path: str | Path) -> list[Path]:
    """Temporary files killed writers of `path` left beside it, newest first: exactly
    `.NAME.PID.tmp` (not another output's whose name starts alike), and none a live writer
    still holds."""
    path = Path(path)
    return abandoned_files(path.parent, path.name)


def resume_sources(path: str | Path) -> list[Path]:
    """What `gsc slam --resume` can continue from: the log at `path` if it is there, then the
    unfinished files of killed writers of it, newest first."""
    path = Path(path)
    return ([path] if path.is_file() else []) + unfinished_files(path)


def read_messages(path: str | Path) -> LogContents:
    """Read a finished log, or an unfinished one up to its last complete record.

    Raises:
        LogFormatError: not an MCAP file, or nothing readable in it.
    """
    path = check_input(path, LogFormatError)
    with open(path, "rb") as stream:
        finished = closed_properly(stream)
    if not finished:
        return _read_unfinished(path)
    with LogReader(path) as log:
        return LogContents(log.metadata, list(log.iter_messages()), finished=True)


def _read_unfinished(path: Path) -> LogContents:
    """Stream an MCAP without a summary, stopping quietly at a truncated tail."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    out = LogContents(LogMetadata(profile_version="", tool_version=""), finished=False)
    metadata: Metadata | None = None
    with open(path, "rb") as stream:
        try:
            for record in file_records(BoundedStream(stream, str(path))):
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Metadata) and record.name == METADATA_NAME:
                    metadata = record
                elif isinstance(record, Message) and record.channel_id in channels:
                    channel = channels[record.channel_id]
                    out.messages.append((schemas.get(channel.schema_id), channel, record))
        except LogFormatError:  # the tail a killed writer left half-written
            pass
        except Exception as exc:
            if not is_read_error(exc):
                raise
    if metadata is None:
        raise LogFormatError(f"{path}: no gscompress metadata record; nothing to resume from")
    out.metadata = LogMetadata.from_record(dict(metadata.metadata), str(path))
    return out
