"""The recordings fuzz target: small valid recordings written by
`gscompress.datasets.recording_writer` (a ROS 2 bag with MCAP or sqlite storage, a ROS 1 bag, a
Foxglove MCAP; raw, JPEG or PNG colour; 32FC1, 16UC1 or compressedDepth depth), edited message
by message and container by container, and read as `gsc info` and `gsc slam` read them: the
recording described, opened (with /tf ground truth when it has /tf) and every frame decoded.

An input is the recording's files in a stored zip archive (a ROS 2 bag is a folder), as the
sequence target holds a folder. The edits:

- a message's fields (an image's size, step, encoding, byte order or bytes; a compressed
  image's format or payload: PNGs of another size, mode or bit depth, a JPEG, a compressedDepth
  header; a camera info's size, K, distortion; a transform's values and frames), the recording
  then written again with its container's own writer (rosbags, mcap), or the message's bytes
  edited raw;
- an MCAP file's records (`fuzz_mcap.mutate_log`: chunks, codecs, sizes, CRCs, indexes), or one
  chunk's zstd data followed by a frame of a gibibyte of zeros, its index kept honest;
- a ROS 1 bag's records: a header field set to an edge value, a record dropped or repeated, a
  chunk compressed again (bz2 or lz4, its declared size honest or not, perhaps followed by
  streams of a gibibyte of zeros), the positions that point at records recomputed or not;
- a sqlite bag's rows and tables (messages deleted, repeated, retimed or replaced, topic types
  and names changed, tables dropped) and its metadata.yaml's fields;
- files dropped, cut short or edited byte by byte.

A camera and its images are never both made large: a legitimate frame of 8192x8192 decodes to
more than the fuzz policy allows an input of a few hundred kilobytes (docs/fuzzing.md).
"""

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
from fuzz_mutations import SPECIAL_FLOATS, Chooser, byte_mutation, edge_value
from fuzz_sequences import _flat_png, _jpeg, _png, pack, unpack

WIDTH, HEIGHT = 16, 12
"""The frames' size."""
FORMATS = ("ros2", "ros2-sqlite", "ros1", "foxglove")
CAMERA_FRAME = "camera_color_optical_frame"
GIB = 1 << 30


# ---------------------------------------------------------------------------------------------
# Valid inputs


def valid_recording(c: Chooser) -> bytes:
    """A recording of 2 or 3 frames (16x12, depth in millimetres, with /tf) in one of the
    formats and codings `gsc convert` writes, as a zip archive of its files."""
    fmt = c.pick(FORMATS)
    color = c.pick(("rgb8", "jpeg", "png"))
    depth = c.pick(
        ("32FC1", "16UC1") if fmt == "foxglove" else ("32FC1", "16UC1", "compressedDepth")
    )
    key = (fmt, color, depth, c.integer(2, 3))
    if key not in _RECORDINGS:
        _RECORDINGS[key] = _write_valid(*key)
    return _RECORDINGS[key]


_RECORDINGS: dict[tuple[str, str, str, int], bytes] = {}


def _write_valid(fmt: str, color: str, depth: str, frames: int) -> bytes:
    from gscompress.datasets import open_sequence, write_tum_sequence
    from gscompress.datasets.recording_writer import write_recording
    from gscompress.datasets.synthetic import synthetic_sequence

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "mm"
        write_tum_sequence(
            synthetic_sequence(frames, (WIDTH, HEIGHT), seed=frames), folder, depth_scale=1000.0
        )
        name = {"ros2": "rec", "ros2-sqlite": "rec", "ros1": "rec.bag", "foxglove": "rec.mcap"}
        out = write_recording(open_sequence(folder), Path(tmp) / name[fmt], fmt, color, depth)
        return pack(_files_of(out))


def _files_of(out: Path) -> dict[str, bytes]:
    """A recording's files by their names in the archive (a bag folder's under its name)."""
    if out.is_dir():
        return {f"{out.name}/{p.name}": p.read_bytes() for p in sorted(out.iterdir())}
    return {out.name: out.read_bytes()}


def _materialise(files: dict[str, bytes], folder: Path) -> Path:
    """The files written under `folder`; the recording's path (a bag folder with its
    metadata.yaml, else its one storage file)."""
    for name, data in files.items():
        target = folder / name
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)
    folders = sorted({name.split("/")[0] for name in files if "/" in name})
    for name in folders:
        if (folder / name / "metadata.yaml").is_file():
            return folder / name
    stored = sorted(p for p in folder.rglob("*") if p.is_file() and p.suffix != ".yaml")
    return stored[0] if stored else folder / "nothing"


