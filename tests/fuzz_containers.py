"""Container-level edits of the recordings fuzz target (tests/fuzz_recordings.py): an MCAP
file's records (the MCAP target's edits, or a chunk's zstd frame followed by a frame of a
gibibyte of zeros with its index kept honest), a ROS 1 bag's records (with the positions that
point at them recomputed or not), a sqlite bag's rows and tables, a ROS 2 bag's metadata.yaml;
and the bombs' helpers the budget tests share."""

from __future__ import annotations

import bz2
import sqlite3
import struct
import tempfile
import zlib
from dataclasses import replace
from pathlib import Path
from typing import Any

from fuzz_mcap import _inner_records, mcap_records, mutate_log, serialize_log
from fuzz_mutations import Chooser, byte_mutation, edge_value

GIB = 1 << 30


def zstd_zeros(n: int) -> bytes:
    """One zstd frame of `n` zero bytes (about 32 kB a gibibyte), made once per size."""
    if n not in _ZEROS:
        import zstandard

        compressor = zstandard.ZstdCompressor(level=1).compressobj()
        block = bytes(16 << 20)
        parts = [compressor.compress(block) for _ in range(n // len(block))]
        _ZEROS[n] = b"".join(parts) + compressor.flush()
    return _ZEROS[n]


def bz2_zeros(n: int) -> bytes:
    """bz2 streams in a row inflating to `n` zero bytes (a stream of 64 MiB, repeated)."""
    if n not in _BZ2_ZEROS:
        part = 64 << 20
        _BZ2_ZEROS[n] = bz2.compress(bytes(part)) * max(n // part, 1)
    return _BZ2_ZEROS[n]


_ZEROS: dict[int, bytes] = {}
_BZ2_ZEROS: dict[int, bytes] = {}


def replace_chunk(
    records: list[Any], at: int, data: bytes, compression: str, crc: int, size: int
) -> None:
    """The MCAP chunk `records[at]` holding `data` (compressed with `compression`, its CRC and
    size as given), and its chunk index saying so (rosbags reads the codec and the compressed
    length from the index)."""
    from mcap.records import Chunk, ChunkIndex

    chunks = [i for i, r in enumerate(records) if isinstance(r, Chunk)]
    indexes = [r for r in records if isinstance(r, ChunkIndex)]
    records[at] = replace(
        records[at],
        compression=compression,
        data=data,
        uncompressed_size=size,
        uncompressed_crc=crc,
    )
    if chunks.index(at) < len(indexes):
        index = indexes[chunks.index(at)]
        index.compression, index.compressed_size = compression, len(data)
        index.uncompressed_size = size


def mutate_mcap(data: bytes, c: Chooser) -> bytes:
    """An MCAP file's records edited (`fuzz_mcap.mutate_log`), or one chunk's records as a zstd
    frame declaring their size, perhaps followed by a frame of a gibibyte of zeros."""
    import zstandard
    from mcap.records import Chunk

    if c.integer(0, 2):
        return mutate_log(data, c)
    records = mcap_records(data)
    chunks = [i for i, r in enumerate(records) if isinstance(r, Chunk)]
    if not chunks:
        return byte_mutation(data, c)
    at = c.pick(chunks)
    inner = _inner_records(records[at])
    frame = zstandard.ZstdCompressor().compress(inner)
    tail = c.pick((zstd_zeros(GIB), frame, b"", zstd_zeros(16 << 20)))
    size = c.pick((len(inner), len(inner), len(inner) + len(tail), edge_value(c, 4)))
    replace_chunk(records, at, frame + tail, "zstd", zlib.crc32(inner), size)
    return serialize_log(records)


def ros1_records(data: bytes) -> list[list[Any]]:
    """A ROS 1 bag's records after its magic line: [header fields (name, value), data, the
    record's offset]; what follows a record cut short is dropped."""
    records, at = [], 13
    while at + 4 <= len(data):
        (header_len,) = struct.unpack_from("<I", data, at)
        end = at + 4 + header_len
        if end + 4 > len(data):
            break
        fields, pos = [], at + 4
        while pos + 4 <= end:
            (n,) = struct.unpack_from("<I", data, pos)
            name, _, value = data[pos + 4 : pos + 4 + n].partition(b"=")
            fields.append([name, value])
            pos += 4 + n
        (data_len,) = struct.unpack_from("<I", data, end)
        records.append([fields, data[end + 4 : end + 4 + data_len], at])
        at = end + 4 + data_len
    return records


def ros1_bytes(records: list[list[Any]], recompute: bool = True) -> bytes:
    """A ROS 1 bag of `records`; with `recompute`, the positions that point at records (the bag
    header's index_pos, each chunk info's chunk_pos) set to where the records now lie."""

    def record(fields: list[Any], body: bytes) -> bytes:
        header = b"".join(struct.pack("<I", len(n) + 1 + len(v)) + n + b"=" + v for n, v in fields)
        return struct.pack("<I", len(header)) + header + struct.pack("<I", len(body)) + body

    def op(r: list[Any]) -> int:
        return next((v[0] for n, v in r[0] if n == b"op" and v), -1)

    if recompute:
        at, moved = 13, {}
        for r in records:
            if op(r) == 3:  # the bag header is padded to 4096 bytes
                size = len(record(r[0], b""))
                r[1] = b" " * max(4096 - size, 0)
            moved[r[2]] = at
            at += len(record(r[0], r[1]))
        index = next((moved[r[2]] for r in records if op(r) == 7), at)
        for r in records:
            for field in r[0]:
                if op(r) == 3 and field[0] == b"index_pos":
                    field[1] = struct.pack("<Q", index)
                if op(r) == 6 and field[0] == b"chunk_pos":
                    old = struct.unpack("<Q", field[1])[0] if len(field[1]) == 8 else -1
                    field[1] = struct.pack("<Q", moved.get(old, old & (2**64 - 1)))
    return b"#ROSBAG V2.0\n" + b"".join(record(f, b) for f, b, _ in records)


def mutate_ros1(data: bytes, c: Chooser) -> bytes:
    """One record-level edit of a ROS 1 bag (see the module docstring)."""
    records = ros1_records(data)
    if not records:
        return byte_mutation(data, c)
    kind = c.integer(0, 4)
    chunks = [r for r in records if any(n == b"op" and v == b"\x05" for n, v in r[0])]
    recompute = c.integer(0, 3) > 0
    if kind <= 1 and chunks:  # a chunk compressed again, its declared size honest or not
        import lz4.frame

        r = c.pick(chunks)
        fields = dict((bytes(n), bytes(v)) for n, v in r[0])
        raw = r[1] if fields.get(b"compression") == b"none" else None
        if raw is None:
            return byte_mutation(data, c)
        codec = c.pick(("bz2", "lz4", "none"))
        body = {"bz2": bz2.compress, "lz4": lz4.frame.compress, "none": bytes}[codec](raw)
        if codec == "bz2" and c.integer(0, 2) == 0:
            body += bz2_zeros(GIB)
        size = len(raw) if c.integer(0, 2) else edge_value(c, 4)
        r[0] = [
            [
                n,
                codec.encode()
                if n == b"compression"
                else struct.pack("<I", size)
                if n == b"size"
                else v,
            ]
            for n, v in r[0]
        ]
        r[1] = body
    elif kind == 2:  # a header field of a fixed width set to an edge value
        r = c.pick(records)
        fixed = [f for f in r[0] if len(f[1]) in (1, 4, 8)]
        if fixed:
            field = c.pick(fixed)
            field[1] = edge_value(c, len(field[1])).to_bytes(len(field[1]), "little")
    elif kind == 3 and len(records) > 2:  # a record dropped or repeated
        i = c.integer(1, len(records) - 1)
        if c.integer(0, 1):
            del records[i]
        else:
            records.insert(i, [[list(f) for f in records[i][0]], records[i][1], -1])
    else:
        return byte_mutation(data, c)
    return ros1_bytes(records, recompute)


def mutate_sqlite(data: bytes, c: Chooser) -> bytes:
    """One edit of a ROS 2 sqlite bag's rows or tables."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "x.db3"
        path.write_bytes(data)
        try:
            db = sqlite3.connect(path)
            ids = [row[0] for row in db.execute("SELECT id FROM messages")]
            target = c.pick(ids) if ids else 0
            kind = c.integer(0, 7)
            if kind == 0:
                db.execute("DELETE FROM messages WHERE id = ?", (target,))
            elif kind == 1:
                db.execute(
                    "INSERT INTO messages (topic_id, timestamp, data) SELECT topic_id, "
                    "timestamp, data FROM messages WHERE id = ?",
                    (target,),
                )
            elif kind == 2:
                db.execute(
                    "UPDATE messages SET timestamp = ? WHERE id = ?",
                    (c.pick((0, -1, 2**63 - 1, 1)), target),
                )
            elif kind == 3:
                (blob,) = db.execute("SELECT data FROM messages WHERE id = ?", (target,)).fetchone()
                db.execute(
                    "UPDATE messages SET data = ? WHERE id = ?",
                    (byte_mutation(bytes(blob), c), target),
                )
            elif kind == 4:
                db.execute(
                    "UPDATE topics SET type = ? WHERE id = ?",
                    (
                        c.pick(
                            (
                                "sensor_msgs/msg/CameraInfo",
                                "sensor_msgs/msg/Image",
                                "sensor_msgs/msg/CompressedImage",
                                "tf2_msgs/msg/TFMessage",
                                "std_msgs/msg/String",
                                "x",
                            )
                        ),
                        c.integer(1, 5),
                    ),
                )
            elif kind == 5:
                db.execute(
                    "UPDATE topics SET name = ? WHERE id = ?",
                    (
                        c.pick(("/camera/depth", "", "/tf", "/camera/color/image_raw")),
                        c.integer(1, 5),
                    ),
                )
            elif kind == 6:
                db.execute(f"DROP TABLE {c.pick(('messages', 'topics', 'schema'))}")
            else:
                db.execute(
                    "UPDATE messages SET topic_id = ? WHERE id = ?",
                    (c.pick((0, 99, -1, 2)), target),
                )
            db.commit()
            db.close()
        except sqlite3.Error:
            return byte_mutation(data, c)
        return path.read_bytes()


def mutate_metadata(data: bytes, c: Chooser) -> bytes:
    """A ROS 2 bag's metadata.yaml with a field's value replaced, or replaced whole."""
    text = data.decode("utf-8", "replace")
    kind = c.integer(0, 3)
    if kind == 0:
        return c.pick(
            (
                b"",
                b"{",
                b"rosbag2_bagfile_information: 1\n",
                b"- a\n",
                b"a: &a [*a, *a]\nrosbag2_bagfile_information: {}\n",
            )
        )
    lines = text.splitlines()
    keyed = [i for i, line in enumerate(lines) if ":" in line]
    if not keyed:
        return data
    i = c.pick(keyed)
    key = lines[i].split(":", 1)[0]
    value = c.pick(
        ("", "0", "5000000", "-1", "FILE", "MESSAGE", "zstd", "[]", "{}", "x", str(2**64), "''")
    )
    if kind == 1:
        lines[i] = f"{key}: {value}"
    elif kind == 2:
        del lines[i]
    else:
        lines.insert(i, lines[i])
    return ("\n".join(lines) + "\n").encode()
