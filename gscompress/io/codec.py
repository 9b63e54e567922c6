"""Map codecs: how a `/gaussians` snapshot stores its Gaussians.

- `fp32`, `fp16`: a foxglove.PointCloud of packed records (`gscompress.io.columns`), which
  Foxglove draws as it is.
- `compact`: our own protobuf message `gscompress.CompactGaussians`
  (schemas/compact_gaussians.v1.proto), column by column, each attribute quantised and
  zstd-compressed on its own. This module encodes and decodes it; docs/codecs.md gives the rules
  and the measurements behind the bit widths.

Compact columns, in the order of the Gaussians along a Morton (Z-order) curve of their grid
positions:

- `position`: means as integers on a grid (origin and step recorded), as sorted Morton codes,
  each stored as its difference from the previous one. The step is `POSITION_STEP_FRACTION` of
  the map's median Gaussian scale unless given, and grows only when the map spans more than
  2^21 steps along an axis.
- `log_scale` (1 component isotropic, 3 anisotropic), `opacity` (in sigmoid space), `f_dc`
  (in asinh space: `asinh-linear`), `f_rest`: `linear` codes of `bits` bits between each
  component's recorded low and high.
- `rotation` (anisotropic only): `smallest-three` in SPZ's layout, 2 bits for the largest
  component's index and a sign and 9 bits of magnitude for each of the other three, 32 in all.
- `id` (optional): `delta`, the difference from the previous id modulo 2^32.
- the PWAS state (optional): the score `importance` as `log-linear` codes (code 0 is a zero
  score), and with the sums also the proximity weight sum `importance_weight` and the alpha x T
  sum `alpha_t_sum`, each in 8 bits: a receiver keeps accumulating from importance_sum = score x
  (weight + eps), and a merge weighs each Gaussian's evidence by its alpha x T sum. The bits are
  recorded per column, so messages whose score has 16 bits (written before the score had 8) and
  those that hold the three sums as float32 (`raw`) still decode, exactly.

Every multi-byte column is stored as its byte planes (all first bytes, then all second bytes...),
which zstd compresses far better than interleaved integers. Decoding checks each count, size and
range against the message before allocating: a share comes from another robot.

numpy + zstandard + protobuf only (no torch).
"""

from __future__ import annotations

import io
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import zstandard
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.message import DecodeError, Message

from gscompress.errors import GscError, InputError, MapError
from gscompress.gaussians import PWAS_EPS, SH_REST_COUNTS, GaussianMap

CODECS = ("fp32", "fp16", "compact")
"""Map codecs, from the largest to the smallest."""

COMPACT_SCHEMA = "gscompress.CompactGaussians"
"""Schema name of the compact map message in a log."""

COMPACT_VERSION = 1
"""Version of the compact message this module writes and reads."""

POSITION_STEP_FRACTION = 1 / 128
"""Default position grid step as a fraction of the map's median Gaussian scale (the standard
deviation exp(log_scale)): the position error is at most half a step per axis, 1/256 of a typical
Gaussian's own scale (positions set most of a compact map's error: docs/codecs.md)."""

MAX_POSITION_BITS = 21
"""Largest grid size per axis, in bits (three axes interleave into a 63-bit Morton code)."""

BITS = {"log_scale": 8, "opacity": 6, "f_dc": 7, "f_rest": 8, "importance": 8,
        "importance_weight": 8, "alpha_t_sum": 8}  # fmt: skip
"""Default quantisation bits of each linear and log-linear column (chosen by bench/codec.py and
the probes in docs/codecs.md): an 8-bit log code keeps a score or a sum within 3% over the
1e-3..1e4 span of real maps, and a 30% prune of the decoded scores keeps 98% of the Gaussians
the exact ones keep. 7-bit asinh colours and 8-bit log scales cost the picture 0.013 dB on the
room's agent A map and 0.027 on office frag1's, where 8-bit linear colours and 7-bit scales
cost 0.042 and 0.055, for 0.2-0.4 more bytes a Gaussian."""

COLOUR_TRANSFORM = "asinh-linear"
"""How `f_dc` is coded: linear in asinh(f_dc), fine near the colours of [0, 1] (|f_dc| < 1.8)
and coarse in the long tails optimisation leaves (f_dc up to 20 on real maps), which would
otherwise stretch a linear code's range and coarsen every colour."""

_MAX_ASINH = float(np.arcsinh(np.float64(np.finfo(np.float32).max)))
"""Largest |asinh(value)| an `asinh-linear` column may code (sinh of it is float32's largest)."""

