"""The RGB-D sequence interface, frame subsets, and image loading shared by every layout.

A sequence is a list of associated colour/depth frames with one set of pinhole intrinsics and,
when the dataset has it, a ground-truth camera-to-world pose per frame. `open_sequence`
(in `gscompress.datasets`) picks the reader by folder layout; every reader returns frames as
`Frame` records: colour [H, W, 3] float32 in [0, 1], depth [H, W] float32 metres (0 = invalid).
"""

from __future__ import annotations

import io
import math
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
from PIL import Image, UnidentifiedImageError

from gscompress.camera import Intrinsics
from gscompress.errors import DatasetError, InputError, OptionError, clipped
from gscompress.io.decode_budget import DecodeBudget, check_image
from gscompress.io.files import read_json


@dataclass(frozen=True)
class Frame:
    """One associated RGB-D frame.

    Attributes:
        index: 0-based position of the frame among all associated frames of the sequence,
            before any subset (`frames="odd"`, ...) is applied.
        timestamp: seconds.
        color: [H, W, 3] float32 in [0, 1].
        depth: [H, W] float32 metres along the optical axis; 0 where invalid.
        T_world_cam: [4, 4] float64 ground-truth camera-to-world pose, or None.
    """

    index: int
    timestamp: float
    color: np.ndarray
    depth: np.ndarray
    T_world_cam: np.ndarray | None

    def fingerprint(self) -> list[float]:
        """[mean valid depth in metres, mean R, G, B]: what tells this frame from another
        scene's with the same name and timing, rounded so that resampling by another version
        of the image library does not (see `same_fingerprint`)."""
        valid = self.depth[self.depth > 0]
        depth = float(valid.mean()) if valid.size else 0.0
        return [round(v, 4) for v in (depth, *self.color.reshape(-1, 3).mean(0).tolist())]


def recorded_fingerprint(value: object) -> list[float] | None:
    """A `Frame.fingerprint` as a log recorded it (`results.first_frame`), or None when there is
    none or it is not four finite numbers (a log from before it, or one edited by hand)."""
    if not isinstance(value, list) or len(value) != 4:
        return None
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value):
        return None
    return [float(v) for v in value] if all(np.isfinite(value)) else None


def same_fingerprint(a: Sequence[float], b: Sequence[float]) -> bool:
    """Whether two `Frame.fingerprint`s are one frame's: within 2 mm and 0.005 of colour."""
    return (
        len(a) == len(b) == 4
        and abs(a[0] - b[0]) <= 2e-3
        and all(abs(x - y) <= 5e-3 for x, y in zip(a[1:], b[1:], strict=True))
    )


@runtime_checkable
class RGBDSequence(Protocol):
    """What the SLAM front end and the evaluation need from a sequence."""

    @property
    def name(self) -> str:
        """A short name (usually the folder name)."""
        ...

    @property
    def intrinsics(self) -> Intrinsics:
        """Intrinsics at the working size (after any resize)."""
        ...

    @property
    def has_ground_truth(self) -> bool:
        """True when at least one selected frame has a ground-truth pose."""
        ...

    @property
    def indices(self) -> np.ndarray:
        """[N] int64: the original frame index of each selected frame."""
        ...

    @property
    def timestamps(self) -> np.ndarray:
        """[N] float64 seconds of each selected frame."""
        ...

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray]:
        """(timestamps [M], T_world_cam [M, 4, 4]) of the selected frames that have a pose."""
        ...

    def __len__(self) -> int: ...

    def frame(self, i: int) -> Frame:
        """The i-th selected frame (0 <= i < len)."""
        ...


def iter_frames(sequence: RGBDSequence) -> Iterator[Frame]:
    """Yield every frame of `sequence` in order."""
    for i in range(len(sequence)):
        yield sequence.frame(i)


# ---------------------------------------------------------------------------------------------
# Frame subsets


_SLICE_RE = re.compile(r"^\s*(-?\d*)\s*:\s*(-?\d*)\s*(?::\s*(-?\d*)\s*)?$")