# ---------------------------------------------------------------------------------------------
# Message edits: the recording written again with one message changed


def _rewrite(files: dict[str, bytes], c: Chooser) -> None:
    """One message of the recording edited (`_edit_ros`, `_edit_foxglove`, or its bytes), the
    recording written again by its container's writer; unchanged when it no longer reads."""
    with tempfile.TemporaryDirectory() as tmp:
        source = _materialise(files, Path(tmp) / "in")
        out = Path(tmp) / "out" / source.name
        out.parent.mkdir()
        try:
            if source.suffix == ".mcap" and _profile(source) != "ros2":
                _rewrite_foxglove(source, out, c)
            else:
                _rewrite_ros(source, out, c)
        except Exception:  # (an earlier edit left nothing to read: the edit is skipped)
            return
        files.clear()
        files.update(_files_of(out))


def _profile(path: Path) -> str:
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return make_reader(f).get_header().profile


def _rewrite_ros(source: Path, out: Path, c: Chooser) -> None:
    from rosbags.highlevel import AnyReader

    with AnyReader([source]) as reader:
        messages = list(reader.messages())
        connections = list(reader.connections)  # (the reader clears its list on closing)
    ros1 = source.suffix == ".bag"
    store = _typestore(ros1)
    target = c.integer(0, len(messages) - 1)
    if ros1:
        from rosbags.rosbag1 import Writer as Writer1

        writer: Any = Writer1(out)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.SQLITE3 if any(source.glob("*.db3")) else StoragePlugin.MCAP
        writer = Writer(out, version=9, storage_plugin=plugin)
    with writer:
        added = {
            conn.id: writer.add_connection(conn.topic, conn.msgtype, typestore=store)
            for conn in connections
        }
        for k, (conn, time, raw) in enumerate(messages):
            if k == target:
                raw = _edit_raw_ros(store, conn.msgtype, raw, ros1, c)
            writer.write(added[conn.id], time, raw)


def _typestore(ros1: bool) -> Any:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if ros1:  # (as the recording writer registers it)
        store.register(
            get_types_from_msg(
                "geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"
            )
        )
    return store


def _edit_raw_ros(store: Any, msgtype: str, raw: Any, ros1: bool, c: Chooser) -> bytes:
    """A serialized ROS message with one field edited (`_edit_ros`), or its bytes edited."""
    if c.integer(0, 4) == 0:
        return byte_mutation(bytes(raw), c)
    try:
        deserialize = store.deserialize_ros1 if ros1 else store.deserialize_cdr
        serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
        msg = deserialize(raw, msgtype)
        _edit_ros(msg, msgtype, c)
        return bytes(serialize(msg, msgtype))
    except Exception:  # (a value its type cannot hold: the bytes are edited instead)
        return byte_mutation(bytes(raw), c)


SIDES = (0, 1, WIDTH + 1, HEIGHT, 2 * WIDTH, 8193, 65535, 2**31 - 1, 2**32 - 1)
"""Values an image's or a camera's width or height is set to (never one a large frame of
`_payload` has, so that a camera and its images are not made large together)."""
ENCODINGS = (
    "rgb8",
    "bgr8",
    "rgba8",
    "mono8",
    "mono16",
    "16UC1",
    "32FC1",
    "8UC3",
    "yuv422",
    "bayer_rggb8",
    "",
    "RGB8",
)
FORMATS_COMPRESSED = (
    "jpeg",
    "png",
    "rgb8; jpeg compressed bgr8",
    "16UC1; compressedDepth png",
    "32FC1; compressedDepth png",
    "16UC1; compressedDepth rvl",
    "compressedDepth",
    "bmp",
    "",
)