SUMS = ("importance_weight", "alpha_t_sum")
"""The PWAS sums a compact message codes beside the score (importance_sum = score x (W + eps))."""

RAW_SUMS = ("importance_sum", "importance_weight", "alpha_t_sum")
"""The PWAS sums as float32 in messages written before they were coded (still read)."""

ZSTD_LEVEL = 3
"""zstd level of every column."""

MAX_GAUSSIANS = 1 << 28
"""Most Gaussians a compact message may declare."""

MIN_BYTES_PER_GAUSSIAN = 1 / 16
"""A compact message must hold at least this many bytes per Gaussian it declares (half a bit;
real maps take 5-20 bytes): a small message cannot make the reader allocate a huge map."""

ROTATION_BITS = 10
"""Bits of each of the three smallest quaternion components in a `smallest-three` code (a sign
and 9 bits of magnitude)."""

_SQRT1_2 = np.float32(np.sqrt(0.5))
"""The largest the three smallest components of a unit quaternion can be."""

_FLOAT32_MAX = float(np.finfo(np.float32).max)
"""Largest value a decoded attribute may take (a map holds float32)."""

_MAX_LOG_SCORE = 88.0
"""Largest log score a `log-linear` column may code (exp of it is a finite float32)."""

_SIGMOID_EPS = 1e-7
"""Opacities are coded in [eps, 1 - eps], so that every code has a finite logit."""


@dataclass(frozen=True)
class CompactOptions:
    """What a compact message carries besides the Gaussians' geometry and appearance.

    Attributes:
        ids: the Gaussians' ids (without them, the receiver numbers them 0..N-1).
        sums: the PWAS state (the score, the weight and alpha x T sums, 8 bits each), for a
            receiver that continues accumulating and a merge that weighs evidence.
        score: without the sums, the PWAS score alone (ignored when `sums`).
        step: position grid step in metres (None: `POSITION_STEP_FRACTION` of the median scale).
    """

    ids: bool = True
    sums: bool = True
    score: bool = True
    step: float | None = None


COMPACT_DEFAULTS = CompactOptions()
"""What a compact map carries unless asked otherwise: ids and PWAS sums."""

SHARE_IDS = False
"""Whether a compact share carries the Gaussians' ids unless asked (`gsc share --ids`). A merge
numbers the share's Gaussians anew past the receiver's ids, so they would only trace a Gaussian
back to the sender's, at about 2 bytes a Gaussian (docs/codecs.md)."""

SHARE_DEFAULTS = CompactOptions(ids=SHARE_IDS)
"""What a compact share carries unless asked otherwise: the PWAS sums, no ids."""


def layout() -> dict[str, Any]:
    """What sets a compact message's bytes besides the map and its `CompactOptions`: each
    column's bits, the colour transform, the rotation bits and the position step (the
    experiment keys its shares by it, so that a share cut by another layout is cut again)."""
    return {"bits": dict(BITS), "colour": COLOUR_TRANSFORM, "rotation_bits": ROTATION_BITS,
            "position_step": POSITION_STEP_FRACTION}  # fmt: skip


def check_codec(codec: str) -> str:
    """Return `codec` if it is one of CODECS, else raise InputError."""
    if codec not in CODECS:
        raise InputError(f"unknown codec {codec!r}; choose one of {', '.join(CODECS)}")
    return codec


# ---------------------------------------------------------------------- the message type


