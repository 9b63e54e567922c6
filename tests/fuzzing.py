"""Structural fuzzing of the readers of untrusted files, and its long-run driver (`make fuzz`).

Each reader is a `FuzzTarget`: a name, a function that makes a valid input (bytes) from a few
choices, a function that mutates such an input structurally, and the read that a command does
with a file. A case passes when the read succeeds or raises a `GscError`; anything else (another
exception, a numpy warning, a case over `HANG_SECONDS`) is a defect. Add a reader by appending a
target to `TARGETS`.

Choices come from a `Chooser`: hypothesis' data in tests/test_fuzz.py, a seeded random generator
here, so that the same mutators serve the fast part of the test suite and the long run.

    python tests/fuzzing.py --cases 10000           # every target, each in its own process
    python tests/fuzzing.py --target ply --cases 500
"""

from __future__ import annotations

import argparse
import io
import json
import logging
import random
import resource
import signal
import struct
import subprocess
import sys
import tempfile
import time
import traceback
import warnings
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

from gscompress.errors import GscError

HANG_SECONDS = 10.0
"""A case running longer than this is counted as a hang (and stopped, in the long run)."""

INTERESTING = (
    0, 1, 2, 7, 8, 9, 21, 22, 255, 256, 2**15, 2**16 - 1, 2**16, 2**31 - 1, 2**31, 2**32 - 1,
    2**32, 2**32 + 1, 2**36, 2**40, 2**62, 2**63 - 1, 2**63, 2**64 - 1,
)  # fmt: skip
"""Values written into length, count, offset and size fields."""

SPECIAL_FLOATS = (
    0.0, -0.0, 1.0, -1.0, 1e-45, 1e30, -1e30, 3.4e38, -3.4e38, float("inf"), float("-inf"),
    float("nan"), 88.0, -88.0, 710.0, 65504.0, 65520.0,
)  # fmt: skip
"""Values written into float fields (PointCloud and PLY records)."""


class Chooser(Protocol):
    """Where a mutator's choices come from."""

    def integer(self, low: int, high: int) -> int:
        """An integer in [low, high]."""
        ...

    def pick(self, options: Sequence[Any]) -> Any:
        """One of `options`."""
        ...


class RandomChooser:
    """Choices from a seeded `random.Random`."""

    def __init__(self, seed: int):
        self.rng = random.Random(seed)

    def integer(self, low: int, high: int) -> int:
        return self.rng.randint(low, high)

    def pick(self, options: Sequence[Any]) -> Any:
        return options[self.rng.randrange(len(options))]


def _value(c: Chooser, width: int) -> int:
    """An interesting or random unsigned value that fits `width` bytes."""
    top = 2 ** (8 * width) - 1
    if c.integer(0, 3) == 0:
        return c.integer(0, top)
    return min(c.pick(INTERESTING), top)


def _overwrite(data: bytes, c: Chooser, start: int = 0, end: int | None = None) -> bytes:
    """`data` with an integer field (1, 2, 4 or 8 bytes) in [start, end) set to a chosen value."""
    end = len(data) if end is None else min(end, len(data))
    width = c.pick((1, 2, 4, 8))
    if end - start < width:
        return data
    at = c.integer(start, end - width)
    value = _value(c, width).to_bytes(width, "little")
    return data[:at] + value + data[at + width :]


def _byte_mutation(data: bytes, c: Chooser) -> bytes:
    """One raw edit: a field overwritten, bytes flipped, cut, inserted, deleted or repeated."""
    kind = c.integer(0, 5)
    at = c.integer(0, max(len(data) - 1, 0))
    if kind == 0:
        return _overwrite(data, c)
    if kind == 1 and data:
        return data[:at] + bytes([data[at] ^ (1 << c.integer(0, 7))]) + data[at + 1 :]
    if kind == 2:
        return data[:at]
    if kind == 3:
        return data[:at] + bytes(c.pick((1, 8, 64, 4096))) + data[at:]
    if kind == 4:
        return data[:at] + data[at + c.integer(1, 64) :]
    return data[:at] + data[at : at + c.integer(1, 256)] * c.integer(2, 4) + data[at:]


