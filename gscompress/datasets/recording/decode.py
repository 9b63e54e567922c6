"""Decoding a recording's images, bounded: sizes and headers checked before pixels. Colour comes
out as [H, W, 3] float32 in [0, 1] and depth as [H, W] float32 metres (0 = no depth), as every
reader's frames; intrinsics come from a camera info."""

from __future__ import annotations

import struct
from typing import Any

import numpy as np
from PIL import Image

from gscompress.camera import Intrinsics
from gscompress.datasets.base import (
    DEFAULT_INVALID_DEPTH,
    DepthCoding,
    check_camera,
    color_from_uint8,
    depth_from_units,
    load_image,
    open_image_header,
)
from gscompress.datasets.recording.messages import CameraMessage, ImageMessage
from gscompress.errors import DatasetError, clipped

MM_PER_METRE = 1000.0
_COMPRESSED_DEPTH_HEADER = 12  # image_transport's ConfigHeader: int32 format, float32[2]

COLOR_ENCODINGS = {
    "rgb8": (3, (0, 1, 2)),
    "bgr8": (3, (2, 1, 0)),
    "rgba8": (4, (0, 1, 2)),
    "bgra8": (4, (2, 1, 0)),
    "mono8": (1, (0, 0, 0)),
}
"""Raw colour encodings: channels per pixel and which give R, G, B."""
DEPTH_ENCODINGS: dict[str, np.dtype[Any]] = {
    "16UC1": np.dtype("u2"),
    "mono16": np.dtype("u2"),
    "32FC1": np.dtype("f4"),
}
"""Raw depth encodings: 16UC1 / mono16 in millimetres, 32FC1 in metres."""
UNDISTORTED_MODELS = (
    "",
    "none",
    "plumb_bob",
    "rational_polynomial",
    "equidistant",
    "kannala_brandt",
)
"""Distortion models accepted when every coefficient is zero (images used as they are)."""


def _raw_pixels(msg: ImageMessage, dtype: np.dtype, channels: int, what: str) -> np.ndarray:
    """[H, W, C] of a raw image, its size, step and byte count checked first."""
    w, h = msg.width, msg.height
    row = w * channels * dtype.itemsize
    data = memoryview(msg.data).cast("B") if not isinstance(msg.data, np.ndarray) else msg.data
    if msg.step < row or len(data) < msg.step * (h - 1) + row:
        raise DatasetError(
            f"{what}: a {w}x{h} {msg.encoding} image with step {msg.step} holds {len(data)} bytes"
        )
    buf = np.frombuffer(data, dtype=np.uint8, count=msg.step * (h - 1) + row)
    rows = np.lib.stride_tricks.as_strided(buf, (h, row), (msg.step, 1))
    if dtype.itemsize > 1:
        dtype = dtype.newbyteorder(">" if msg.big_endian else "<")
    pixels = np.ascontiguousarray(rows).view(dtype)
    return pixels.reshape(h, w, channels)


def open_image(data: Any, expected: tuple[int, int], what: str, kind: str) -> Image.Image:
    """A compressed `kind` ("colour", "depth") image decoded, its PNG or JPEG header checked
    first, as a folder's frames are (`gscompress.datasets.base.open_image_header`): its size
    against `expected` (W, H), its pixels against what its bytes may decode to."""
    img = open_image_header(
        memoryview(data).cast("B"), what, kind, expected, "the camera info says", ("PNG", "JPEG")
    )
    return load_image(img, what, kind)


def decode_color(msg: ImageMessage, expected: tuple[int, int], what: str) -> np.ndarray:
    """[H, W, 3] float32 in [0, 1] of a colour message of size `expected` (W, H)."""
    if msg.compressed:
        if "compresseddepth" in msg.encoding.lower():
            raise DatasetError(f"{what}: a compressedDepth image on the colour topic")
        with open_image(msg.data, expected, what, "colour") as img:
            if img.mode != "RGB":
                if img.mode not in ("L", "P", "RGBA", "LA", "CMYK", "YCbCr"):
                    raise DatasetError(f"{what}: colour image of mode {img.mode}")
                img = img.convert("RGB")
            rgb8 = np.asarray(img, dtype=np.uint8)
        return color_from_uint8(rgb8)
    found = COLOR_ENCODINGS.get(msg.encoding)
    if found is None:
        raise DatasetError(
            f"{what}: colour encoding {clipped(msg.encoding)} is not one of "
            f"{', '.join(COLOR_ENCODINGS)} (or JPEG / PNG)"
        )
    _check_expected(msg, expected, what)
    channels, pick = found
    pixels = _raw_pixels(msg, np.dtype("u1"), channels, what)
    return color_from_uint8(np.ascontiguousarray(pixels[..., list(pick)]))