def _payload(c: Chooser) -> bytes:
    """A compressed image's bytes: a PNG or JPEG of the frame's size or another (a flat one of
    4096 or 9000 pixels a side is small on disk), of another mode or depth, a compressedDepth
    header before one, or bytes that are no image."""
    import numpy as np

    shape = (HEIGHT, WIDTH)
    kind = c.integer(0, 6)
    if kind == 0:
        return _flat_png(
            c.pick(((4096, 4096), (9000, 9000), (WIDTH + 1, HEIGHT), (1, 1))), c.integer(0, 1) == 1
        )
    if kind == 1:
        return c.pick(
            (
                _png(np.zeros(shape, np.uint16)),
                _png(np.zeros((*shape, 3), np.uint8)),
                _png(np.zeros((*shape, 4), np.uint8)),
                _png(np.zeros(shape, np.uint8), "P"),
                _jpeg(shape),
            )
        )
    if kind == 2:
        header = struct.pack(
            "<iff", c.pick((0, -1, 2**31 - 1)), c.pick(SPECIAL_FLOATS), c.pick(SPECIAL_FLOATS)
        )
        return header + _png(np.full(shape, c.pick((0, 1, 65535)), np.uint16))
    if kind == 3:
        return bytes(c.pick((0, 4, 12, 64)))
    if kind == 4:
        png = _png(np.zeros(shape, np.uint16))
        return png[: c.integer(0, len(png))]
    if kind == 5:  # a PNG whose header claims another size (CRC fixed or not)
        png = bytearray(_png(np.zeros(shape, np.uint16)))
        struct.pack_into(">I", png, c.pick((16, 20)), c.pick(SIDES[:7]) & 0xFFFFFFFF)
        if c.integer(0, 1):
            struct.pack_into(">I", png, 29, zlib.crc32(bytes(png[12:29])))
        return bytes(png)
    return b"\x89PNG\r\n\x1a\n" + bytes(c.integer(0, 64))


def _edit_ros(msg: Any, msgtype: str, c: Chooser) -> None:
    """One field of a deserialized Image, CompressedImage, CameraInfo or TFMessage edited."""
    import numpy as np

    def stamp(header: Any) -> None:
        header.stamp.sec = c.pick((0, 1, 2**31 - 1, 10**9))
        header.stamp.nanosec = c.pick((0, 999_999_999, 2**32 - 1))

    kind = msgtype.rsplit("/", 1)[-1]
    if kind == "Image":
        field = c.pick(
            ("width", "height", "step", "encoding", "is_bigendian", "data", "stamp", "frame_id")
        )
        if field in ("width", "height", "step"):
            setattr(msg, field, c.pick((*SIDES, getattr(msg, field) + 1)))
        elif field == "encoding":
            msg.encoding = c.pick(ENCODINGS)
        elif field == "is_bigendian":
            msg.is_bigendian = 1 - msg.is_bigendian
        elif field == "data":
            cut = c.integer(0, len(msg.data))
            msg.data = np.concatenate([msg.data[:cut], np.zeros(c.pick((0, 1, 64)), np.uint8)])
        elif field == "stamp":
            stamp(msg.header)
        else:
            msg.header.frame_id = c.pick(("", "elsewhere", CAMERA_FRAME + "_x"))
    elif kind == "CompressedImage":
        if c.integer(0, 1):
            msg.format = c.pick(FORMATS_COMPRESSED)
        else:
            msg.data = np.frombuffer(_payload(c), np.uint8)
    elif kind == "CameraInfo":
        field = c.pick(("width", "height", "k", "d", "distortion_model"))
        k_name = "K" if hasattr(msg, "K") else "k"
        d_name = "D" if hasattr(msg, "D") else "d"
        if field in ("width", "height"):
            setattr(msg, field, c.pick(SIDES))
        elif field == "k":
            values = np.array(getattr(msg, k_name), np.float64)
            values[c.integer(0, 8)] = c.pick(SPECIAL_FLOATS)
            setattr(msg, k_name, values)
        elif field == "d":
            setattr(msg, d_name, np.array(c.pick(([0.1, 0, 0, 0, 0], [], [0.0] * 1000))))
        else:
            msg.distortion_model = c.pick(("", "none", "equidistant", "fisheye", "x" * 5000))
    elif kind in ("TFMessage", "tfMessage") and msg.transforms:
        t = msg.transforms[0]
        field = c.pick(("translation", "rotation", "frames", "stamp"))
        if field == "translation":
            t.transform.translation.x = c.pick(SPECIAL_FLOATS)
        elif field == "rotation":
            r = t.transform.rotation
            r.x, r.y, r.z, r.w = (c.pick(SPECIAL_FLOATS) for _ in range(4))
        elif field == "frames":
            t.child_frame_id = c.pick(("", "world", "/" + CAMERA_FRAME, "loop"))
        else:
            stamp(t.header)


def _rewrite_foxglove(source: Path, out: Path, c: Chooser) -> None:
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    with open(source, "rb") as f:
        messages = list(make_reader(f).iter_messages())
    target = c.integer(0, len(messages) - 1)
    with open(out, "wb") as f:
        writer = Writer(
            f, compression=c.pick((CompressionType.ZSTD, CompressionType.LZ4, CompressionType.NONE))
        )
        writer.start(profile="", library="fuzz")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for k, (schema, channel, message) in enumerate(messages):
            if channel.id not in channels:
                assert schema is not None
                if schema.id not in schemas:
                    schemas[schema.id] = writer.register_schema(
                        schema.name, schema.encoding, schema.data
                    )
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id]
                )
            data = message.data
            if k == target:
                data = _edit_foxglove(schema.name if schema else "", data, c)
            writer.add_message(channels[channel.id], message.log_time, data, message.publish_time)
        writer.finish()


