"""The sequence-folder fuzz target: a small TUM folder (colour and depth PNGs, rgb.txt, depth.txt,
intrinsics.json, groundtruth.txt) edited file by file, and read as `gsc slam` reads it: opened,
then every frame loaded.

An input is the folder as a zip archive (stored, not compressed): the archive is only the
harness's way to hold a folder in bytes; the edits are to the files in it, and `read_sequence`
writes them back to a folder before reading.
"""

from __future__ import annotations

import io
import json
import struct
import tempfile
import zipfile
import zlib
from pathlib import Path
from typing import Any

from fuzz_mutations import INTERESTING, SPECIAL_FLOATS, Chooser, byte_mutation

WIDTH, HEIGHT = 16, 12
"""The frames' size."""


def valid_sequence(c: Chooser) -> bytes:
    """A TUM folder of 1 to 3 frames, with or without ground truth, max_depth and
    invalid_depth, as a zip archive."""
    key = (c.integer(1, 3), c.integer(0, 1), c.integer(0, 1))
    if key in _SEQUENCES:
        return _SEQUENCES[key]
    import numpy as np

    frames, with_poses, with_limits = key
    rng = np.random.default_rng(frames)
    files: dict[str, bytes] = {}
    for i in range(frames):
        colour = rng.integers(0, 256, (HEIGHT, WIDTH, 3), np.uint8)
        depth = rng.integers(0, 20000, (HEIGHT, WIDTH)).astype(np.uint16)
        files[f"rgb/{i}.png"] = _png(colour)
        files[f"depth/{i}.png"] = _png(depth)
    for kind in ("rgb", "depth"):
        lines = ["# timestamp filename"] + [f"{i / 30:.6f} {kind}/{i}.png" for i in range(frames)]
        files[f"{kind}.txt"] = ("\n".join(lines) + "\n").encode()
    if with_poses:
        rows = [f"{i / 30:.6f} {0.1 * i} 0 0 0 0 0 1" for i in range(frames)]
        files["groundtruth.txt"] = ("\n".join(rows) + "\n").encode()
    camera: dict[str, Any] = {"fx": 14.0, "fy": 14.0, "cx": 7.5, "cy": 5.5}
    camera |= {"width": WIDTH, "height": HEIGHT, "depth_scale": 5000.0}
    if with_limits:
        camera |= {"max_depth": 3.0, "invalid_depth": [65535, 1]}
    files["intrinsics.json"] = json.dumps(camera).encode()
    data = pack(files)
    _SEQUENCES[key] = data
    return data


_SEQUENCES: dict[tuple[int, int, int], bytes] = {}


def pack(files: dict[str, bytes]) -> bytes:
    """A folder's files as a stored zip archive."""
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as archive:
        for name, data in files.items():
            archive.writestr(name, data)
    return out.getvalue()


def unpack(data: bytes) -> dict[str, bytes]:
    """The files of a `pack`ed folder."""
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        return {info.filename: archive.read(info) for info in archive.infolist()}


def _png(pixels: Any, mode: str | None = None) -> bytes:
    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(pixels, mode).save(out, "PNG")
    return out.getvalue()


_CAMERA_VALUES = (
    *SPECIAL_FLOATS,
    1e-320,
    1e308,
    -1e308,
    0.5,
    1e5,
    1e7,
    8192,
    8193,
    2**31,
    2**64,
    16.5,
    "16",
    "x",
    None,
    True,
    [],
    {},
)
"""Values an intrinsics field is set to."""

_CAMERA_FIELDS = (
    "fx",
    "fy",
    "cx",
    "cy",
    "width",
    "height",
    "depth_scale",
    "max_depth",
    "invalid_depth",
)


def _edit_camera(files: dict[str, bytes], c: Chooser) -> None:
    """intrinsics.json with a field set to an edge value or removed, or replaced whole."""
    try:
        camera = json.loads(files["intrinsics.json"])
    except ValueError:  # (replaced whole by an earlier edit)
        camera = {}
    if not isinstance(camera, dict):
        camera = {}
    kind = c.integer(0, 5)
    if kind == 0:
        files["intrinsics.json"] = c.pick((b"", b"{", b"[]", b"null", b'{"camera": 1}'))
        return
    field = c.pick(_CAMERA_FIELDS)
    if kind == 1:
        camera.pop(field, None)
    elif field == "invalid_depth":
        camera[field] = c.pick(([], [0], [-1], [70000], [1.5], "65535", [65535] * 1000))
    else:
        camera[field] = c.pick(_CAMERA_VALUES)
    files["intrinsics.json"] = json.dumps(camera).encode()  # (NaN and Infinity as Python writes)


