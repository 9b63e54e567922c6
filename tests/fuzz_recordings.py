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

The container edits live in tests/fuzz_containers.py.

A camera and its images are never both made large: a legitimate frame of 8192x8192 decodes to
more than the fuzz policy allows an input of a few hundred kilobytes (docs/fuzzing.md).
"""

from __future__ import annotations

import struct
import tempfile
import zlib
from pathlib import Path
from typing import Any

from fuzz_containers import mutate_mcap, mutate_metadata, mutate_ros1, mutate_sqlite
from fuzz_mutations import SPECIAL_FLOATS, Chooser, byte_mutation
from fuzz_sequences import _flat_png, _jpeg, _png, pack, unpack

WIDTH, HEIGHT = 16, 12
"""The frames' size."""
FORMATS = ("ros2", "ros2-sqlite", "ros1", "foxglove")
CAMERA_FRAME = "camera_color_optical_frame"


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
            edit = {".mcap": mutate_mcap, ".bag": mutate_ros1, ".db3": mutate_sqlite}.get(
                Path(name).suffix, mutate_metadata
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