def _edit_foxglove(schema: str, data: bytes, c: Chooser) -> bytes:
    """A Foxglove message with one field edited, or its bytes edited."""
    from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    kinds = {
        "foxglove.RawImage": RawImage,
        "foxglove.CompressedImage": CompressedImage,
        "foxglove.CameraCalibration": CameraCalibration,
        "foxglove.FrameTransforms": FrameTransforms,
    }
    if schema not in kinds or c.integer(0, 4) == 0:
        return byte_mutation(data, c)
    m = kinds[schema]()
    m.ParseFromString(data)
    if isinstance(m, RawImage):
        field = c.pick(("width", "height", "step", "encoding", "data"))
        if field in ("width", "height", "step"):
            setattr(m, field, c.pick(SIDES))
        elif field == "encoding":
            m.encoding = c.pick(ENCODINGS)
        else:
            m.data = m.data[: c.integer(0, len(m.data))]
    elif isinstance(m, CompressedImage):
        if c.integer(0, 1):
            m.format = c.pick(FORMATS_COMPRESSED)
        else:
            m.data = _payload(c)
    elif isinstance(m, CameraCalibration):
        field = c.pick(("width", "height", "K", "D"))
        if field in ("width", "height"):
            setattr(m, field, c.pick(SIDES))
        elif field == "K":
            m.K[c.integer(0, len(m.K) - 1)] = c.pick(SPECIAL_FLOATS)
        else:
            m.D[0] = 0.5
    elif m.transforms:
        t = m.transforms[0]
        t.rotation.w, t.rotation.x = c.pick(SPECIAL_FLOATS), c.pick(SPECIAL_FLOATS)
        t.translation.x = c.pick(SPECIAL_FLOATS)
    return m.SerializeToString()


# ---------------------------------------------------------------------------------------------
# Container edits


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


def _mutate_mcap(data: bytes, c: Chooser) -> bytes:
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


def _mutate_ros1(data: bytes, c: Chooser) -> bytes:
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


def _mutate_sqlite(data: bytes, c: Chooser) -> bytes:
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


def _mutate_metadata(data: bytes, c: Chooser) -> bytes:
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


def mutate_recording(data: bytes, c: Chooser) -> bytes:
    """A message edited (two cases in three), then up to two edits of the files (at least one
    without a message edited; see the module docstring)."""
    files = unpack(data)
    rewritten = c.integer(0, 2) > 0
    if rewritten:
        _rewrite(files, c)
    for _ in range(c.integer(0 if rewritten else 1, 2)):
        if not files:
            break
        name = c.pick(sorted(files))
        kind = c.integer(0, 9)
        if kind == 0:
            del files[name]
        elif kind == 1:
            files[name] = files[name][: c.integer(0, len(files[name]))]
        elif kind == 2:
            files[name] = byte_mutation(files[name], c)
        else:
            edit = {".mcap": _mutate_mcap, ".bag": _mutate_ros1, ".db3": _mutate_sqlite}.get(
                Path(name).suffix, _mutate_metadata
            )
            try:
                files[name] = edit(files[name], c)
            except Exception:  # (an earlier edit broke the structure this one edits)
                files[name] = byte_mutation(files[name], c)
    return pack(files)


# ---------------------------------------------------------------------------------------------
# The read


def read_recording(path: Path) -> None:
    """What `gsc info` and `gsc slam` read of a recording: it described, then opened (with
    /tf ground truth when it has /tf) and every frame decoded."""
    from gscompress.datasets import RecordingOptions, open_sequence
    from gscompress.datasets.recording import describe_recording

    with tempfile.TemporaryDirectory(dir=path.parent) as tmp:
        recording = _materialise(unpack(path.read_bytes()), Path(tmp))
        described = describe_recording(recording)
        has_tf = any(t["kind"] == "tf" for t in described["topics"])
        frames = ("world", CAMERA_FRAME) if has_tf else None
        sequence = open_sequence(recording, recording=RecordingOptions(gt_frames=frames))
        try:
            for i in range(len(sequence)):
                sequence.frame(i)
            sequence.ground_truth()
        finally:
            sequence.close()  # type: ignore[attr-defined]