@dataclass(frozen=True)
class FrameSelection:
    """A subset of frame indices: `all`, `odd`, `even` or a Python slice `START:STOP:STEP`.

    Indices are 0-based positions among the associated frames. In the two-agent protocol the
    odd-indexed frames (1, 3, 5, ...) go to agent A and the even-indexed ones (0, 2, 4, ...) to
    agent B, so the two agents see interleaved, disjoint halves of one sequence.
    """

    start: int | None = None
    stop: int | None = None
    step: int = 1
    spec: str = "all"

    def apply(self, n: int) -> np.ndarray:
        """[M] int64 selected indices out of `n` frames, increasing."""
        return np.arange(n, dtype=np.int64)[slice(self.start, self.stop, self.step)]

    def __str__(self) -> str:
        return self.spec


def parse_frames(spec: str | FrameSelection) -> FrameSelection:
    """Parse a frame-subset spec: `all`, `odd`, `even` or `START:STOP:STEP` (parts optional).

    `START:STOP:STEP` follows Python slicing on the 0-based frame index (`10:`, `:100`, `::5`,
    `-30:`); STEP must be positive so that frames stay in time order.

    Raises:
        InputError: anything else.
    """
    if isinstance(spec, FrameSelection):
        return spec
    text = str(spec).strip().lower()
    if text == "all":
        return FrameSelection(spec="all")
    if text == "odd":
        return FrameSelection(1, None, 2, spec="odd")
    if text == "even":
        return FrameSelection(0, None, 2, spec="even")
    shown = clipped(spec)
    m = _SLICE_RE.match(text)
    if m is None:
        raise InputError(f"bad frame subset {shown}: use all, odd, even or START:STOP:STEP")
    if max(len(part or "") for part in m.groups()) > 18:  # (int() refuses 4300 digits)
        raise InputError("bad frame subset: an index of over 18 digits")
    start = int(m.group(1)) if m.group(1) not in ("", "-") else None
    stop = int(m.group(2)) if m.group(2) not in ("", "-") else None
    if m.group(1) == "-" or m.group(2) == "-":
        raise InputError(f"bad frame subset {shown}: use all, odd, even or START:STOP:STEP")
    if m.group(3) == "-":
        raise InputError(f"bad frame subset {shown}: STEP must be a positive integer")
    step = int(m.group(3)) if m.group(3) else 1
    if step <= 0:
        raise InputError(f"bad frame subset {shown}: STEP must be a positive integer")
    if start is not None and stop is not None and (start < 0) == (stop < 0) and start >= stop:
        raise InputError(f"bad frame subset {shown}: it selects no frame (START >= STOP)")
    return FrameSelection(start, stop, step, spec=text)


# ---------------------------------------------------------------------------------------------
# Image loading and resizing


