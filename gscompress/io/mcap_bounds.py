"""Bounded reading of untrusted MCAP files.

The `mcap` package reads a length field and then that many bytes, and inflates a chunk to
whatever its frame says. Here every length is compared with what remains of its input before
anything is read or allocated, and every chunk is decompressed with a hard bound on its output:

- `BoundedStream`: a file (or buffer) whose reads may not run past its end; the `mcap` readers
  are given one, so that each record field they read is checked first.
- `read_chunk_header` / `chunk_records`: a chunk record's fields checked against the record and
  the file, its records decompressed within `MAX_CHUNK_BYTES` and the decode budget's ratio of
  their compressed size (`gscompress.io.decode_budget`, "mcap-chunk"), then split with every
  length checked. A chunk holds Schema, Channel and Message records only (the MCAP
  specification), so padding of other records is refused.
"""

from __future__ import annotations

import io
import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import IO, TypeVar

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, McapRecord, Message, Schema
from mcap.stream_reader import StreamReader
from zstandard import ZstdError, frame_content_size

from gscompress.errors import GscError, LogFormatError
from gscompress.io.decode_budget import DecodeBudget, inflate_lz4, inflate_zstd

MAX_CHUNK_BYTES = 2 * 2**30
"""Largest decompressed chunk a reader accepts (a snapshot of some 25 million Gaussians): a
guard against hostile size fields."""
LZ4_MAGIC = b"\x04\x22\x4d\x18"
_CHUNK_FIXED = 8 + 8 + 8 + 4 + 4  # start and end times, size, crc, codec-name length
_MESSAGE_FIXED = 2 + 4 + 8 + 8  # channel id, sequence, log and publish times


class BoundedStream:
    """A read-only seekable stream that refuses, before reading, a read past its end.

    Args:
        raw: the underlying seekable binary stream (a file or a BytesIO); its size is taken
            once, when the stream is made.
        source: what the stream is, for messages ("FILE" or "FILE: a chunk").
    """

    def __init__(self, raw: IO[bytes], source: str):
        self.raw = raw
        self.source = source
        position = raw.tell()
        self.size = raw.seek(0, os.SEEK_END)
        raw.seek(position)

    def remaining(self) -> int:
        """Bytes between the position and the end."""
        return max(self.size - self.raw.tell(), 0)

    def read(self, n: int) -> bytes:
        """Exactly `n` bytes (`n` >= 0), or LogFormatError when fewer remain."""
        if n < 0:
            raise LogFormatError(f"{self.source}: a record is shorter than its own fields")
        left = self.remaining()
        if n > left:
            raise LogFormatError(
                f"{self.source}: a field of {n} bytes at offset {self.raw.tell()} runs past the "
                f"end ({left} bytes remain)"
            )
        return self.raw.read(n)

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        """Move as the underlying stream does."""
        return self.raw.seek(offset, whence)

    def tell(self) -> int:
        """The position."""
        return self.raw.tell()

    def seekable(self) -> bool:
        """Always: a reader may jump to the summary."""
        return True


@dataclass(frozen=True)
class ChunkHeader:
    """A chunk record's fields, checked against the record and the file.

    Attributes:
        uncompressed_size: what the records decompress to (at most `MAX_CHUNK_BYTES`).
        uncompressed_crc: their CRC-32 (0: none recorded).
        compression: "", "zstd" or "lz4" (others are refused).
        data_offset: file offset of the compressed records.
        data_length: their length.
    """

    uncompressed_size: int
    uncompressed_crc: int
    compression: str
    data_offset: int
    data_length: int


