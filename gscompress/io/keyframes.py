"""Keyframes a share carries: a few of the sender's frames, so that the receiver can refine the
merged map on the sender's views as well as its own.

Each carried frame is three messages at the frame's timestamp (its log time), which Foxglove
shows as they are:

- `/share/keyframe/color`: foxglove.CompressedImage, JPEG (`JPEG_QUALITY`);
- `/share/keyframe/depth`: foxglove.CompressedImage, 16-bit greyscale PNG in units of
  `DEPTH_UNIT_M` (0 = no depth; lossless at that unit);
- `/share/keyframe/pose`: foxglove.PoseInFrame, the sender's estimated camera-to-world pose.

The share's `/camera/calibration` is the camera of those images (the sender's working size).
Every image is checked before it is decoded: its format, and a size equal to the calibration's
(so a file cannot make the reader allocate more than the camera it declares, itself at most
`MAX_PIXELS`), at most `MAX_CARRIED` frames are read, and all of them together no more than the
log's bytes may decode to (`LogReader.budget`).
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from google.protobuf.message import DecodeError, Message

from gscompress.camera import Intrinsics
from gscompress.errors import LogFormatError
from gscompress.io.mcap_log import (
    CAMERA_FRAME,
    LogReader,
    LogWriter,
    decode_pose,
    pose_message,
)

TOPIC_KEYFRAME_COLOR = "/share/keyframe/color"
TOPIC_KEYFRAME_DEPTH = "/share/keyframe/depth"
TOPIC_KEYFRAME_POSE = "/share/keyframe/pose"
KEYFRAME_TOPICS = (TOPIC_KEYFRAME_COLOR, TOPIC_KEYFRAME_DEPTH, TOPIC_KEYFRAME_POSE)

JPEG_QUALITY = 90
"""Colour quality of a carried keyframe (Pillow's scale). What a keyframe, colour and depth,
takes in a share: docs/merge.md, "A share that carries the sender's keyframes"."""

DEPTH_UNIT_M = 0.001
"""A carried depth PNG counts in millimetres (deeper than 65.535 m is left out, as 0)."""

MAX_CARRIED = 64
"""The most keyframes a share may carry (more is refused: a share is a few of them)."""

MAX_PIXELS = 4096 * 4096
"""The largest carried image read (pixels): a camera declaring more is refused before any
image is decoded (16-bit depth at this size is 32 MiB)."""


_BYTES_PER_PIXEL = 3 + 2 + 12 + 4
"""What a carried frame takes a pixel once decoded: its JPEG and PNG pixels, then colour and depth
as float32."""


@dataclass(frozen=True)
class CarriedFrame:
    """One of the sender's frames in a share.

    Attributes:
        time_ns: the frame's timestamp (ns), which also names it in the sender's sequence.
        color: [H, W, 3] float32 in [0, 1].
        depth: [H, W] float32 metres, 0 where invalid.
        T_world_cam: [4, 4] float64 camera-to-world pose, in the share's world frame.
    """

    time_ns: int
    color: np.ndarray
    depth: np.ndarray
    T_world_cam: np.ndarray

    def moved(self, T_new_old: np.ndarray) -> CarriedFrame:
        """The frame with its pose moved into another world frame."""
        T = np.asarray(T_new_old, np.float64) @ self.T_world_cam
        return CarriedFrame(self.time_ns, self.color, self.depth, T)


def encode_color(color: np.ndarray) -> bytes:
    """JPEG bytes of a float colour image in [0, 1]."""
    from PIL import Image

    pixels = np.clip(np.round(np.asarray(color) * 255.0), 0, 255).astype(np.uint8)
    out = io.BytesIO()
    Image.fromarray(pixels, "RGB").save(out, format="JPEG", quality=JPEG_QUALITY)
    return out.getvalue()


def encode_depth(depth: np.ndarray) -> bytes:
    """16-bit PNG bytes of a depth image in metres (`DEPTH_UNIT_M`; invalid or beyond the
    range: 0)."""
    from PIL import Image

    units = np.round(np.nan_to_num(np.asarray(depth, np.float64), nan=0.0) / DEPTH_UNIT_M)
    units = np.where((units > 0) & (units <= 65535), units, 0).astype(np.uint16)
    out = io.BytesIO()
    Image.fromarray(units).save(out, format="PNG", optimize=True)
    return out.getvalue()


def carried_messages(frames: Sequence[CarriedFrame]) -> list[tuple[str, Message, int]]:
    """The messages of carried keyframes, (topic, message, log time): each frame's colour
    JPEG, depth PNG and pose. Encoded once, they go into every share file a byte budget's
    search tries (`write_carried`)."""
    if len(frames) > MAX_CARRIED:
        raise ValueError(f"a share carries at most {MAX_CARRIED} keyframes, got {len(frames)}")
    messages: list[tuple[str, Message, int]] = []
    for frame in frames:
        for topic, fmt, data in (
            (TOPIC_KEYFRAME_COLOR, "jpeg", encode_color(frame.color)),
            (TOPIC_KEYFRAME_DEPTH, "png", encode_depth(frame.depth)),
        ):
            image = CompressedImage(frame_id=CAMERA_FRAME, data=data, format=fmt)
            image.timestamp.FromNanoseconds(frame.time_ns)
            messages.append((topic, image, frame.time_ns))
        messages.append(
            (TOPIC_KEYFRAME_POSE, pose_message(frame.T_world_cam, frame.time_ns), frame.time_ns)
        )
    return messages


def write_carried(
    writer: LogWriter,
    frames: Sequence[CarriedFrame],
    intrinsics: Intrinsics,
    messages: Sequence[tuple[str, Message, int]] | None = None,
) -> int:
    """Write the carried keyframes and their camera into a share; returns their bytes (the
    messages' payloads). `messages`: theirs from `carried_messages`, when already encoded."""
    if messages is None:
        messages = carried_messages(frames)
    if not frames:
        return 0
    writer.write_calibration(intrinsics, frames[0].time_ns)
    return sum(
        writer.write_protobuf(topic, message, time_ns) for topic, message, time_ns in messages
    )


def decode_image(data: bytes, fmt: str, size: tuple[int, int], where: str) -> np.ndarray:
    """The pixels of a carried image, refused unless it is `fmt` ("jpeg": RGB; "png": 16-bit
    or 8-bit greyscale) of exactly `size` (W, H), checked before its pixels are decoded."""
    from PIL import Image, UnidentifiedImageError

    try:
        image = Image.open(io.BytesIO(data))
        kind = image.format
        if kind != {"jpeg": "JPEG", "png": "PNG"}[fmt] or image.size != size:
            raise LogFormatError(
                f"{where} is a {kind} image of {image.size[0]}x{image.size[1]}, not a {fmt} "
                f"of the share's camera, {size[0]}x{size[1]}"
            )
        modes = ("RGB",) if fmt == "jpeg" else ("I;16", "I", "L")
        if image.mode not in modes:
            raise LogFormatError(f"{where} has pixel mode {image.mode}, not {' or '.join(modes)}")
        image.load()
        return np.asarray(image)
    except (
        UnidentifiedImageError,
        Image.DecompressionBombError,
        OSError,
        ValueError,
        SyntaxError,
        EOFError,
    ) as exc:
        raise LogFormatError(f"{where} is not a readable {fmt} image ({exc})") from None


def read_carried(reader: LogReader) -> tuple[list[CarriedFrame], Intrinsics | None]:
    """The keyframes a share carries (in time order) and their camera; ([], camera) for a share
    that carries none.

    Raises:
        LogFormatError: more than `MAX_CARRIED`, a frame without its colour, depth or pose, a
            message that is not what its topic says, or images without a camera.
    """
    parts: dict[int, dict[str, object]] = {}
    names = {
        TOPIC_KEYFRAME_COLOR: "color",
        TOPIC_KEYFRAME_DEPTH: "depth",
        TOPIC_KEYFRAME_POSE: "pose",
    }
    for schema, channel, message in reader.iter_messages(list(KEYFRAME_TOPICS)):
        t = int(message.log_time)
        part = names[channel.topic]
        where = f"{reader.path}: {channel.topic} at {t} ns"
        if t not in parts and len(parts) >= MAX_CARRIED:
            raise LogFormatError(f"{reader.path} carries more than {MAX_CARRIED} keyframes")
        entry = parts.setdefault(t, {})
        if part in entry:
            raise LogFormatError(f"{where} comes twice")
        if part == "pose":
            entry[part] = decode_pose(schema, message, str(reader.path))
            continue
        if schema is None or schema.name != "foxglove.CompressedImage":
            raise LogFormatError(f"{where} is not a foxglove.CompressedImage")
        try:
            entry[part] = CompressedImage.FromString(message.data)
        except DecodeError:
            raise LogFormatError(f"{where} is corrupt") from None
    if not parts:
        return [], reader.read_intrinsics()
    camera = reader.read_intrinsics()
    if camera is None:
        raise LogFormatError(f"{reader.path} carries keyframes but no {CAMERA_FRAME} calibration")
    size = (camera.width, camera.height)
    if camera.width * camera.height > MAX_PIXELS:
        raise LogFormatError(
            f"{reader.path} carries keyframes of {size[0]}x{size[1]} pixels, more than the "
            f"{MAX_PIXELS} a share's keyframe may have"
        )
    reader.budget.check(
        len(parts) * camera.width * camera.height * _BYTES_PER_PIXEL,
        f"carries {len(parts)} keyframes of {size[0]}x{size[1]}",
    )
    frames = []
    for t in sorted(parts):
        entry = parts[t]
        missing = [p for p in ("color", "depth", "pose") if p not in entry]
        if missing:
            raise LogFormatError(f"{reader.path}: the keyframe at {t} ns has no {missing[0]}")
        color_msg, depth_msg = entry["color"], entry["depth"]
        assert isinstance(color_msg, CompressedImage) and isinstance(depth_msg, CompressedImage)
        where = f"{reader.path}: the keyframe at {t} ns"
        color = decode_image(color_msg.data, "jpeg", size, f"{where}, colour,")
        depth = decode_image(depth_msg.data, "png", size, f"{where}, depth,")
        pose = entry["pose"]
        assert isinstance(pose, np.ndarray)
        frames.append(
            CarriedFrame(
                t,
                (color.astype(np.float32) / 255.0),
                depth.astype(np.float32) * np.float32(DEPTH_UNIT_M),
                pose,
            )
        )
    return frames, camera