def load_color(path: Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """[H, W, 3] float32 in [0, 1] from an 8-bit colour (or grey) image file, refused before its
    pixels are decoded unless its header says `size` (W, H)."""
    img = _open_image(path, "colour", size)
    with img:
        if img.mode in ("RGBA", "P", "L", "LA", "CMYK", "YCbCr"):
            img = img.convert("RGB")
        if img.mode != "RGB":
            raise DatasetError(f"colour image {path} has unsupported mode {img.mode}")
        arr = np.asarray(img, dtype=np.uint8)
    return color_from_uint8(arr)


def color_from_uint8(rgb8: np.ndarray) -> np.ndarray:
    """[H, W, 3] float32 in [0, 1] from 8-bit RGB [H, W, 3] (every reader's one conversion)."""
    return rgb8.astype(np.float32) / np.float32(255.0)


DEFAULT_INVALID_DEPTH = (65535,)
"""Raw depth values that mark a pixel without a measurement besides 0: the 16-bit saturation
value, which Microsoft 7-Scenes and several RealSense and Kinect exports write there."""


@dataclass(frozen=True)
class DepthCoding:
    """How a sequence's 16-bit depth PNGs hold metres.

    Attributes:
        scale: units per metre (None: the layout's default, e.g. 5000 for TUM).
        invalid: raw values that mean "no measurement" (read as 0, as 0 itself is).
        max_depth: metres beyond which a measurement is dropped (read as 0); None: no limit.
    """

    scale: float | None = None
    invalid: tuple[int, ...] = DEFAULT_INVALID_DEPTH
    max_depth: float | None = None

    def with_default_scale(self, scale: float) -> DepthCoding:
        """This coding, its scale `scale` when it has none."""
        return self if self.scale is not None else replace(self, scale=scale)


def load_depth(
    path: Path,
    depth_scale: float,
    invalid: Sequence[int] = DEFAULT_INVALID_DEPTH,
    max_depth: float | None = None,
    size: tuple[int, int] | None = None,
) -> np.ndarray:
    """[H, W] float32 metres from a 16-bit depth PNG holding `depth_scale` units per metre;
    pixels of an `invalid` raw value or beyond `max_depth` metres read as 0 (no depth), as 0
    itself does. Refused before its pixels are decoded unless its header says `size` (W, H)."""
    img = _open_image(path, "depth", size)
    with img:
        if img.mode in ("L", "P", "RGB", "RGBA", "LA", "1"):
            raise DatasetError(
                f"depth image {path} is {img.mode} (8-bit); expected a 16-bit single-channel PNG"
            )
        if img.mode not in ("I;16", "I;16B", "I;16L", "I"):
            raise DatasetError(f"depth image {path} has unsupported mode {img.mode}")
        raw = np.asarray(img)
    if raw.dtype.kind == "i" and (raw.min(initial=0) < 0 or raw.max(initial=0) > 65535):
        raise DatasetError(f"depth image {path} has values outside 0..65535")
    return depth_from_units(raw, depth_scale, invalid, max_depth)


def depth_from_units(
    raw: np.ndarray,
    depth_scale: float,
    invalid: Sequence[int] = DEFAULT_INVALID_DEPTH,
    max_depth: float | None = None,
) -> np.ndarray:
    """[H, W] float32 metres from integer depth [H, W] of `depth_scale` units per metre (every
    reader's one conversion); `invalid` raw values and depths beyond `max_depth` read as 0."""
    depth = raw.astype(np.float64) / depth_scale
    dropped = np.isin(raw, invalid)
    if max_depth is not None:
        dropped |= depth > max_depth
    depth[dropped] = 0.0
    return depth.astype(np.float32)


def _open_image(path: Path, what: str, size: tuple[int, int] | None) -> Image.Image:
    """Open and decode an image file, its header checked first (`open_image_header`); every
    failure a DatasetError naming the file."""
    if not path.is_file():
        raise DatasetError(f"{what} image not found: {path}")
    return load_image(open_image_header(path, str(path), what, size), str(path), what)


def open_image_header(
    source: Path | bytes | bytearray | memoryview,
    where: str,
    what: str,
    size: tuple[int, int] | None,
    said: str = "the intrinsics are for",
    formats: tuple[str, ...] | None = None,
) -> Image.Image:
    """An image opened from its header alone, a file's or the bytes of a recording's message,
    refused before any pixel is decoded unless the header says `size` (W, H), when given, and
    its pixels are within what its bytes may decode to (`gscompress.io.decode_budget`, format
    "image"). The caller decodes it (`load_image`) and closes it.

    Args:
        source: the image file, or its bytes.
        where: the file or the message, for messages ("PATH", "PATH: TOPIC frame 3").
        what: "colour" or "depth".
        size: the size the frame must have (the camera's), or None.
        said: what says `size`, for messages ("the intrinsics are for", "the camera info says").
        formats: the formats accepted (PIL's names; None: any).

    Raises:
        DatasetError: not an image (of `formats`), another size, or over the decode budget.
    """
    if isinstance(source, Path):
        stream: Path | io.BytesIO = source
        input_bytes = source.stat().st_size
    else:
        stream, input_bytes = io.BytesIO(source), len(source)
    try:
        img = Image.open(stream, formats=formats)
    except UnidentifiedImageError as exc:
        kind = f"not a {' or '.join(formats)} image" if formats else str(exc)
        raise DatasetError(f"cannot read {what} image {where}: {kind}") from None
    except (OSError, ValueError, SyntaxError, EOFError, Image.DecompressionBombError) as exc:
        raise DatasetError(f"cannot read {what} image {where}: {exc}") from None
    try:
        if size is not None and img.size != tuple(size):
            raise DatasetError(
                f"{what} image {where} is {img.size[0]}x{img.size[1]} but {said} "
                f"{size[0]}x{size[1]}"
            )
        check_image(img, DecodeBudget("image", input_bytes, where, DatasetError), f"{what} image")
    except BaseException:
        img.close()
        raise
    return img


def load_image(img: Image.Image, where: str, what: str) -> Image.Image:
    """`img` (from `open_image_header`) with its pixels decoded; closed and refused in one
    line when they cannot be."""
    try:
        img.load()
    except (OSError, ValueError, SyntaxError, EOFError, Image.DecompressionBombError) as exc:
        img.close()
        raise DatasetError(f"cannot read {what} image {where}: {exc}") from None
    return img


def resize_color(color: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize colour [H, W, 3] float32: area average when shrinking, bilinear when enlarging."""
    h0, w0 = color.shape[:2]
    if (w0, h0) == (width, height):
        return color
    shrink = width <= w0 and height <= h0
    resample = Image.Resampling.BOX if shrink else Image.Resampling.BILINEAR
    channels = [
        np.asarray(
            Image.fromarray(np.ascontiguousarray(color[..., c], dtype=np.float32), mode="F").resize(
                (width, height), resample
            )
        )
        for c in range(color.shape[2])
    ]
    return np.clip(np.stack(channels, axis=-1), 0.0, 1.0).astype(np.float32)


def resize_depth(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize depth [H, W] by nearest neighbour (pixel-centre convention; never mixes depths)."""
    h0, w0 = depth.shape
    if (w0, h0) == (width, height):
        return depth
    rows = np.minimum(((np.arange(height) + 0.5) * (h0 / height)).astype(np.int64), h0 - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * (w0 / width)).astype(np.int64), w0 - 1)
    return depth[rows[:, None], cols[None, :]]


# ---------------------------------------------------------------------------------------------
# A sequence backed by image files


@dataclass(frozen=True)
class FrameRecord:
    """Where one associated frame lives on disk."""

    timestamp: float
    color_path: Path
    depth_path: Path
    T_world_cam: np.ndarray | None


class FileSequence:
    """An `RGBDSequence` over image files listed by a layout reader (TUM, Replica).

    Frames are loaded on demand; `frame(i)` checks from each image's header, before its pixels
    are decoded, that colour and depth have the intrinsics' size, and resizes to the working
    size when one was asked for.
    """

    def __init__(
        self,
        name: str,
        records: Sequence[FrameRecord],
        native_intrinsics: Intrinsics,
        depth: DepthCoding,
        selection: FrameSelection,
        size: tuple[int, int] | None = None,
    ) -> None:
        check_camera(native_intrinsics, depth, f"{name}: intrinsics")
        depth_scale = depth.scale
        if depth_scale is None:
            raise DatasetError(f"{name}: the depth scale is not known")
        self._depth = depth
        self._name = name
        self._all = list(records)
        self._indices = selection.apply(len(self._all))
        if len(self._indices) == 0:
            raise DatasetError(
                f"{name}: frame subset {selection} selects none of {len(self._all)} frames"
            )
        self._native = native_intrinsics
        self._depth_scale = float(depth_scale)
        w, h = size if size is not None else (native_intrinsics.width, native_intrinsics.height)
        self._intrinsics = native_intrinsics.scaled(w, h)

    @property
    def name(self) -> str:
        return self._name

    @property
    def intrinsics(self) -> Intrinsics:
        return self._intrinsics

    @property
    def native_intrinsics(self) -> Intrinsics:
        """Intrinsics at the size of the files."""
        return self._native

    @property
    def depth_scale(self) -> float:
        """Depth PNG units per metre."""
        return self._depth_scale

    @property
    def indices(self) -> np.ndarray:
        return self._indices.copy()

    @property
    def timestamps(self) -> np.ndarray:
        return np.array([self._all[i].timestamp for i in self._indices], dtype=np.float64)

    @property
    def has_ground_truth(self) -> bool:
        return any(self._all[i].T_world_cam is not None for i in self._indices)

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray]:
        recs = [self._all[i] for i in self._indices if self._all[i].T_world_cam is not None]
        stamps = np.array([r.timestamp for r in recs], dtype=np.float64)
        poses = np.array([r.T_world_cam for r in recs], dtype=np.float64).reshape(-1, 4, 4)
        return stamps, poses

    def __len__(self) -> int:
        return len(self._indices)

    def __iter__(self) -> Iterator[Frame]:
        return iter_frames(self)

    def frame(self, i: int) -> Frame:
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame {i} out of range for {len(self)} frames")
        index = int(self._indices[i])
        rec = self._all[index]
        native = (self._native.width, self._native.height)
        color = load_color(rec.color_path, native)
        depth = load_depth(
            rec.depth_path, self._depth_scale, self._depth.invalid, self._depth.max_depth, native
        )
        k = self._intrinsics
        return Frame(
            index=index,
            timestamp=rec.timestamp,
            color=resize_color(color, k.width, k.height),
            depth=resize_depth(depth, k.width, k.height),
            T_world_cam=None if rec.T_world_cam is None else rec.T_world_cam.copy(),
        )


