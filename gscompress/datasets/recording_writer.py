"""Writing a sequence as a recording: a ROS 2 bag (MCAP or sqlite), a ROS 1 bag or a Foxglove
MCAP, with the topics a RealSense driver (or a Foxglove app) publishes, for users who want to try
the recording path without a robot (`gsc convert`, `gsc synth --format`).

ROS bags are written with rosbags' writers: `/camera/color/image_raw` (Image rgb8, or
CompressedImage JPEG / PNG on `.../compressed`), `/camera/aligned_depth_to_color/image_raw`
(Image 32FC1 metres or 16UC1 millimetres, or compressedDepth PNG on `.../compressedDepth`),
`/camera/color/camera_info` (plumb_bob, zero distortion) and, where the sequence has ground truth,
`/tf` from `world` to `camera_color_optical_frame`. A Foxglove MCAP holds `/camera/color`,
`/camera/depth`, `/camera/calibration` and `/tf` in the Foxglove protobuf schemas. Each message's
log time is its stamp: the frame's time to the nanosecond (`seconds_to_stamp_ns`).

Colour is written from 8-bit values and 16UC1 depth refuses metres finer than a millimetre, so
that reading the recording gives the sequence's frames bit for bit (JPEG excepted).
"""

from __future__ import annotations

import io
import os
import shutil
import struct
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from gscompress.camera import rotmat_to_quat
from gscompress.datasets.base import RGBDSequence
from gscompress.datasets.recording import MM_PER_METRE, seconds_to_stamp_ns
from gscompress.errors import MissingDependencyError, OptionError, OutputError

CAMERA_FRAME = "camera_color_optical_frame"
WORLD_FRAME = "world"


@dataclass(frozen=True)
class RecordingFormat:
    """One way of writing a recording: what it is and what the output is (a folder or a file
    of `suffix`)."""

    name: str
    description: str
    folder: bool
    suffix: str


RECORDING_FORMATS: dict[str, RecordingFormat] = {
    f.name: f
    for f in (
        RecordingFormat("ros2", "ROS 2 bag, MCAP storage (a folder)", True, ""),
        RecordingFormat("ros2-sqlite", "ROS 2 bag, sqlite storage (a folder)", True, ""),
        RecordingFormat("ros1", "ROS 1 bag (a .bag file)", False, ".bag"),
        RecordingFormat("foxglove", "Foxglove-schema MCAP (a .mcap file)", False, ".mcap"),
    )
}
"""The recording formats `gsc convert` / `gsc synth --format` write (one table for both)."""
COLOR_CODINGS = ("rgb8", "jpeg", "png")
DEPTH_CODINGS = ("32FC1", "16UC1", "compressedDepth")
"""How colour and depth are carried: raw rgb8 / JPEG / PNG; 32FC1 metres, 16UC1 millimetres or
compressedDepth (16-bit PNG of millimetres behind image_transport's 12-byte header)."""


def check_recording_output(out: Path, fmt: str, force: bool) -> RecordingFormat:
    """The format, with `out` checked as its output (never a link; replaced only with `force`)."""
    if fmt not in RECORDING_FORMATS:
        raise OptionError(f"unknown recording format {fmt!r}: {', '.join(RECORDING_FORMATS)}")
    spec = RECORDING_FORMATS[fmt]
    if out.is_symlink():
        raise OutputError(f"{out} is a symbolic link; name the output itself")
    if spec.suffix and out.suffix.lower() != spec.suffix:
        raise OutputError(f"{out}: a {fmt} recording is a {spec.suffix} file; name it so")
    if spec.folder and out.suffix.lower() in (".mcap", ".db3", ".bag"):
        raise OutputError(f"{out}: a {fmt} bag is a folder; name it without {out.suffix}")
    if out.exists():
        if not force:
            raise OutputError(f"{out} exists; pass `force` to replace it", options=("force",))
        if out.is_dir() and not (out / "metadata.yaml").is_file():
            raise OutputError(f"{out} is a folder but not a ROS 2 bag; not replacing it")
    if not out.parent.is_dir():
        raise OutputError(f"directory {out.parent} does not exist")
    return spec