def _message_types() -> tuple[type[Message], type[Message]]:
    """The CompactGaussians and CompactColumn message classes, built from a descriptor written
    here (schemas/compact_gaussians.v1.proto is the same schema in text; a test compares them)."""
    T = descriptor_pb2.FieldDescriptorProto
    proto = descriptor_pb2.FileDescriptorProto(
        name="gscompress/compact_gaussians.v1.proto", package="gscompress", syntax="proto3"
    )
    fields = {
        "CompactGaussians": [
            ("version", T.TYPE_UINT32, None),
            ("timestamp_ns", T.TYPE_UINT64, None),
            ("frame_id", T.TYPE_STRING, None),
            ("count", T.TYPE_UINT32, None),
            ("isotropic", T.TYPE_BOOL, None),
            ("sh_degree", T.TYPE_UINT32, None),
            ("origin", T.TYPE_DOUBLE, "repeated"),
            ("step", T.TYPE_DOUBLE, None),
            ("position_bits", T.TYPE_UINT32, None),
            ("columns", T.TYPE_MESSAGE, ".gscompress.CompactColumn"),
        ],
        "CompactColumn": [
            ("name", T.TYPE_STRING, None),
            ("transform", T.TYPE_STRING, None),
            ("dtype", T.TYPE_STRING, None),
            ("components", T.TYPE_UINT32, None),
            ("bits", T.TYPE_UINT32, None),
            ("low", T.TYPE_DOUBLE, "repeated"),
            ("high", T.TYPE_DOUBLE, "repeated"),
            ("raw_bytes", T.TYPE_UINT64, None),
            ("data", T.TYPE_BYTES, None),
        ],
    }
    for name, spec in fields.items():
        message = proto.message_type.add(name=name)
        for number, (field_name, kind, extra) in enumerate(spec, start=1):
            field = message.field.add(name=field_name, number=number, type=kind)
            repeated = extra == "repeated" or kind == T.TYPE_MESSAGE
            field.label = T.LABEL_REPEATED if repeated else T.LABEL_OPTIONAL
            if kind == T.TYPE_MESSAGE:
                field.type_name = str(extra)
    pool = descriptor_pool.DescriptorPool()
    pool.Add(proto)
    return (
        message_factory.GetMessageClass(pool.FindMessageTypeByName(COMPACT_SCHEMA)),
        message_factory.GetMessageClass(pool.FindMessageTypeByName("gscompress.CompactColumn")),
    )


CompactGaussians, CompactColumn = _message_types()


def compact_schema_bytes() -> bytes:
    """The serialized FileDescriptorSet of CompactGaussians (the schema record of a log)."""
    fds = descriptor_pb2.FileDescriptorSet()
    CompactGaussians.DESCRIPTOR.file.CopyToProto(fds.file.add())
    return fds.SerializeToString()


# ---------------------------------------------------------------------- one rule per transform