# ------------------------------------------------------------------------------------- MCAP


def _valid_log(c: Chooser) -> bytes:
    """A small gscompress log (map snapshots, poses, calibration, stats, metadata) in one of
    several layouts: zstd, lz4 or no compression; indexed or not; chunked or not."""
    import numpy as np
    from mcap.writer import CompressionType, IndexType

    from gscompress.camera import Intrinsics
    from gscompress.gaussians import random_map
    from gscompress.io.mcap_log import LogMetadata, LogWriter

    seed = c.integer(0, 3)
    layout = c.pick(("zstd", "lz4", "none", "unindexed", "unchunked", "small-chunks"))
    key = (seed, layout)
    if key in _LOGS:
        return _LOGS[key]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "log.mcap"
        meta = LogMetadata(command="fuzz", sequence="s", frames="all", results={"poses": "x"})
        with LogWriter(path, meta, chunk_size=256 if layout == "small-chunks" else 1 << 20) as w:
            camera = Intrinsics(20.0, 20.0, 8.0, 6.0, 16, 12)
            w.write_calibration(camera, 0)
            for t in range(2):
                w.write_pose(np.eye(4), t)
                w.write_gaussians(random_map(6 + 3 * t, seed=seed, sh_degree=t), t)
            if seed % 2:  # a share's carried keyframe (JPEG and PNG inside the chunks)
                from gscompress.io.keyframes import CarriedFrame, write_carried

                rng = np.random.default_rng(seed)
                color = rng.random((12, 16, 3)).astype(np.float32)
                depth = rng.uniform(0.5, 3.0, (12, 16)).astype(np.float32)
                write_carried(w, [CarriedFrame(5, color, depth, np.eye(4))], camera)
        data = path.read_bytes()
        if layout not in ("zstd", "small-chunks"):
            from conftest import rewrite_log

            options: dict[str, Any] = {
                "lz4": {"compression": CompressionType.LZ4},
                "none": {"compression": CompressionType.NONE},
                "unindexed": {"index_types": IndexType.NONE},
                "unchunked": {"use_chunking": False},
            }[layout]
            out = Path(tmp) / "other.mcap"
            rewrite_log(path, out, **options)
            data = out.read_bytes()
    _LOGS[key] = data
    return data


_LOGS: dict[tuple[int, str], bytes] = {}


def mcap_records(data: bytes) -> list[Any]:
    """The records of a valid MCAP file, chunks unopened."""
    from mcap.stream_reader import StreamReader

    return list(StreamReader(io.BytesIO(data), emit_chunks=True).records)