def _check_expected(msg: ImageMessage, expected: tuple[int, int], what: str) -> None:
    if (msg.width, msg.height) != expected:
        raise DatasetError(
            f"{what}: image is {msg.width}x{msg.height} but the camera info says "
            f"{expected[0]}x{expected[1]}"
        )


def decode_depth(msg: ImageMessage, expected: tuple[int, int], what: str) -> np.ndarray:
    """[H, W] float32 metres (0 = no depth) of a depth message of size `expected` (W, H)."""
    if msg.compressed:
        return _decode_compressed_depth(msg, expected, what)
    dtype = DEPTH_ENCODINGS.get(msg.encoding)
    if dtype is None:
        raise DatasetError(
            f"{what}: depth encoding {clipped(msg.encoding)} is not 16UC1 (millimetres) or "
            "32FC1 (metres)"
        )
    _check_expected(msg, expected, what)
    raw = _raw_pixels(msg, dtype, 1, what)[..., 0]
    if dtype.kind == "u":
        return depth_from_units(raw.astype(np.uint16), MM_PER_METRE, DEFAULT_INVALID_DEPTH)
    return metres_depth(raw)


def metres_depth(raw: np.ndarray) -> np.ndarray:
    """float32 metres with 0, negative and non-finite values read as no depth (0)."""
    depth = raw.astype(np.float32)
    depth[~(np.isfinite(depth) & (depth > 0))] = 0.0
    return depth


def _decode_compressed_depth(msg: ImageMessage, expected: tuple[int, int], what: str) -> np.ndarray:
    """compressedDepth (header + PNG) or a plain 16-bit PNG of millimetres."""
    fmt = msg.encoding.lower()
    data = bytes(msg.data)
    inverse: tuple[float, float] | None = None
    if "compresseddepth" in fmt:
        if "rvl" in fmt:
            raise DatasetError(f"{what}: compressedDepth RVL is not read; record it as PNG")
        if len(data) < _COMPRESSED_DEPTH_HEADER:
            raise DatasetError(f"{what}: a compressedDepth message of {len(data)} bytes")
        _fmt, quant_a, quant_b = struct.unpack_from("<iff", data)
        data = data[_COMPRESSED_DEPTH_HEADER:]
        if fmt.split(";")[0].strip().upper() == "32FC1":
            inverse = (quant_a, quant_b)
    elif "png" not in fmt:
        raise DatasetError(f"{what}: compressed depth of format {clipped(msg.encoding)}: PNG only")
    header = open_image_header(data, what, "depth", expected, "the camera info says", ("PNG",))
    with header as img:
        if img.mode not in ("I;16", "I;16B", "I;16L", "I"):
            raise DatasetError(f"{what}: compressed depth must be a 16-bit PNG, got {img.mode}")
        raw = np.asarray(load_image(img, what, "depth"))
    if raw.min(initial=0) < 0 or raw.max(initial=0) > 65535:
        raise DatasetError(f"{what}: depth values outside 0..65535")
    raw16 = raw.astype(np.uint16)
    if inverse is None:
        return depth_from_units(raw16, MM_PER_METRE, DEFAULT_INVALID_DEPTH)
    # image_transport's quantised inverse depth: depth = A / (v - B), v = 0 for none
    a, b = inverse
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.float32(a) / (raw16.astype(np.float32) - np.float32(b))
    depth[raw16 == 0] = 0.0
    return metres_depth(depth)


def intrinsics_of(info: CameraMessage, topic: str) -> Intrinsics:
    """Pinhole intrinsics of a camera info, refusing a distortion this reader does not undo."""
    what = f"camera info {topic}"
    if len(info.K) != 9:
        raise DatasetError(f"{what}: K must be 9 numbers, got {len(info.K)}")
    fx, _, cx, _, fy, cy, *_ = info.K
    k = Intrinsics(float(fx), float(fy), float(cx), float(cy), info.width, info.height)
    check_camera(k, DepthCoding(), what)
    model = info.model.strip().lower()
    if any(v != 0 for v in info.D) or model not in UNDISTORTED_MODELS:
        raise DatasetError(
            f"{what}: distortion {clipped(info.model)} with coefficients {clipped(list(info.D))} "
            "is not undone here; record rectified images (zero coefficients are fine)"
        )
    return k
