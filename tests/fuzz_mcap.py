"""The MCAP fuzz target: valid gscompress logs in several layouts (compression, indexes,
chunking), edited record by record, and read as `gsc info`, `prune`, `share`, `merge` and
`eval` read them."""

from __future__ import annotations

import io
import json
import struct
import tempfile
import zlib
from dataclasses import replace
from pathlib import Path
from typing import Any

from fuzz_mutations import SPECIAL_FLOATS, Chooser, byte_mutation, edge_value, overwrite


def valid_log(c: Chooser) -> bytes:
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
    size = len(inner) if c.integer(0, 3) else edge_value(c, 8)
    crc = c.pick((zlib.crc32(inner), 0, edge_value(c, 4)))
    return replace(
        chunk,
        compression=codec.split("-")[0],
        data=data,
        uncompressed_size=size,
        uncompressed_crc=crc,
    )


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
        record = overwrite(record, c, 0, 9)
    elif kind == 2:  # a message header field (channel, sequence, times)
        record = overwrite(record, c, 9, 9 + 22)
    elif kind == 3 and record[0] == 0x05:
        record = record[:31] + _mutate_cloud(record[31:], c)
        record = record[:1] + struct.pack("<Q", len(record) - 9) + record[9:]
    elif kind == 4:
        record = record[: c.integer(0, len(record))]
    else:
        record = byte_mutation(record, c)
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
        return byte_mutation(data, c)
    field = c.pick(list(cloud.fields))
    kind = c.integer(0, 7)
    if kind == 0:
        cloud.point_stride = c.pick(
            (
                0,
                1,
                cloud.point_stride * 2,
                cloud.point_stride + 4,
                cloud.point_stride - 4,
                2**32 - 1,
            )
        )
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
    values[key] = c.pick(
        (
            "",
            "{",
            "[]",
            "null",
            "1.0",
            "99.0",
            "[" * 5000,
            '{"poses": 1}',
            '[{"operation": 1}]',
            json.dumps({"tracking": {"use_ground_truth": "yes"}}),
            "\u0661.0",
            "1e999",
        )
    )
    return replace(record, metadata=values)


def mutate_log(data: bytes, c: Chooser) -> bytes:
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
                    records[i] = replace(records[i], data=byte_mutation(records[i].data, c))
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
            name = c.pick(
                (
                    "chunk_start_offset",
                    "chunk_length",
                    "message_start_time",
                    "message_end_time",
                    "uncompressed_size",
                    "compressed_size",
                )
            )
            setattr(index, name, edge_value(c, 8))
            out = serialize_as_is(records)
    elif index_kind == 1:
        out = byte_mutation(out, c)
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