def serialize_log(records: list[Any]) -> bytes:
    """An MCAP file of `records`, its offsets (chunk, message-index, metadata and summary
    indexes, footer) recomputed for where the records now lie; CRCs of sections left out."""
    from mcap.data_stream import RecordBuilder
    from mcap.records import (
        Chunk,
        ChunkIndex,
        DataEnd,
        Footer,
        MessageIndex,
        Metadata,
        MetadataIndex,
        SummaryOffset,
    )
    from mcap.stream_reader import MAGIC_SIZE

    magic = b"\x89MCAP0\r\n"
    assert len(magic) == MAGIC_SIZE

    def layout(records: list[Any]) -> list[tuple[int, int]]:
        spans, offset = [], len(magic)
        for record in records:
            builder = RecordBuilder()
            record.write(builder)
            size = len(builder.end())
            spans.append((offset, size))
            offset += size
        return spans

    for _ in range(2):  # the fixed-size index fields settle after one pass
        spans = layout(records)
        chunks = [i for i, r in enumerate(records) if isinstance(r, Chunk)]
        metadata = [i for i, r in enumerate(records) if isinstance(r, Metadata)]
        chunk_indexes = [r for r in records if isinstance(r, ChunkIndex)]
        for k, index in enumerate(chunk_indexes[: len(chunks)]):
            i = chunks[k]
            index.chunk_start_offset, index.chunk_length = spans[i]
            offsets, j = {}, i + 1
            while j < len(records) and isinstance(records[j], MessageIndex):
                offsets[records[j].channel_id] = spans[j][0]
                j += 1
            index.message_index_offsets = offsets
            index.message_index_length = sum(spans[m][1] for m in range(i + 1, j))
        for k, index in enumerate(r for r in records if isinstance(r, MetadataIndex)):
            if k < len(metadata):
                index.offset, index.length = spans[metadata[k]]
        end = next((i for i, r in enumerate(records) if isinstance(r, DataEnd)), None)
        footer = next((r for r in records if isinstance(r, Footer)), None)
        if end is not None:
            records[end].data_section_crc = 0
        if end is not None and footer is not None:
            first = end + 1
            summary = [i for i in range(first, len(records) - 1)]
            offsets_at = [i for i in summary if isinstance(records[i], SummaryOffset)]
            footer.summary_start = spans[first][0] if summary else 0
            footer.summary_offset_start = spans[offsets_at[0]][0] if offsets_at else 0
            footer.summary_crc = 0
            groups: dict[int, list[int]] = {}
            for i in summary:
                if not isinstance(records[i], SummaryOffset):
                    groups.setdefault(_opcode(records[i]), []).append(i)
            for record in (records[i] for i in offsets_at):
                members = groups.get(record.group_opcode)
                if members:
                    record.group_start = spans[members[0]][0]
                    record.group_length = sum(spans[m][1] for m in members)
    builder = RecordBuilder()
    for record in records:
        record.write(builder)
    return magic + builder.end() + magic


def _opcode(record: Any) -> int:
    from mcap.data_stream import RecordBuilder

    builder = RecordBuilder()
    record.write(builder)
    return builder.end()[0]


def _inner_records(chunk: Any) -> bytes:
    from mcap.stream_reader import get_chunk_data_stream

    stream, _ = get_chunk_data_stream(chunk)
    return stream.read(chunk.uncompressed_size) if chunk.uncompressed_size else b""


def _recompress(chunk: Any, inner: bytes, c: Chooser) -> Any:
    """`chunk` holding `inner` under a chosen codec, its size and CRC honest or not."""
    import lz4.frame
    import zstandard

    codec = c.pick(("zstd", "lz4", "lz4-unsized", "", "bogus"))
    if codec == "zstd":
        data = zstandard.ZstdCompressor(write_content_size=c.integer(0, 1) == 1).compress(inner)
    elif codec.startswith("lz4"):
        data = lz4.frame.compress(inner, store_size=codec == "lz4")
    else:
        data = inner
    size = len(inner) if c.integer(0, 3) else _value(c, 8)
    crc = c.pick((zlib.crc32(inner), 0, _value(c, 4)))
    return replace(
        chunk, compression=codec.split("-")[0], data=data, uncompressed_size=size,
        uncompressed_crc=crc,
    )  # fmt: skip


def _mutate_inner(inner: bytes, c: Chooser) -> bytes:
    """A chunk's records with one structural edit: a record's opcode, length or message
    header field, its body cut or padded, a record inserted (padding, unknown opcode, a huge
    length) or a PointCloud message rewritten."""
    spans, at = [], 0
    while at + 9 <= len(inner):
        length = struct.unpack_from("<Q", inner, at + 1)[0]
        spans.append((at, 9 + length))
        at += 9 + length
    kind = c.integer(0, 5)
    if kind == 0 or not spans:  # a record of another kind, or padding
        filler = c.pick(
            (bytes(c.pick((9, 64, 5000, 4 << 20))), b"\x80" + struct.pack("<Q", 3) + b"abc")
        )
        where = c.pick([0, len(inner)] + [s for s, _ in spans])
        return inner[:where] + filler + inner[where:]
    start, size = c.pick(spans)
    record = inner[start : start + size]
    if kind == 1:  # the opcode or the length
        record = _overwrite(record, c, 0, 9)
    elif kind == 2:  # a message header field (channel, sequence, times)
        record = _overwrite(record, c, 9, 9 + 22)
    elif kind == 3 and record[0] == 0x05:
        record = record[:31] + _mutate_cloud(record[31:], c)
        record = record[:1] + struct.pack("<Q", len(record) - 9) + record[9:]
    elif kind == 4:
        record = record[: c.integer(0, len(record))]
    else:
        record = _byte_mutation(record, c)
    return inner[:start] + record + inner[start + size :]