MAX_SIDE = 8192
"""Largest image width or height accepted: beyond it one frame's buffers no longer fit in memory."""

MAX_FOCAL_PER_SIDE = 100
"""A focal length may be at most this many times the image's longer side (a field of view of
about 0.6 degrees: a telescope, not an RGB-D camera)."""

DEPTH_SCALES = (1.0, 1e5)
"""The plausible depth scales, units per metre: from metres (1) to 10 micrometre steps; real
sensors write millimetres (1000), TUM 5000, Replica 6553.5."""

MAX_DEPTH_M = 1e4
"""The largest plausible `max_depth` in metres."""


def check_camera(intrinsics: Intrinsics, depth: DepthCoding, where: str) -> None:
    """Refuse a camera no RGB-D sensor has, naming the field: focal lengths that are not finite
    or outside 1 pixel .. `MAX_FOCAL_PER_SIDE` times the longer side, a principal point that is
    not finite or more than half the image outside it, a size that is not positive or over
    `MAX_SIDE`, a depth scale outside `DEPTH_SCALES` or a `max_depth` that is not positive or
    over `MAX_DEPTH_M` (so that a bad value fails when the sequence is opened, not as a
    diverged optimisation minutes later).

    Raises:
        DatasetError: "`where`: `field` `value` ..." on one line.
    """
    k = intrinsics
    width, height = k.width, k.height
    for field, side in (("width", width), ("height", height)):
        if not 0 < side <= MAX_SIDE:
            raise DatasetError(f"{where}: {field} {side} is outside 1..{MAX_SIDE} pixels")
    longest = max(width, height) * MAX_FOCAL_PER_SIDE
    checks = [
        ("fx", k.fx, 1.0, longest, "pixels"),
        ("fy", k.fy, 1.0, longest, "pixels"),
        ("cx", k.cx, -width / 2, 1.5 * width, "pixels"),
        ("cy", k.cy, -height / 2, 1.5 * height, "pixels"),
    ]
    if depth.scale is not None:
        checks.append(("depth_scale", depth.scale, *DEPTH_SCALES, "units per metre"))
    if depth.max_depth is not None:
        checks.append(("max_depth", depth.max_depth, 0.0, MAX_DEPTH_M, "metres"))
    for field, value, low, high, unit in checks:
        if not (math.isfinite(value) and low <= value <= high and (field != "max_depth" or value)):
            raise DatasetError(
                f"{where}: {field} {float(value)!r} is not plausible for a {width}x{height} camera "
                f"(from {low:g} to {high:g} {unit})"
            )