def write_recording(
    sequence: RGBDSequence,
    out: str | Path,
    fmt: str = "ros2",
    color: str = "rgb8",
    depth: str = "32FC1",
    force: bool = False,
    progress: Callable[[int], None] | None = None,
) -> Path:
    """Write `sequence` as a recording (see the module docstring), under a temporary name
    renamed into place when complete.

    Args:
        sequence: the frames to write (their working size).
        out: a folder for ros2 / ros2-sqlite, a `.bag` or `.mcap` file for ros1 / foxglove.
        fmt: a key of `RECORDING_FORMATS`.
        color: a `COLOR_CODINGS` entry.
        depth: a `DEPTH_CODINGS` entry.
        force: replace an existing recording at `out`.
        progress: called with 1 after each frame.

    Raises:
        OptionError: an unknown format or coding.
        OutputError: `out` exists (without `force`), is a link, has the wrong suffix; depth
            too fine or too far for 16UC1.
    """
    out = Path(out)
    spec = check_recording_output(out, fmt, force)
    if color not in COLOR_CODINGS or depth not in DEPTH_CODINGS:
        raise OptionError(f"colour is one of {COLOR_CODINGS}, depth one of {DEPTH_CODINGS}")
    if spec.name == "foxglove" and depth == "compressedDepth":
        raise OptionError("compressedDepth is a ROS transport: a Foxglove MCAP takes 32FC1/16UC1")
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    try:
        target = staging / out.name
        writer = _FoxgloveWriter(target) if spec.name == "foxglove" else _RosWriter(target, spec)
        with writer:
            for i in range(len(sequence)):
                _write_frame(writer, sequence, i, color, depth)
                if progress is not None:
                    progress(1)
        _replace(target, out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return out


def _replace(target: Path, out: Path) -> None:
    """Move the finished recording over `out` (an earlier one moved aside first)."""
    if out.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".old", dir=out.parent))
        os.rename(out, old / "x")
        os.rename(target, out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.rename(target, out)


def _write_frame(writer: Any, sequence: RGBDSequence, i: int, color: str, depth: str) -> None:
    """One frame's colour, depth, camera info and (with a pose) transform."""
    f = sequence.frame(i)
    stamp = seconds_to_stamp_ns(f.timestamp)
    rgb8 = np.clip(np.rint(f.color * 255.0), 0, 255).astype(np.uint8)
    writer.color(stamp, rgb8, color)
    writer.depth(stamp, f.depth, depth)
    writer.camera_info(stamp, sequence.intrinsics)
    if f.T_world_cam is not None:
        writer.transform(stamp, f.T_world_cam)


def millimetres(depth: np.ndarray) -> np.ndarray:
    """uint16 millimetres of metres depth (0 = none), refusing depth that 16UC1 would change."""
    valid = depth > 0
    mm = np.rint(np.where(valid, depth, 0.0).astype(np.float64) * MM_PER_METRE)
    if float(mm.max(initial=0.0)) > 65534:
        raise OutputError("depth beyond 65.534 m cannot be carried as 16UC1 millimetres")
    mm16 = mm.astype(np.uint16)
    back = (mm16.astype(np.float64) / MM_PER_METRE).astype(np.float32)
    if not np.array_equal(back[valid], depth[valid]):
        raise OutputError(
            "depth is finer than a millimetre: 16UC1 would change it; use `depth_encoding` 32FC1",
            options=("depth_encoding",),
        )
    return mm16


def _png(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG")
    return buf.getvalue()


def _jpeg(rgb8: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(rgb8, mode="RGB").save(buf, format="JPEG", quality=95)
    return buf.getvalue()


class _RosWriter:
    """A ROS 1 or ROS 2 bag through rosbags' writers, RealSense topic names."""

    def __init__(self, path: Path, spec: Any) -> None:
        try:
            from rosbags.typesys import Stores, get_types_from_msg, get_typestore
        except ImportError:  # pragma: no cover - a dependency of the package
            raise MissingDependencyError(
                "writing ROS bags needs rosbags: pip install rosbags"
            ) from None
        self.ros1 = spec.name == "ros1"
        self.store = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        if self.ros1:  # (noetic's store has tf's message under tf2_msgs only in ROS 2)
            self.store.register(
                get_types_from_msg(
                    "geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"
                )
            )
        if self.ros1:
            from rosbags.rosbag1 import Writer as Writer1

            self.writer: Any = Writer1(path)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.SQLITE3 if spec.name == "ros2-sqlite" else StoragePlugin.MCAP
            self.writer = Writer(path, version=9, storage_plugin=plugin)
        self.connections: dict[str, Any] = {}
        self.types = self.store.types

    def __enter__(self) -> _RosWriter:
        self.writer.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.writer.close()

    def _header(self, stamp: int, frame: str) -> Any:
        t = self.types["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9)
        extra = {"seq": 0} if self.ros1 else {}
        return self.types["std_msgs/msg/Header"](stamp=t, frame_id=frame, **extra)

    def _write(self, topic: str, msgtype: str, stamp: int, msg: Any) -> None:
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(
                topic, msgtype, typestore=self.store
            )
        serialize = self.store.serialize_ros1 if self.ros1 else self.store.serialize_cdr
        self.writer.write(self.connections[topic], stamp, serialize(msg, msgtype))

    def _image(self, topic: str, stamp: int, encoding: str, pixels: np.ndarray) -> None:
        h, w = pixels.shape[:2]
        data = np.ascontiguousarray(pixels).view(np.uint8).reshape(-1)
        msg = self.types["sensor_msgs/msg/Image"](
            header=self._header(stamp, CAMERA_FRAME),
            height=h,
            width=w,
            encoding=encoding,
            is_bigendian=0,
            step=data.size // h,
            data=data,
        )
        self._write(topic, "sensor_msgs/msg/Image", stamp, msg)

    def _compressed(self, topic: str, stamp: int, fmt: str, data: bytes) -> None:
        msg = self.types["sensor_msgs/msg/CompressedImage"](
            header=self._header(stamp, CAMERA_FRAME),
            format=fmt,
            data=np.frombuffer(data, dtype=np.uint8),
        )
        self._write(topic, "sensor_msgs/msg/CompressedImage", stamp, msg)

    def color(self, stamp: int, rgb8: np.ndarray, coding: str) -> None:
        """The colour image."""
        topic = "/camera/color/image_raw"
        if coding == "rgb8":
            self._image(topic, stamp, "rgb8", rgb8)
        else:
            data = _jpeg(rgb8) if coding == "jpeg" else _png(rgb8)
            self._compressed(f"{topic}/compressed", stamp, f"rgb8; {coding} compressed rgb8", data)

    def depth(self, stamp: int, depth: np.ndarray, coding: str) -> None:
        """The depth image, registered to colour (aligned_depth_to_color)."""
        topic = "/camera/aligned_depth_to_color/image_raw"
        if coding == "32FC1":
            self._image(topic, stamp, "32FC1", depth.astype("<f4"))
        elif coding == "16UC1":
            self._image(topic, stamp, "16UC1", millimetres(depth).astype("<u2"))
        else:
            data = struct.pack("<iff", 0, 0.0, 0.0) + _png(millimetres(depth))
            self._compressed(f"{topic}/compressedDepth", stamp, "16UC1; compressedDepth png", data)

    def camera_info(self, stamp: int, k: Any) -> None:
        """The colour camera's calibration (plumb_bob, zero distortion)."""
        K = np.array([k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1], dtype=np.float64)
        P = np.array([k.fx, 0, k.cx, 0, 0, k.fy, k.cy, 0, 0, 0, 1, 0], dtype=np.float64)
        R = np.eye(3).reshape(-1)
        names = ("D", "K", "R", "P") if self.ros1 else ("d", "k", "r", "p")
        values = dict(zip(names, (np.zeros(5), K, R, P), strict=True))
        roi = self.types["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        msg = self.types["sensor_msgs/msg/CameraInfo"](
            header=self._header(stamp, CAMERA_FRAME),
            height=k.height,
            width=k.width,
            distortion_model="plumb_bob",
            binning_x=0,
            binning_y=0,
            roi=roi,
            **values,
        )
        self._write("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo", stamp, msg)

    def transform(self, stamp: int, T_world_cam: np.ndarray) -> None:
        """/tf: world to the colour camera."""
        q = rotmat_to_quat(T_world_cam[:3, :3])  # w, x, y, z
        v = self.types["geometry_msgs/msg/Vector3"](*T_world_cam[:3, 3].tolist())
        r = self.types["geometry_msgs/msg/Quaternion"](x=q[1], y=q[2], z=q[3], w=q[0])
        stamped = self.types["geometry_msgs/msg/TransformStamped"](
            header=self._header(stamp, WORLD_FRAME),
            child_frame_id=CAMERA_FRAME,
            transform=self.types["geometry_msgs/msg/Transform"](translation=v, rotation=r),
        )
        msg = self.types["tf2_msgs/msg/TFMessage"](transforms=[stamped])
        self._write("/tf", "tf2_msgs/msg/TFMessage", stamp, msg)


class _FoxgloveWriter:
    """A Foxglove-schema MCAP (protobuf), Foxglove-style topic names."""

    def __init__(self, path: Path) -> None:
        from mcap.writer import CompressionType, Writer

        self.file = open(path, "xb")
        self.mcap = Writer(self.file, compression=CompressionType.ZSTD)
        self.mcap.start(profile="", library="gscompress")
        self.channels: dict[str, int] = {}

    def __enter__(self) -> _FoxgloveWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.mcap.finish()
        self.file.close()

    def _write(self, topic: str, message: Any, stamp: int) -> None:
        from mcap_protobuf.schema import build_file_descriptor_set

        if topic not in self.channels:
            schema = self.mcap.register_schema(
                message.DESCRIPTOR.full_name,
                "protobuf",
                build_file_descriptor_set(type(message)).SerializeToString(),
            )
            self.channels[topic] = self.mcap.register_channel(topic, "protobuf", schema)
        self.mcap.add_message(self.channels[topic], stamp, message.SerializeToString(), stamp)

    @staticmethod
    def _time(message: Any, stamp: int) -> None:
        message.timestamp.seconds, message.timestamp.nanos = divmod(stamp, 10**9)

    def _raw(self, topic: str, stamp: int, encoding: str, pixels: np.ndarray) -> None:
        from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

        h, w = pixels.shape[:2]
        data = np.ascontiguousarray(pixels).tobytes()
        m = RawImage(
            frame_id=CAMERA_FRAME,
            width=w,
            height=h,
            encoding=encoding,
            step=len(data) // h,
            data=data,
        )
        self._time(m, stamp)
        self._write(topic, m, stamp)

    def color(self, stamp: int, rgb8: np.ndarray, coding: str) -> None:
        """The colour image."""
        from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

        if coding == "rgb8":
            self._raw("/camera/color", stamp, "rgb8", rgb8)
            return
        data = _jpeg(rgb8) if coding == "jpeg" else _png(rgb8)
        m = CompressedImage(frame_id=CAMERA_FRAME, data=data, format=coding)
        self._time(m, stamp)
        self._write("/camera/color", m, stamp)

    def depth(self, stamp: int, depth: np.ndarray, coding: str) -> None:
        """The depth image (same camera frame as colour)."""
        if coding == "32FC1":
            self._raw("/camera/depth", stamp, "32FC1", depth.astype("<f4"))
        else:
            self._raw("/camera/depth", stamp, "16UC1", millimetres(depth).astype("<u2"))

    def camera_info(self, stamp: int, k: Any) -> None:
        """The colour camera's calibration."""
        from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration

        m = CameraCalibration(
            frame_id=CAMERA_FRAME,
            width=k.width,
            height=k.height,
            distortion_model="plumb_bob",
            D=[0.0] * 5,
            K=[k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1],
            R=[1, 0, 0, 0, 1, 0, 0, 0, 1],
            P=[k.fx, 0, k.cx, 0, 0, k.fy, k.cy, 0, 0, 0, 1, 0],
        )
        self._time(m, stamp)
        self._write("/camera/calibration", m, stamp)

    def transform(self, stamp: int, T_world_cam: np.ndarray) -> None:
        """/tf: world to the camera."""
        from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms

        q = rotmat_to_quat(T_world_cam[:3, :3])
        m = FrameTransforms()
        t = m.transforms.add(parent_frame_id=WORLD_FRAME, child_frame_id=CAMERA_FRAME)
        self._time(t, stamp)
        t.translation.x, t.translation.y, t.translation.z = T_world_cam[:3, 3].tolist()
        t.rotation.w, t.rotation.x, t.rotation.y, t.rotation.z = q.tolist()
        self._write("/tf", m, stamp)