def read_chunk_header(stream: BoundedStream, offset: int) -> ChunkHeader:
    """Read and check the fields of the chunk record at file offset `offset`.

    Raises:
        LogFormatError: not a chunk record, a length beyond the record or the file, an unknown
            codec, a size beyond `MAX_CHUNK_BYTES` or the ratio ceiling, or a codec frame that
            declares more than the record.
    """
    source = stream.source
    if not 0 <= offset <= stream.size - 9:
        raise LogFormatError(f"{source}: a chunk index points at offset {offset}, off the file")
    stream.seek(offset)
    opcode, length = struct.unpack("<BQ", stream.read(9))
    if opcode != Opcode.CHUNK:
        raise LogFormatError(f"{source}: the record at offset {offset} is not a chunk")
    if length > stream.remaining() or length < _CHUNK_FIXED + 8:
        raise LogFormatError(
            f"{source}: the chunk at offset {offset} declares {length} bytes; "
            f"{stream.remaining()} remain in the file"
        )
    end = offset + 9 + length
    _start, _end, size, crc, name_length = struct.unpack("<QQQII", stream.read(_CHUNK_FIXED))
    if name_length > length - _CHUNK_FIXED - 8:
        raise LogFormatError(f"{source}: a chunk's codec name of {name_length} bytes overruns it")
    compression = stream.read(name_length).decode("utf-8", "replace")
    (data_length,) = struct.unpack("<Q", stream.read(8))
    data_offset = stream.tell()
    if data_length > end - data_offset:
        raise LogFormatError(
            f"{source}: a chunk's records of {data_length} bytes overrun its record of {length}"
        )
    header = ChunkHeader(size, crc, compression, data_offset, data_length)
    check_chunk(header, stream.read(min(data_length, 18)), source)
    return header


def check_chunk_claim(size: int, compressed: int, source: str, error: type[GscError]) -> None:
    """Refuse a chunk (of an MCAP, or of a ROS 1 bag) of `compressed` bytes that claims `size`
    bytes uncompressed: more than a chunk may hold (`MAX_CHUNK_BYTES`) or than its bytes may
    decode to (the decode budget's `mcap-chunk` ratio), raising `error`."""
    if size > MAX_CHUNK_BYTES:
        raise error(
            f"{source}: a chunk of {compressed} bytes claims {size} bytes uncompressed, more "
            f"than the {MAX_CHUNK_BYTES >> 30} GiB a chunk may hold"
        )
    budget = DecodeBudget("mcap-chunk", compressed, source, error)
    budget.check(size, f"a chunk of {compressed} bytes claims {size} bytes uncompressed")


def check_chunk(header: ChunkHeader, head: bytes, source: str) -> None:
    """Refuse a chunk whose decompressed size is implausible, before it is decompressed.

    Args:
        header: the chunk's fields.
        head: the first bytes of its compressed records (18: a zstd frame header's longest).
        source: the file, for messages.
    """
    size, compressed, compression = (
        header.uncompressed_size,
        header.data_length,
        header.compression,
    )
    if compression not in ("", "zstd", "lz4"):
        raise LogFormatError(f"{source}: a chunk is compressed with unknown codec {compression!r}")
    if compression == "" and size != compressed:
        raise LogFormatError(
            f"{source}: an uncompressed chunk of {compressed} bytes claims {size} bytes"
        )
    check_chunk_claim(size, compressed, source, LogFormatError)
    declared = -1  # what the codec's frame header says it will allocate (-1: unsaid)
    if compression == "zstd":
        try:
            declared = frame_content_size(head)
        except ZstdError:
            raise LogFormatError(f"{source}: a chunk's zstd frame header is corrupt") from None
    elif compression == "lz4" and head[:4] == LZ4_MAGIC and len(head) >= 14 and head[4] & 8:
        declared = int.from_bytes(head[6:14], "little")  # FLG bit 3: a content size follows
    if declared > size:
        raise LogFormatError(
            f"{source}: a chunk's {compression} frame declares {declared} bytes, its record {size}"
        )


def decompress_chunk(header: ChunkHeader, data: bytes, source: str) -> bytes | bytearray:
    """The chunk's records, decompressed to exactly their declared size (checked by
    `check_chunk` first) and their CRC checked.

    Raises:
        LogFormatError: corrupt compressed data, a size other than declared, a CRC mismatch.
    """
    size = header.uncompressed_size
    if header.compression == "zstd":
        out = inflate_zstd(data, size, f"{source}: a chunk's zstd data", LogFormatError)
    elif header.compression == "lz4":
        out = inflate_lz4(data, size, f"{source}: a chunk's lz4 data", LogFormatError)
    else:
        out = data
    if len(out) != size:
        raise LogFormatError(
            f"{source}: a chunk decompresses to {len(out)} bytes, its record says {size}"
        )
    if header.uncompressed_crc and zlib.crc32(out) != header.uncompressed_crc:
        raise LogFormatError(f"{source}: a chunk's records fail their CRC check")
    return out