def parse_size(text: str) -> tuple[int, int] | None:
    """(W, H) from `WxH` text (ASCII digits, at most 9 a side, x or X, spaces around), or None."""
    m = re.fullmatch(r"\s*([0-9]{1,9})\s*[xX]\s*([0-9]{1,9})\s*", text)
    return None if m is None else (int(m.group(1)), int(m.group(2)))


def enlargement_note(sequence: RGBDSequence) -> str | None:
    """What to warn of when a sequence's working size enlarges its frames, else None."""
    k = sequence.intrinsics
    native = getattr(sequence, "native_intrinsics", k)
    if k.width * k.height <= native.width * native.height:
        return None
    return (
        f"working size {k.width}x{k.height} enlarges {sequence.name}'s {native.width}x"
        f"{native.height} frames (more time, no more detail); --size {native.width}x"
        f"{native.height} keeps them"
    )


def check_size(size: tuple[int, int] | None) -> tuple[int, int] | None:
    """Validate a working size (W, H): positive, at most MAX_SIDE per side."""
    if size is None:
        return None
    try:
        w, h = (int(v) for v in size)
    except (TypeError, ValueError):
        raise OptionError(f"size must be (width, height), got {size!r}") from None
    if w <= 0 or h <= 0:
        raise OptionError(f"size must be positive, got {w}x{h}")
    if max(w, h) > MAX_SIDE:
        raise OptionError(f"size {w}x{h} is too large: at most {MAX_SIDE} pixels per side")
    return w, h