def _mutate_cloud(data: bytes, c: Chooser) -> bytes:
    """A serialized foxglove.PointCloud with one layout or value edit (or the bytes as they
    are when they are not one)."""
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
    from google.protobuf.message import DecodeError

    cloud = PointCloud()
    try:
        cloud.ParseFromString(data)
    except DecodeError:
        return data
    if not cloud.fields:
        return _byte_mutation(data, c)
    field = c.pick(list(cloud.fields))
    kind = c.integer(0, 7)
    if kind == 0:
        cloud.point_stride = c.pick((0, 1, cloud.point_stride * 2, cloud.point_stride + 4,
                                     cloud.point_stride - 4, 2**32 - 1))  # fmt: skip
    elif kind == 1:
        field.offset = c.pick((0, field.offset + 2, cloud.point_stride, 2**31, 2**32 - 1))
    elif kind == 2:
        field.type = c.integer(0, 9)
    elif kind == 3:
        field.name = c.pick(("x", "opacity", "id", "opacity_f16", "f_rest_0", "", "scale_0"))
    elif kind == 4:
        del cloud.fields[c.integer(0, len(cloud.fields) - 1)]
    elif kind == 5 and cloud.point_stride and field.type == 7:  # a float32 value
        record = c.integer(0, max(len(cloud.data) // cloud.point_stride - 1, 0))
        at = record * cloud.point_stride + field.offset
        if at + 4 <= len(cloud.data):
            value = struct.pack("<f", c.pick(SPECIAL_FLOATS))
            cloud.data = cloud.data[:at] + value + cloud.data[at + 4 :]
    elif kind == 6:
        cloud.data = cloud.data[: c.integer(0, len(cloud.data))]
    else:
        cloud.data = cloud.data + bytes(c.pick((1, 4, cloud.point_stride)))
    return cloud.SerializeToString()


def _mutate_metadata(record: Any, c: Chooser) -> Any:
    """The gscompress metadata record with one of its values replaced."""
    values = dict(record.metadata)
    key = c.pick([*sorted(values), "results"])
    values[key] = c.pick((
        "", "{", "[]", "null", "1.0", "99.0", "[" * 5000, '{"poses": 1}', '[{"operation": 1}]',
        json.dumps({"tracking": {"use_ground_truth": "yes"}}), "\u0661.0", "1e999",
    ))  # fmt: skip
    return replace(record, metadata=values)


def _mutate_log(data: bytes, c: Chooser) -> bytes:
    """One to three structural edits of a valid log's records, then perhaps a raw edit."""
    from mcap.records import Chunk, ChunkIndex, Message, Metadata, Schema

    records = mcap_records(data)
    inner_of = {id(r): _inner_records(r) for r in records if isinstance(r, Chunk)}
    for _ in range(c.integer(1, 3)):
        kind = c.integer(0, 6)
        chunks = [i for i, r in enumerate(records) if isinstance(r, Chunk)]
        if kind <= 2 and chunks:  # a chunk's records, codec, size or CRC
            i = c.pick(chunks)
            inner = inner_of[id(records[i])]  # (what the chunk holds, whatever its fields say)
            if kind < 2:
                inner = _mutate_inner(inner, c)
            records[i] = _recompress(records[i], inner, c)
            inner_of[id(records[i])] = inner
        elif kind == 3:  # a message outside chunks, or a schema
            found = [i for i, r in enumerate(records) if isinstance(r, Message | Schema)]
            if found:
                i = c.pick(found)
                if isinstance(records[i], Message):
                    records[i] = replace(records[i], data=_mutate_cloud(records[i].data, c))
                else:
                    records[i] = replace(records[i], data=_byte_mutation(records[i].data, c))
        elif kind == 4:
            found = [i for i, r in enumerate(records) if isinstance(r, Metadata)]
            if found:
                i = c.pick(found)
                records[i] = _mutate_metadata(records[i], c)
        elif kind == 5 and len(records) > 3:  # a record dropped or repeated
            i = c.integer(1, len(records) - 2)
            if c.integer(0, 1):
                del records[i]
            else:
                records.insert(i, records[i])
    out = serialize_log(records)
    index_kind = c.integer(0, 3)
    if index_kind == 0:  # a chunk index field, after the offsets were fixed
        found = [r for r in records if isinstance(r, ChunkIndex)]
        if found:
            index = c.pick(found)
            name = c.pick(("chunk_start_offset", "chunk_length", "message_start_time",
                           "message_end_time", "uncompressed_size", "compressed_size"))  # fmt: skip
            setattr(index, name, _value(c, 8))
            out = serialize_as_is(records)
    elif index_kind == 1:
        out = _byte_mutation(out, c)
    return out


def serialize_as_is(records: list[Any]) -> bytes:
    """The records as they are (no offsets recomputed)."""
    from mcap.data_stream import RecordBuilder

    builder = RecordBuilder()
    for record in records:
        record.write(builder)
    magic = b"\x89MCAP0\r\n"
    return magic + builder.end() + magic


def read_log(path: Path) -> None:
    """What `gsc info`, `prune`, `share`, `merge` and `eval` read of a log."""
    from gscompress.io.keyframes import read_carried
    from gscompress.io.mcap_log import TOPIC_POSE, LogReader

    with LogReader(path) as log:
        _ = log.channels, log.metadata.pose_origin()
        read_carried(log)
        if log.snapshot_count:
            log.read_map().opacities()
            log.read_map(0)
        log.read_poses(TOPIC_POSE)
        for _ in log.iter_messages(reverse=True):
            pass


# -------------------------------------------------------------------------------------- PLY


def _valid_ply(c: Chooser) -> bytes:
    """A small 3DGS PLY: ours with or without scores, another tool's layout, big-endian, an
    extra element, or the compressed (packed) layout."""
    from gscompress.gaussians import random_map
    from gscompress.io.ply import write_ply

    kind = c.pick(("ours", "plain", "sh3", "big-endian", "extra", "packed"))
    if kind in _PLYS:
        return _PLYS[kind]
    if kind == "packed":
        header = (
            "ply\nformat binary_little_endian 1.0\nelement chunk 1\n"
            + "".join(f"property float {n}\n" for n in ("min_x", "min_y", "min_z"))
            + "element vertex 2\n"
            + "".join(
                f"property uint packed_{n}\n" for n in ("position", "rotation", "scale", "color")
            )
            + "end_header\n"
        )
        data = header.encode() + bytes(12 + 2 * 16)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            g = random_map(5, seed=1, sh_degree=3 if kind == "sh3" else 0)
            path = write_ply(g, Path(tmp) / "m.ply", importance=kind != "plain")
            data = path.read_bytes()
        if kind == "big-endian":
            data = _to_big_endian(data)
        elif kind == "extra":
            end = data.index(b"end_header\n")
            data = data[:end] + b"element face 2\nproperty int a\n" + data[end:] + bytes(8)
    _PLYS[kind] = data
    return data


_PLYS: dict[str, bytes] = {}


def _to_big_endian(data: bytes) -> bytes:
    """Our little-endian PLY (float and uint properties only) as big-endian."""
    import numpy as np

    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode()
    names = [line.split() for line in header.splitlines() if line.startswith("property")]
    dtype = np.dtype([(n, "<f4" if t == "float" else "<u4") for _, t, n in names])
    body = np.frombuffer(data[end:], dtype=dtype).astype(dtype.newbyteorder(">"))
    return header.replace("binary_little_endian", "binary_big_endian").encode() + body.tobytes()


_HEADER_EDITS = (
    "property", "property float", "property list uchar int vertex_indices", "element",
    "element vertex", "element vertex -1", "element vertex 9223372036854775808",
    "element vertex 18446744073709551616", "element vertex \u0661", "element face 1000000000000",
    "element chunk 1", "property uint packed_position", "format ascii 1.0",
    "format binary_big_endian 1.0", "format", "comment \xff", "obj_info x", "end_header",
    "property double opacity", "property uchar x", "property float x", "bogus 1",
)  # fmt: skip


def _mutate_ply(data: bytes, c: Chooser) -> bytes:
    """One to three edits of a PLY: a header line deleted, repeated, replaced or added, the
    vertex count changed, a value of the body replaced, or a raw edit."""
    end = data.find(b"end_header\n")
    if end < 0:
        return _byte_mutation(data, c)
    end += len(b"end_header\n")
    lines, body = data[:end].decode("latin-1").split("\n")[:-1], data[end:]
    for _ in range(c.integer(1, 3)):
        kind = c.pick((0, 1, 2, 3, 4, 4, 4, 4, 5, 6))  # values of the body most often
        at = c.integer(1, max(len(lines) - 1, 1))
        if kind == 0 and len(lines) > 1:
            del lines[at]
        elif kind == 1:
            lines.insert(at, c.pick(_HEADER_EDITS))
        elif kind == 2 and at < len(lines):
            lines[at] = c.pick(_HEADER_EDITS)
        elif kind == 3:  # the vertex count
            counts = [i for i, line in enumerate(lines) if line.startswith("element vertex")]
            if counts:
                lines[counts[0]] = f"element vertex {_value(c, 8) if c.integer(0, 1) else 4}"
        elif kind == 4 and len(body) >= 4:  # a float of the body (the opacity of a row, often)
            at = 4 * c.integer(0, len(body) // 4 - 1)
            value = struct.pack("<f", c.pick(SPECIAL_FLOATS))
            body = body[:at] + value + body[at + 4 :]
        elif kind == 5:
            body = body[: c.integer(0, len(body))] if c.integer(0, 1) else body + bytes(64)
        else:
            body = _byte_mutation(body, c)
    return ("\n".join(lines) + "\n").encode("utf-8") + body


def read_ply_map(path: Path) -> None:
    """What `gsc import-ply` and `gsc score` read of a PLY."""
    from gscompress.io.ply import read_ply

    read_ply(path).opacities()


# ------------------------------------------------------------------------ compact map and SPZ


def _random_map(c: Chooser, smallest: int = 0) -> Any:
    from gscompress.gaussians import random_map

    return random_map(c.integer(smallest, 60), c.integer(0, 999), bool(c.integer(0, 1)),
                      c.pick((0, 0, 1, 3)))  # fmt: skip


def _valid_compact(c: Chooser) -> bytes:
    """A compact map message: isotropic or not, with or without ids, sums or score."""
    from gscompress.io.codec import CompactOptions, encode_compact

    options = CompactOptions(ids=bool(c.integer(0, 1)), sums=bool(c.integer(0, 1)))
    return encode_compact(_random_map(c), options).SerializeToString()


def _mutate_compact(data: bytes, c: Chooser) -> bytes:
    """A header field, a column's field or its compressed codes set to an edge value, a column
    dropped or repeated, or raw bytes edited."""
    import zstandard

    from gscompress.io.codec import CompactGaussians

    message = CompactGaussians.FromString(data)
    kind = c.integer(0, 6)
    if kind == 0:
        name = c.pick(("version", "count", "sh_degree", "position_bits"))
        setattr(message, name, _value(c, 4))
    elif kind == 1:
        message.step = c.pick(SPECIAL_FLOATS)
        if c.integer(0, 1) and message.origin:
            message.origin[c.integer(0, len(message.origin) - 1)] = c.pick(SPECIAL_FLOATS)
    elif kind <= 4 and message.columns:
        column = message.columns[c.integer(0, len(message.columns) - 1)]
        edit = c.integer(0, 5)
        if edit == 0:
            setattr(column, c.pick(("components", "bits")), _value(c, 4))
        elif edit == 1:
            column.raw_bytes = _value(c, 8)
        elif edit == 2:
            column.dtype = c.pick(("u1", "<u2", "<u4", "<u8", "<f4", "<f8", "", "O"))
        elif edit == 3 and (column.low or column.high):
            column.low[0] = c.pick(SPECIAL_FLOATS)
        elif edit == 4:
            raw = bytes(c.pick((0, 1, 7, 4096, 1 << 20)))
            column.data = zstandard.ZstdCompressor(write_content_size=bool(c.integer(0, 1))
                                                   ).compress(raw)  # fmt: skip
        else:
            column.data = _byte_mutation(column.data, c)
    elif kind == 5 and message.columns:
        at = c.integer(0, len(message.columns) - 1)
        if c.integer(0, 1):
            del message.columns[at]
        else:
            message.columns.add().CopyFrom(message.columns[at])
    else:
        return _byte_mutation(message.SerializeToString(), c)
    return message.SerializeToString()


def read_compact(path: Path) -> None:
    """What a log reader does with a compact `/gaussians` message."""
    from gscompress.io.codec import decode_compact_bytes

    decode_compact_bytes(path.read_bytes(), str(path))[0].opacities()


def _valid_spz(c: Chooser) -> bytes:
    """An SPZ file of version 3 (gzip) or 4 (zstd streams)."""
    from gscompress.io.spz import encode_bytes

    return encode_bytes(_random_map(c, 1), version=c.pick((3, 4)))  # (SPZ holds no empty map)


def _mutate_spz(data: bytes, c: Chooser) -> bytes:
    """A header field (the first 32 bytes of a v4 file; of the inflated stream of a v3 one)
    set to an edge value, or raw bytes edited."""
    import gzip

    if data[:2] == b"\x1f\x8b" and c.integer(0, 1):  # v3: edit inside the gzip stream
        inner = gzip.decompress(data)
        return gzip.compress(_overwrite(inner, c, 0, 16) if c.integer(0, 1)
                             else _byte_mutation(inner, c))  # fmt: skip
    return _overwrite(data, c, 0, 32) if c.integer(0, 1) else _byte_mutation(data, c)


def read_spz_map(path: Path) -> None:
    """What `gsc import-ply` reads of an SPZ file."""
    from gscompress.io.spz import read_spz

    read_spz(path).opacities()


# ---------------------------------------------------------------------------------- targets


@dataclass(frozen=True)
class FuzzTarget:
    """One reader under fuzzing.

    Attributes:
        name: what `--target` calls it.
        suffix: the file-name suffix of its inputs.
        make_valid_input: a valid input from a few choices.
        mutate: a structurally edited input from a valid one.
        read: what a command does with such a file; returns normally or raises GscError.
    """

    name: str
    suffix: str
    make_valid_input: Callable[[Chooser], bytes]
    mutate: Callable[[bytes, Chooser], bytes]
    read: Callable[[Path], None]


TARGETS: list[FuzzTarget] = [
    FuzzTarget("mcap", ".mcap", _valid_log, _mutate_log, read_log),
    FuzzTarget("ply", ".ply", _valid_ply, _mutate_ply, read_ply_map),
    FuzzTarget("compact", ".bin", _valid_compact, _mutate_compact, read_compact),
    FuzzTarget("spz", ".spz", _valid_spz, _mutate_spz, read_spz_map),
]


class Hang(Exception):
    """A case ran past `HANG_SECONDS`."""


def run_case(target: FuzzTarget, c: Chooser, folder: Path) -> tuple[str, str]:
    """Make, mutate and read one input. Returns (outcome, detail): "ok", "refused" (a
    GscError), or "defect" with the traceback (any other exception or a warning)."""
    path = make_case(target, c, folder)
    return read_case(target, path)


def make_case(target: FuzzTarget, c: Chooser, folder: Path) -> Path:
    """A mutated input of `target`, written in `folder`."""
    path = folder / f"case{target.suffix}"
    path.write_bytes(target.mutate(target.make_valid_input(c), c))
    return path


def read_case(target: FuzzTarget, path: Path) -> tuple[str, str]:
    """Read one input: see `run_case`."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # numpy's RuntimeWarnings are defects too
            target.read(path)
    except GscError as exc:
        if "\n" in str(exc):
            return "defect", f"a GscError of several lines: {exc!r}"
        return "refused", str(exc)
    except Hang:
        raise
    except Exception:  # the defects the fuzzing looks for, recorded rather than raised
        return "defect", traceback.format_exc()
    return "ok", ""


def _on_alarm(_signum: int, _frame: Any) -> None:
    raise Hang


def fuzz(target: FuzzTarget, cases: int, seed: int) -> dict[str, Any]:
    """Run `cases` cases of `target`; counts, the slowest case, peak memory and defects."""
    counts = {"ok": 0, "refused": 0, "defect": 0, "hang": 0}
    defects: list[str] = []
    slowest = (0.0, -1)
    largest = 0
    signal.signal(signal.SIGALRM, _on_alarm)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for case in range(cases):
            path = make_case(target, RandomChooser(seed * 1_000_003 + case), Path(tmp))
            largest = max(largest, path.stat().st_size)
            began = time.perf_counter()
            signal.setitimer(signal.ITIMER_REAL, HANG_SECONDS)
            try:
                outcome, detail = read_case(target, path)
            except Hang:
                outcome, detail = "hang", f"case {case} ran over {HANG_SECONDS} s"
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
            took = time.perf_counter() - began
            slowest = max(slowest, (took, case))
            counts[outcome] += 1
            if outcome in ("defect", "hang") and len(defects) < 20:
                defects.append(f"case {case} (seed {seed}):\n{detail}")
    seconds = time.perf_counter() - start
    return {
        "target": target.name,
        "cases": cases,
        **counts,
        "cases_per_second": round(cases / seconds, 1),
        "slowest_case_seconds": round(slowest[0], 3),
        "slowest_case": slowest[1],
        "peak_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "largest_input_bytes": largest,
        "defects": defects,
    }


def main(argv: Sequence[str] | None = None) -> int:
    """The long run: each target in its own process, all at once (so that each peak RSS is its
    own); their reports are printed in target order."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", type=int, default=10_000, help="cases per target")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--target", choices=[t.name for t in TARGETS], help="one target only")
    args = parser.parse_args(argv)
    logging.disable(logging.WARNING)  # (the readers' notes on clamped values, once a case)
    if args.target is None:
        runs = [
            subprocess.Popen(
                [
                    sys.executable,
                    __file__,
                    "--target",
                    target.name,
                    "--cases",
                    str(args.cases),
                    "--seed",
                    str(args.seed),
                ],
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
            )
            for target in TARGETS
        ]
        failed = 0
        for run in runs:
            output, _ = run.communicate()
            print(output, end="", flush=True)
            failed |= run.returncode
        return failed
    target = next(t for t in TARGETS if t.name == args.target)
    result = fuzz(target, args.cases, args.seed)
    for defect in result["defects"]:
        print(defect, file=sys.stderr)
    print(
        f"{result['target']}: {result['cases']} cases ({result['ok']} read, {result['refused']} "
        f"refused with a GscError), {result['defect']} tracebacks, {result['hang']} hangs; "
        f"{result['cases_per_second']} cases/s; slowest case {result['slowest_case_seconds']} s "
        f"(#{result['slowest_case']}, reading only); peak RSS {result['peak_rss_mib']} MiB; "
        f"largest input {result['largest_input_bytes']} bytes"
    )
    return 1 if result["defect"] or result["hang"] else 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))  # (conftest's rewrite_log)
    sys.exit(main())