def _edit_list(files: dict[str, bytes], c: Chooser) -> None:
    """A line of rgb.txt, depth.txt or groundtruth.txt edited: a timestamp or a path replaced,
    the line repeated, deleted or cut, a field added."""
    names = [n for n in ("rgb.txt", "depth.txt", "groundtruth.txt") if n in files]
    name = c.pick(names)
    lines = files[name].decode("utf-8", "replace").splitlines()
    at = c.integer(0, max(len(lines) - 1, 0))
    fields = lines[at].split() if lines else []
    kind = c.integer(0, 5)
    if kind == 0 and fields:
        fields[0] = c.pick(("nan", "inf", "-1", "1e308", "x", "0", "0.033333", "1e-320", ""))
    elif kind == 1 and len(fields) > 1:
        fields[c.integer(1, len(fields) - 1)] = c.pick(
            ("../x.png", "/etc/hostname", "rgb/9.png", "depth/0.png", "rgb", "", "nan", "1e308")
        )
    elif kind == 2:
        lines[at:at] = lines[at : at + 1] * c.integer(1, 16)  # (a few: not the N x M blow-up)
    elif kind == 3 and lines:
        del lines[at]
    elif kind == 4:
        fields = fields[: c.integer(0, len(fields))]
    else:
        fields.append(c.pick(("extra", "1", "#")))
    if lines and kind not in (2, 3):
        lines[at] = " ".join(fields)
    files[name] = ("\n".join(lines) + "\n").encode()


def _edit_image(files: dict[str, bytes], c: Chooser) -> None:
    """A frame's image replaced: by one of another size (flat: small on disk, large decoded),
    mode or format, its header's size fields overwritten, cut short, or bytes edited."""
    import numpy as np

    name = c.pick(sorted(n for n in files if n.endswith(".png")))
    depth = name.startswith("depth/")
    data = files[name]
    kind = c.integer(0, 5)
    if kind == 0:
        size = c.pick(
            (
                (1, 1),
                (WIDTH + 1, HEIGHT),
                (WIDTH, HEIGHT + 1),
                (4096, 4096),
                (9000, 9000),
                (HEIGHT, WIDTH),
            )
        )
        files[name] = _flat_png(size, depth)
    elif kind == 1:
        shape = (HEIGHT, WIDTH)
        files[name] = c.pick(
            (
                _png(np.zeros((*shape, 4), np.uint8)),
                _png(np.zeros(shape, np.uint8)),
                _png(np.zeros(shape, np.uint8), "P"),
                _png(np.zeros(shape, np.uint16)),
                _png(np.full((*shape, 3), 200, np.uint8)),
                _jpeg(shape),
            )
        )
    elif kind == 2 and len(data) >= 33:  # IHDR's width or height, its CRC fixed or not
        at = c.pick((16, 20))
        value = c.pick((0, 1, WIDTH, 2**16, 2**31 - 1, 2**32 - 1, *INTERESTING[:6]))
        edited = data[:at] + struct.pack(">I", value & 0xFFFFFFFF) + data[at + 4 :]
        if c.integer(0, 1):
            crc = zlib.crc32(edited[12:29])
            edited = edited[:29] + struct.pack(">I", crc) + edited[33:]
        files[name] = edited
    elif kind == 3:
        files[name] = data[: c.integer(0, len(data))]
    else:
        files[name] = byte_mutation(data, c)


def _flat_png(size: tuple[int, int], depth: bool) -> bytes:
    """A black PNG of `size` (W, H), 16-bit grey for depth, else 8-bit RGB, compressed a row at
    a time (a large one is a few hundred kilobytes, and never whole in memory)."""
    key = (size, depth)
    if key not in _FLAT:
        width, height = size
        row = bytes(1 + width * (2 if depth else 3))  # (filter byte 0, then the pixels)
        deflate = zlib.compressobj(9)
        body = b"".join(deflate.compress(row) for _ in range(height)) + deflate.flush()
        header = struct.pack(
            ">IIBBBBB", width, height, 16 if depth else 8, 0 if depth else 2, 0, 0, 0
        )
        _FLAT[key] = (
            b"\x89PNG\r\n\x1a\n"
            + _chunk(b"IHDR", header)
            + _chunk(b"IDAT", body)
            + _chunk(b"IEND", b"")
        )
    return _FLAT[key]


def _chunk(kind: bytes, data: bytes) -> bytes:
    """A PNG chunk: length, kind, data, CRC."""
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


_FLAT: dict[tuple[tuple[int, int], bool], bytes] = {}


def _jpeg(shape: tuple[int, int]) -> bytes:
    import numpy as np
    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(np.zeros((*shape, 3), np.uint8)).save(out, "JPEG")
    return out.getvalue()


def mutate_sequence(data: bytes, c: Chooser) -> bytes:
    """One to three edits of a folder's files: intrinsics, lists, images."""
    files = unpack(data)
    for _ in range(c.integer(1, 3)):
        edit = c.pick((_edit_camera, _edit_list, _edit_image, _edit_image))
        edit(files, c)
    return pack(files)


def read_sequence(path: Path) -> None:
    """What `gsc slam` reads of a folder: the sequence opened and every frame loaded."""
    from gscompress.datasets import open_sequence

    with tempfile.TemporaryDirectory(dir=path.parent) as tmp:
        folder = Path(tmp) / "seq"
        for name, data in unpack(path.read_bytes()).items():
            target = folder / name
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(data)
        sequence = open_sequence(folder)
        for i in range(len(sequence)):
            sequence.frame(i)