def read_intrinsics_file(path: Path) -> tuple[Intrinsics, DepthCoding]:
    """Intrinsics and how the depth PNGs hold metres, from a JSON file.

    Two schemas are accepted: flat `{"fx", "fy", "cx", "cy", "width", "height",
    "depth_scale"?, "invalid_depth"?, "max_depth"?}` (ours, written by `gsc synth`) and
    NICE-SLAM's `cam_params.json` `{"camera": {"fx", "fy", "cx", "cy", "w", "h", "scale"?}}`.
    `depth_scale` is in units per metre; `invalid_depth` lists the raw values that mean "no
    measurement" besides 0 (default [65535], the 16-bit saturation value; [] for none);
    `max_depth` drops measurements beyond so many metres.

    Raises:
        DatasetError: missing file, bad JSON, or missing / non-positive fields.
    """
    data = read_json(path, "intrinsics", DatasetError)
    if isinstance(data, dict) and isinstance(data.get("camera"), dict):
        data = dict(data["camera"])
        data.setdefault("width", data.get("w"))
        data.setdefault("height", data.get("h"))
        data.setdefault("depth_scale", data.get("scale"))
    if not isinstance(data, dict):
        raise DatasetError(f"intrinsics file {path}: expected a JSON object")
    names = ("fx", "fy", "cx", "cy", "width", "height", "depth_scale", "max_depth")
    try:
        if any(isinstance(data.get(k), bool) for k in names):
            raise TypeError("true/false is not a number")
        fx, fy, cx, cy, w, h = (float(data[k]) for k in names[:6])
        scale, limit = data.get("depth_scale"), data.get("max_depth")
        depth_scale = None if scale is None else float(scale)
        max_depth = None if limit is None else float(limit)
    except KeyError as exc:
        raise DatasetError(f"intrinsics file {path}: missing field {exc.args[0]!r}") from None
    except (TypeError, ValueError, OverflowError) as exc:
        raise DatasetError(f"intrinsics file {path}: bad value ({exc})") from None
    values = [fx, fy, cx, cy, w, h] + ([depth_scale] if depth_scale else [])
    if not np.all(np.isfinite(values)) or min(fx, fy, w, h) <= 0:
        raise DatasetError(f"intrinsics file {path}: focal lengths and size must be positive")
    if min(fx, fy) < 1:
        raise DatasetError(
            f"intrinsics file {path}: fx and fy are in pixels, at least 1 (normalised "
            "intrinsics? multiply fx and cx by the width, fy and cy by the height)"
        )
    if max(w, h) > MAX_SIDE or w != int(w) or h != int(h):
        raise DatasetError(f"intrinsics file {path}: width and height are whole, <= {MAX_SIDE}")
    width, height = int(w), int(h)
    if depth_scale is not None and depth_scale <= 0:
        raise DatasetError(f"intrinsics file {path}: depth_scale must be positive")
    if max_depth is not None and not (np.isfinite(max_depth) and max_depth > 0):
        raise DatasetError(f"intrinsics file {path}: max_depth must be positive metres")
    invalid = data.get("invalid_depth", list(DEFAULT_INVALID_DEPTH))
    if not isinstance(invalid, list) or not all(
        isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= 65535 for v in invalid
    ):
        raise DatasetError(
            f"intrinsics file {path}: invalid_depth must be a list of raw depth values in "
            f"0..65535, got {clipped(invalid)}"
        )
    coding = DepthCoding(depth_scale, tuple(invalid), max_depth)
    intrinsics = Intrinsics(fx, fy, cx, cy, width, height)
    check_camera(intrinsics, coding, f"intrinsics file {path}")
    return intrinsics, coding