def chunk_records(
    data: bytes | bytearray, source: str, channels: set[int] | None = None
) -> list[Schema | Channel | Message]:
    """Split a chunk's decompressed records, every length checked against what remains.

    Args:
        data: the decompressed records.
        source: the file, for messages.
        channels: keep only messages of these channel ids (None: all); the others are skipped
            without being copied.

    Raises:
        LogFormatError: a record cut short, longer than the chunk, shorter than its fields,
            or of a kind a chunk may not hold.
    """
    where = f"{source}: a chunk"
    records: list[Schema | Channel | Message] = []
    view = memoryview(data)
    position, end = 0, len(data)
    while position < end:
        if end - position < 9:
            raise LogFormatError(f"{where} ends inside a record header")
        opcode, length = struct.unpack_from("<BQ", view, position)
        start = position + 9
        if length > end - start:
            raise LogFormatError(
                f"{where} holds a record of {length} bytes with {end - start} bytes left"
            )
        position = start + length
        if opcode == Opcode.MESSAGE:
            if length < _MESSAGE_FIXED:
                raise LogFormatError(f"{where} holds a message of {length} bytes, too short")
            channel_id, sequence, log_time, publish_time = struct.unpack_from("<HIQQ", view, start)
            if channels is None or channel_id in channels:
                records.append(
                    Message(
                        channel_id=channel_id,
                        sequence=sequence,
                        log_time=log_time,
                        publish_time=publish_time,
                        data=bytes(view[start + _MESSAGE_FIXED : position]),
                    )
                )
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
            body = BoundedStream(io.BytesIO(view[start:position]), where)
            kind = Schema if opcode == Opcode.SCHEMA else Channel
            records.append(kind.read(ReadDataStream(body)))  # type: ignore[arg-type]
        else:
            raise LogFormatError(
                f"{where} holds a record of opcode {opcode:#04x}; a chunk holds schemas, "
                "channels and messages only"
            )
    return records


R = TypeVar("R", bound=McapRecord)


def read_record_at(stream: BoundedStream, offset: int, kind: type[R]) -> R:
    """The record of type `kind` (Metadata, ...) at file offset `offset`, its length checked
    against the file and its fields against its length.

    Raises:
        LogFormatError: the offset is off the file, the record runs past its end, or is of
            another kind.
    """
    source = stream.source
    name = kind.__name__.lower()
    if not 0 <= offset <= stream.size - 9:
        raise LogFormatError(f"{source}: a {name} index points at offset {offset}, off the file")
    stream.seek(offset)
    opcode, length = struct.unpack("<BQ", stream.read(9))
    if opcode != getattr(Opcode, name.upper()):
        raise LogFormatError(f"{source}: the record at offset {offset} is not a {name} record")
    body = BoundedStream(io.BytesIO(stream.read(length)), f"{source}: a {name} record")
    return kind.read(ReadDataStream(body))  # type: ignore[arg-type,attr-defined]


def file_records(stream: BoundedStream, open_chunks: bool = True) -> Iterator[McapRecord]:
    """The records of an MCAP file in file order, from its start; each chunk checked
    (`check_chunk`) and, with `open_chunks`, replaced by its records (`chunk_records`)."""
    stream.seek(0)
    reader = StreamReader(
        stream,  # type: ignore[arg-type]
        emit_chunks=True,
        validate_crcs=True,
        record_size_limit=stream.size,
    )
    for record in reader.records:
        if not isinstance(record, Chunk):
            yield record
            continue
        header = ChunkHeader(
            record.uncompressed_size,
            record.uncompressed_crc,
            record.compression,
            -1,
            len(record.data),
        )
        check_chunk(header, record.data[:18], stream.source)
        if open_chunks:
            yield from chunk_records(
                decompress_chunk(header, record.data, stream.source), stream.source
            )
        else:
            yield record