def quantise_linear(values: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear codes of `bits` bits for each column of `values` [N, C] between its min and max.

    Returns:
        (codes [N, C] uint8 or uint16, low [C], high [C]); decoding is `dequantise_linear`.
    """
    values = np.asarray(values, dtype=np.float64)
    levels = (1 << bits) - 1
    if len(values):
        low, high = values.min(axis=0), values.max(axis=0)
    else:
        low = high = np.zeros(values.shape[1])
    span = np.where(high > low, high - low, 1.0)
    codes = np.rint((values - low) / span * levels)
    return codes.astype(np.uint8 if bits <= 8 else np.uint16), low, high


def dequantise_linear(
    codes: np.ndarray, low: np.ndarray, high: np.ndarray, bits: int
) -> np.ndarray:
    """Values of linear codes: low + code * (high - low) / (2^bits - 1), as float32."""
    levels = (1 << bits) - 1
    return (low + codes.astype(np.float64) * ((high - low) / levels)).astype(np.float32)


def sigmoid(logits: np.ndarray) -> np.ndarray:
    """Opacity in (0, 1) of opacity logits (float64; no overflow warning at large |logit|)."""
    return 0.5 * (1.0 + np.tanh(0.5 * np.asarray(logits, dtype=np.float64)))


def logit(p: np.ndarray) -> np.ndarray:
    """Opacity logits of opacities, clamped to [eps, 1 - eps] so that each is finite."""
    p = np.clip(np.asarray(p, dtype=np.float64), _SIGMOID_EPS, 1 - _SIGMOID_EPS)
    return np.log(p / (1 - p))


def _asinh(values: np.ndarray) -> np.ndarray:
    return np.arcsinh(np.asarray(values, dtype=np.float64))


def _sinh(values: np.ndarray) -> np.ndarray:
    """sinh, within float32's range (an `asinh-linear` column's range is bounded by it)."""
    return np.clip(np.sinh(np.asarray(values, dtype=np.float64)), -_FLOAT32_MAX, _FLOAT32_MAX)


LINEAR_TRANSFORMS: dict[str, tuple[Callable[[np.ndarray], np.ndarray], ...]] = {
    "linear": (np.asarray, np.asarray),
    "sigmoid-linear": (sigmoid, logit),
    "asinh-linear": (_asinh, _sinh),
}
"""A linear column's transform -> (forward: a value into the space its codes are linear in,
inverse: back). The encoder, the decoder and bench/codec_columns.py take them from here."""


def quantise_log(scores: np.ndarray, bits: int) -> tuple[np.ndarray, float, float]:
    """Codes of nonnegative scores on a log scale: 0 for a zero score, 1..2^bits-1 linear in log
    score between the smallest and largest positive score.

    Returns:
        (codes [N] uint16, low, high: log of the smallest and largest positive score).
    """
    scores = np.asarray(scores, dtype=np.float64)
    positive = scores > 0
    codes = np.zeros(len(scores), np.uint16)
    if not positive.any():
        return codes, 0.0, 0.0
    logs = np.log(scores[positive])
    logs = np.clip(logs, -_MAX_LOG_SCORE, _MAX_LOG_SCORE)  # (subnormal float32 goes below -88)
    low, high = float(logs.min()), float(logs.max())
    steps = (1 << bits) - 2
    span = high - low if high > low else 1.0
    codes[positive] = 1 + np.rint((logs - low) / span * steps).astype(np.uint16)
    return codes, low, high


def dequantise_log(codes: np.ndarray, low: float, high: float, bits: int) -> np.ndarray:
    """Scores of log codes (see `quantise_log`), as float32: a table of every code's value,
    indexed (codes must be below 2^bits)."""
    steps = (1 << bits) - 2
    table = np.exp(low + (np.arange(1 << bits) - 1.0) * ((high - low) / steps))
    table[0] = 0.0
    return table.astype(np.float32)[codes]


def encode_smallest_three(quats_wxyz: np.ndarray) -> np.ndarray:
    """[N] uint32 smallest-three codes of rotations (w x y z, any nonzero norm), in SPZ's
    layout: the index of the largest |component| (in x y z w order) in the top 2 bits, then
    the other three, each as a sign bit and 9 bits of magnitude in [0, 1/sqrt2], signed so
    that the largest is positive (one layout for SPZ files and compact maps)."""
    norms = np.linalg.norm(np.asarray(quats_wxyz, dtype=np.float64), axis=1, keepdims=True)
    quats_wxyz = np.asarray(quats_wxyz, dtype=np.float64) / np.where(norms > 0, norms, 1.0)
    q = [quats_wxyz[:, i] for i in (1, 2, 3, 0)]  # x y z w
    size = np.abs(quats_wxyz)[:, [1, 2, 3, 0]]
    largest = np.argmax(size, axis=1)  # the first of equal magnitudes, as the reference
    flip = np.choose(largest, q) < 0
    code = largest.astype(np.uint32) << np.uint32(30)
    for i in range(4):
        magnitude = np.minimum(np.floor(size[:, i] * (511 / np.sqrt(0.5)) + 0.5), 511)
        negative = ((q[i] < 0) ^ flip) & (q[i] != 0)
        field = magnitude.astype(np.uint32) | negative.astype(np.uint32) << np.uint32(9)
        slot = i - (largest < i)  # its place among the three stored, first in the high bits
        shift = (10 * (2 - slot)).clip(0).astype(np.uint32)
        code |= np.where(largest != i, field << shift, np.uint32(0)).astype(np.uint32)
    return code


def decode_smallest_three(code: np.ndarray) -> np.ndarray:
    """[N, 4] float32 unit quaternions (w x y z) of `encode_smallest_three` codes."""
    n = len(code)
    largest = (code >> 30).astype(np.intp)
    q = np.zeros((n, 4), np.float32)  # x y z w
    rows = np.arange(n)
    rest = code.astype(np.uint32)
    squares = np.zeros(n, np.float32)
    for i in range(3, -1, -1):
        here = largest != i
        value = (rest & 511).astype(np.float32) * (_SQRT1_2 / np.float32(511))
        value = np.where((rest >> 9) & 1, -value, value)
        q[:, i] = np.where(here, value, 0)
        squares += np.where(here, value * value, 0)
        rest = np.where(here, rest >> 10, rest)
    q[rows, largest] = np.sqrt(np.maximum(0, 1 - squares))
    return q[:, [3, 0, 1, 2]]


def _spread_bits(v: np.ndarray) -> np.ndarray:
    """Each bit i of 21-bit integers moved to bit 3i (uint64)."""
    v = v.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in (
        (32, 0x1F00000000FFFF),
        (16, 0x1F0000FF0000FF),
        (8, 0x100F00F00F00F00F),
        (4, 0x10C30C30C30C30C3),
        (2, 0x1249249249249249),
    ):
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


def _compact_bits(v: np.ndarray) -> np.ndarray:
    """The inverse of `_spread_bits`: bits 3i back to bit i."""
    v = v.astype(np.uint64) & np.uint64(0x1249249249249249)
    for shift, mask in (
        (2, 0x10C30C30C30C30C3),
        (4, 0x100F00F00F00F00F),
        (8, 0x1F0000FF0000FF),
        (16, 0x1F00000000FFFF),
        (32, 0x1FFFFF),
    ):
        v = (v | (v >> np.uint64(shift))) & np.uint64(mask)
    return v


def morton_codes(grid: np.ndarray) -> np.ndarray:
    """Morton codes (uint64) of grid coordinates [N, 3] below 2^21: x in bit 0, y 1, z 2."""
    grid = np.asarray(grid)
    return (
        _spread_bits(grid[:, 0])
        | (_spread_bits(grid[:, 1]) << np.uint64(1))
        | (_spread_bits(grid[:, 2]) << np.uint64(2))
    )


def morton_grid(codes: np.ndarray) -> np.ndarray:
    """Grid coordinates [N, 3] (int64) of Morton codes (the inverse of `morton_codes`)."""
    codes = np.asarray(codes, dtype=np.uint64)
    return np.stack([_compact_bits(codes >> np.uint64(axis)) for axis in range(3)], axis=1).astype(
        np.int64
    )


def position_step(
    gaussians: GaussianMap, step: float | None = None
) -> tuple[np.ndarray, float, int]:
    """The position grid of a map: origin [3] (float64), step and bits per axis.

    The step is `step`, else `POSITION_STEP_FRACTION` of the median scale; it grows where the
    map would span more than 2^MAX_POSITION_BITS steps along an axis.

    Raises:
        InputError: a given step that is not a positive finite number.
    """
    if step is not None and not (np.isfinite(step) and step > 0):
        raise InputError(f"position step must be a positive number of metres, got {step}")
    means = gaussians.means.astype(np.float64)
    if not len(means):
        return np.zeros(3), float(step or 1.0), 1
    origin = means.min(axis=0)
    extent = float((means.max(axis=0) - origin).max())
    if step is None:
        median_scale = float(np.median(np.exp(gaussians.log_scales.astype(np.float64))))
        step = POSITION_STEP_FRACTION * median_scale if median_scale > 0 else 1e-3
    step = max(step, extent / ((1 << MAX_POSITION_BITS) - 1) * (1 + 1e-9), np.finfo(float).tiny)
    bits = max(1, int(np.ceil(np.log2(extent / step + 1.5))))
    return origin, float(step), min(bits, MAX_POSITION_BITS)


def grid_codes(
    gaussians: GaussianMap, step: float | None = None
) -> tuple[np.ndarray, float, int, np.ndarray]:
    """The position grid of a map (`position_step`: origin, step, bits per axis) and each
    Gaussian's Morton code on it; a compact message stores the Gaussians in that code's order.

    Raises:
        InputError: a bad `step`.
    """
    origin, step, bits = position_step(gaussians, step)
    grid = np.rint((gaussians.means.astype(np.float64) - origin) / step).astype(np.int64)
    return origin, step, bits, morton_codes(np.clip(grid, 0, (1 << bits) - 1))


# ---------------------------------------------------------------------- columns


def _shuffle(codes: np.ndarray) -> bytes:
    """The bytes of a little-endian code array [N, C] as byte planes (see the module doc)."""
    flat = np.ascontiguousarray(codes)
    itemsize = flat.dtype.itemsize
    raw = flat.view(np.uint8).reshape(flat.shape[0], flat.shape[1], itemsize)
    return np.ascontiguousarray(raw.transpose(2, 0, 1)).tobytes()


def _unshuffle(planes: bytes, count: int, components: int, dtype: np.dtype) -> np.ndarray:
    """The inverse of `_shuffle`: codes [count, components] of `dtype`."""
    raw = np.frombuffer(planes, np.uint8).reshape(dtype.itemsize, count, components)
    return np.ascontiguousarray(raw.transpose(1, 2, 0)).view(dtype).reshape(count, components)


def _column(
    name: str,
    transform: str,
    codes: np.ndarray,
    *,
    bits: int = 0,
    low: Any = (),
    high: Any = (),
    compressor: zstandard.ZstdCompressor,
) -> Message:
    codes = np.asarray(codes)
    width = int(np.prod(codes.shape[1:]))  # (1 for a [N] column, also when N is 0)
    codes = codes.reshape(len(codes), width).astype(codes.dtype.newbyteorder("<"), copy=False)
    planes = _shuffle(codes)
    return CompactColumn(
        name=name,
        transform=transform,
        dtype=codes.dtype.str.lstrip("|"),
        components=codes.shape[1],
        bits=bits,
        low=[float(v) for v in np.atleast_1d(low)],
        high=[float(v) for v in np.atleast_1d(high)],
        raw_bytes=len(planes),
        data=compressor.compress(planes),
    )


def encode_compact(
    gaussians: GaussianMap,
    options: CompactOptions = COMPACT_DEFAULTS,
    *,
    timestamp_ns: int = 0,
    frame_id: str = "world",
) -> Message:
    """The compact message of a map (see the module docstring).

    Decoding returns the Gaussians in Morton order of their grid positions, not in the map's.

    Raises:
        InputError: a bad `options.step`.
    """
    n = len(gaussians)
    origin, step, bits, codes = grid_codes(gaussians, options.step)
    order = np.argsort(codes, kind="stable")
    codes = codes[order]

    def ordered(name: str) -> np.ndarray:
        return np.asarray(getattr(gaussians, name))[order]  # (the arrays used, not a whole copy)

    zstd = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
    columns = [
        _column("position", "morton-delta", np.diff(codes, prepend=np.uint64(0)), compressor=zstd)
    ]

    def linear(name: str, values: np.ndarray, transform: str = "linear") -> None:
        values = LINEAR_TRANSFORMS[transform][0](values)
        q, low, high = quantise_linear(
            values.reshape(n, int(np.prod(values.shape[1:]))), BITS[name]
        )
        columns.append(
            _column(name, transform, q, bits=BITS[name], low=low, high=high, compressor=zstd)
        )

    linear("log_scale", ordered("log_scales"))
    if not gaussians.isotropic:
        rotations = encode_smallest_three(ordered("quats"))
        columns.append(
            _column("rotation", "smallest-three", rotations, bits=ROTATION_BITS, compressor=zstd)
        )
    linear("opacity", ordered("opacity_logits"), "sigmoid-linear")
    linear("f_dc", ordered("sh_dc"), COLOUR_TRANSFORM)
    if gaussians.sh_degree:
        linear("f_rest", ordered("sh_rest"))
    if options.ids:
        deltas = np.diff(ordered("ids"), prepend=np.uint32(0))  # modulo 2^32
        columns.append(_column("id", "delta", deltas, compressor=zstd))

    def log_linear(name: str, values: np.ndarray) -> None:
        q, low, high = quantise_log(values, BITS[name])
        columns.append(_column(name, "log-linear", q, bits=BITS[name], low=low, high=high,
                               compressor=zstd))  # fmt: skip

    if options.sums or (options.score and gaussians.has_importance):
        log_linear("importance", ordered("importance"))
    if options.sums:
        for name in SUMS:
            log_linear(name, ordered(name))
    return CompactGaussians(
        version=COMPACT_VERSION,
        timestamp_ns=max(int(timestamp_ns), 0),
        frame_id=frame_id,
        count=n,
        isotropic=gaussians.isotropic,
        sh_degree=gaussians.sh_degree,
        origin=[float(v) for v in origin],
        step=step,
        position_bits=bits,
        columns=columns,
    )


# ---------------------------------------------------------------------- decoding

_SHAPES: dict[str, tuple[tuple[str, ...], Callable[[Message], int]]] = {
    "position": (("morton-delta",), lambda m: 1),
    "log_scale": (("linear",), lambda m: 1 if m.isotropic else 3),
    "rotation": (("smallest-three",), lambda m: 1),
    "opacity": (("sigmoid-linear",), lambda m: 1),
    "f_dc": (("asinh-linear", "linear"), lambda m: 3),
    "f_rest": (("linear",), lambda m: 3 * SH_REST_COUNTS.get(m.sh_degree, 0)),
    "id": (("delta",), lambda m: 1),
    "importance_sum": (("raw",), lambda m: 1),
    "importance_weight": (("log-linear", "raw"), lambda m: 1),
    "alpha_t_sum": (("log-linear", "raw"), lambda m: 1),
    "importance": (("log-linear",), lambda m: 1),
}
"""Column name -> (the transforms it may have, its components in a message)."""

_DTYPES = {
    "morton-delta": ("<u8",),
    "linear": ("u1", "<u2"),
    "sigmoid-linear": ("u1", "<u2"),
    "asinh-linear": ("u1", "<u2"),
    "log-linear": ("<u2",),
    "smallest-three": ("<u4",),
    "delta": ("<u4",),
    "raw": ("<f4",),
}
"""Transform -> the code dtypes it may be stored as."""


def decode_compact_bytes(data: bytes, source: str = "compact map") -> tuple[GaussianMap, Message]:
    """Parse and decode a serialized compact message (see `decode_compact`).

    Raises:
        MapError: not a CompactGaussians message, or one `decode_compact` refuses.
    """
    message = CompactGaussians()
    try:
        message.ParseFromString(data)
    except DecodeError:
        raise MapError(f"{source}: a corrupt compact map message") from None
    return decode_compact(message, len(data), source), message


def decode_compact(
    message: Message, message_bytes: int, source: str = "compact map"
) -> GaussianMap:
    """The map of a compact message, checked before anything is allocated.

    Args:
        message: a parsed CompactGaussians.
        message_bytes: its serialized size (bounds the count it may declare).
        source: the file, for messages.

    Raises:
        MapError: an unknown version, a count beyond `MAX_GAUSSIANS` or the message's size, a
            missing, repeated or unknown column, a column whose type, components or sizes do not
            match the count, a bad grid (non-finite origin, step zero or non-finite), codes
            outside their range, or a decoded map that is not valid.
    """

    def fail(what: str) -> MapError:
        return MapError(f"{source}: compact map {what}")

    if message.version != COMPACT_VERSION:
        raise fail(f"has version {message.version}; this gscompress reads {COMPACT_VERSION}")
    n = int(message.count)
    if n > MAX_GAUSSIANS or n > message_bytes / MIN_BYTES_PER_GAUSSIAN:
        raise fail(f"declares {n} Gaussians in {message_bytes} bytes")
    if message.sh_degree not in SH_REST_COUNTS:
        raise fail(f"has SH degree {message.sh_degree}")
    origin = np.array(message.origin, dtype=np.float64)
    step = float(message.step)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise fail("has no finite grid origin of three numbers")
    if not (np.isfinite(step) and step > 0):
        raise fail(f"has grid step {step}: not a positive number")
    bits = int(message.position_bits)
    if not 1 <= bits <= MAX_POSITION_BITS:
        raise fail(f"has {bits} position bits (1..{MAX_POSITION_BITS})")

    columns: dict[str, np.ndarray] = {}
    params: dict[str, Message] = {}
    for column in message.columns:
        name = column.name
        if name not in _SHAPES:
            raise fail(f"has an unknown column {name[:40]!r}")
        if name in columns:
            raise fail(f"has column {name!r} twice")
        transform, components = column.transform, _SHAPES[name][1](message)
        if transform not in _SHAPES[name][0] or column.dtype not in _DTYPES[transform]:
            raise fail(f"column {name!r} is {column.transform[:40]!r} {column.dtype[:8]!r}")
        if column.components != components:
            raise fail(f"column {name!r} has {column.components} components, not {components}")
        dtype = np.dtype(column.dtype)
        expected = n * components * dtype.itemsize
        if column.raw_bytes != expected:
            raise fail(f"column {name!r} declares {column.raw_bytes} bytes; {n} Gaussians take "
                       f"{expected}")  # fmt: skip
        if transform in ("linear", "sigmoid-linear", "asinh-linear", "log-linear"):
            low, high = np.array(column.low), np.array(column.high)
            wanted = 1 if transform == "log-linear" else components
            if low.shape != (wanted,) or high.shape != (wanted,):
                raise fail(f"column {name!r} lacks its low and high values")
            bound = {"log-linear": _MAX_LOG_SCORE, "asinh-linear": _MAX_ASINH}.get(
                transform, _FLOAT32_MAX
            )
            if not (
                np.all(np.abs(low) <= bound)
                and np.all(np.abs(high) <= bound)
                and np.all(high >= low)
            ):  # fmt: skip  (also: not NaN)
                worst = float(np.max(np.abs(np.concatenate([low, high]))))
                raise fail(f"column {name!r} has a range beyond +-{bound:g} or inverted "
                           f"(largest |value| {worst:g})")  # fmt: skip
            if not 1 <= column.bits <= dtype.itemsize * 8 or (
                transform == "log-linear" and column.bits < 2
            ):
                raise fail(f"column {name!r} has {column.bits} bits in {column.dtype}")
        planes = inflate_zstd(column.data, expected, f"{source}: compact map column {name!r}")
        columns[name] = _unshuffle(planes, n, components, dtype)
        params[name] = column

    required = ["position", "log_scale", "opacity", "f_dc"]
    required += [] if message.isotropic else ["rotation"]
    required += ["f_rest"] if message.sh_degree else []
    missing = [name for name in required if name not in columns]
    if missing:
        raise fail(f"lacks column(s) {', '.join(missing)}")
    raw = {name for name in RAW_SUMS if name in columns and params[name].transform == "raw"}
    coded = {name for name in SUMS if name in columns} - raw
    if (raw and len(raw) != len(RAW_SUMS)) or (coded and len(coded) != len(SUMS)):
        raise fail("has some of the PWAS sums but not all of them")
    if coded and "importance" not in columns:
        raise fail("has the PWAS sums but not the score")
    if message.isotropic and "rotation" in columns:
        raise fail("is isotropic but has rotations")

    deltas = columns["position"][:, 0]
    total = np.cumsum(deltas, dtype=np.uint64)
    limit = np.uint64(1) << np.uint64(3 * bits)
    if n and (np.any(deltas >= limit) or np.any(total[1:] < total[:-1]) or total[-1] >= limit):
        raise fail(f"has positions outside its {bits}-bit grid")
    positions = origin + morton_grid(total) * step
    if n and not np.all(np.abs(positions) <= _FLOAT32_MAX):
        raise fail("has positions beyond the float32 range (its grid's origin or step)")
    means = positions.astype(np.float32)

    def codes(name: str) -> tuple[np.ndarray, Message]:
        """A quantised column's codes, checked to fit its bits, and its parameters."""
        c = params[name]
        if np.any(columns[name] > (1 << c.bits) - 1):
            raise fail(f"column {name!r} has codes beyond {c.bits} bits")
        return columns[name], c

    def linear(name: str) -> np.ndarray:
        values, c = codes(name)
        inverse = LINEAR_TRANSFORMS[c.transform][1]  # (f_dc: "linear" in older messages)
        return inverse(dequantise_linear(values, np.array(c.low), np.array(c.high), c.bits))

    rotation = columns.get("rotation")
    k = SH_REST_COUNTS[message.sh_degree]

    def log_linear(name: str) -> np.ndarray:
        values, c = codes(name)
        return dequantise_log(values[:, 0], c.low[0], c.high[0], c.bits)

    extra: dict[str, Any] = {name: columns[name][:, 0] for name in raw}
    if "importance" in columns and not raw:
        score = log_linear("importance")
        if coded:
            weight = log_linear("importance_weight")
            extra = {"importance_sum": score * (weight + np.float32(PWAS_EPS)),
                     "importance_weight": weight,
                     "alpha_t_sum": log_linear("alpha_t_sum")}  # fmt: skip
        else:
            extra = {"importance_sum": score, "importance_weight": np.ones(n, np.float32)}
    if "id" in columns:
        extra["ids"] = np.cumsum(columns["id"][:, 0], dtype=np.uint32)
    gaussians = GaussianMap.new(
        means=means,
        log_scales=linear("log_scale"),
        quats=(
            np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1))
            if rotation is None
            else decode_smallest_three(rotation[:, 0])
        ),
        opacity_logits=linear("opacity")[:, 0].astype(np.float32),
        sh_dc=linear("f_dc"),
        sh_rest=linear("f_rest").reshape(n, k, 3) if k else None,
        **extra,
    )
    try:
        return gaussians.validate()
    except MapError as exc:
        raise fail(str(exc)) from None


def inflate_zstd(
    data: bytes | memoryview, size: int, where: str, error: type[GscError] = MapError
) -> bytes:
    """A zstd frame inflated to exactly `size` bytes, never more: refused (`error`, led by
    `where`) when it is not zstd, declares another size, is corrupt, or holds more or less."""
    if size == 0 and not len(data):
        return b""
    try:
        declared = zstandard.frame_content_size(data)
    except zstandard.ZstdError:
        raise error(f"{where} is not a zstd frame") from None
    if declared not in (-1, size):
        raise error(f"{where} declares {declared} bytes, not {size}")
    try:
        with zstandard.ZstdDecompressor().stream_reader(io.BytesIO(data)) as reader:
            out = reader.read(size + 1)
            while len(out) <= size and (more := reader.read(size + 1 - len(out))):
                out += more
    except zstandard.ZstdError as exc:
        raise error(f"{where} is corrupt ({' '.join(str(exc).split())[:80]})") from None
    if len(out) != size:
        raise error(f"{where} decompresses to {len(out)} bytes, not {size}")
    return out
