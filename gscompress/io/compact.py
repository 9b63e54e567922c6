"""The compact map codec: our own protobuf message `gscompress.CompactGaussians`
(schemas/compact_gaussians.v1.proto), which stores a map column by column, each attribute
quantised and zstd-compressed on its own. This module encodes and decodes it (the quantisation
rules, one per transform, are in `gscompress.io.quantise`); docs/codecs.md gives the rules and
the measurements behind the bit widths. `gscompress.io.codec` is the table of every map codec.

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

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import zstandard
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.message import DecodeError, Message

from gscompress.errors import MapError
from gscompress.gaussians import PWAS_EPS, SH_REST_COUNTS, GaussianMap
from gscompress.io.decode_budget import DecodeBudget, inflate_zstd
from gscompress.io.quantise import (
    FLOAT32_MAX,
    LINEAR_TRANSFORMS,
    MAX_ASINH,
    MAX_LOG_SCORE,
    MAX_POSITION_BITS,
    POSITION_STEP_FRACTION,
    decode_smallest_three,
    dequantise_linear,
    dequantise_log,
    encode_smallest_three,
    grid_codes,
    morton_grid,
    morton_order,
    quantise_linear,
    quantise_log,
)

COMPACT_SCHEMA = "gscompress.CompactGaussians"
"""Schema name of the compact map message in a log."""

COMPACT_VERSION = 1
"""Version of the compact message this module writes and reads."""

BITS = {
    "log_scale": 8,
    "opacity": 6,
    "f_dc": 7,
    "f_rest": 8,
    "importance": 8,
    "importance_weight": 8,
    "alpha_t_sum": 8,
}
"""Default quantisation bits of each linear and log-linear column (chosen by bench/codec.py and
the probes in docs/codecs.md, "The compact message", which holds the measurements): an 8-bit
log code keeps a score or a sum within half a code step over the span of real maps, and a prune
by the decoded scores keeps nearly all the Gaussians the exact ones keep. 7-bit asinh colours
and 8-bit log scales cost the picture less than 8-bit linear colours and 7-bit scales did, for
a fraction of a byte more a Gaussian."""

COLOUR_TRANSFORM = "asinh-linear"
"""How `f_dc` is coded: linear in asinh(f_dc), fine near the colours of [0, 1] (|f_dc| < 1.8)
and coarse in the long tails optimisation leaves (far outside it on real maps: docs/codecs.md),
which would otherwise stretch a linear code's range and coarsen every colour."""

SUMS = ("importance_weight", "alpha_t_sum")
"""The PWAS sums a compact message codes beside the score (importance_sum = score x (W + eps))."""

RAW_SUMS = ("importance_sum", "importance_weight", "alpha_t_sum")
"""The PWAS sums as float32 in messages written before they were coded (still read)."""

ZSTD_LEVEL = 3
"""zstd level of every column."""

MAX_GAUSSIANS = 1 << 28
"""Most Gaussians a compact message may declare."""

ROTATION_BITS = 10
"""Bits of each of the three smallest quaternion components in a `smallest-three` code (a sign
and 9 bits of magnitude)."""


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


def layout() -> dict[str, Any]:
    """What sets a compact message's bytes besides the map and its `CompactOptions`: each
    column's bits, the colour transform, the rotation bits and the position step (the
    experiment keys its shares by it, so that a share cut by another layout is cut again)."""
    return {
        "bits": dict(BITS),
        "colour": COLOUR_TRANSFORM,
        "rotation_bits": ROTATION_BITS,
        "position_step": POSITION_STEP_FRACTION,
    }


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


# ---------------------------------------------------------------------- columns


def _shuffle(codes: np.ndarray) -> bytes:
    """The bytes of a little-endian code array [N, C] as byte planes (see the module doc)."""
    flat = np.ascontiguousarray(codes)
    itemsize = flat.dtype.itemsize
    raw = flat.view(np.uint8).reshape(flat.shape[0], flat.shape[1], itemsize)
    return np.ascontiguousarray(raw.transpose(2, 0, 1)).tobytes()


def _unshuffle(
    planes: bytes | bytearray, count: int, components: int, dtype: np.dtype
) -> np.ndarray:
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
    order = morton_order(codes, 3 * bits)
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
        columns.append(
            _column(name, "log-linear", q, bits=BITS[name], low=low, high=high, compressor=zstd)
        )

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
    grid = _check_header(message, message_bytes, source)
    columns = _inflate_columns(message, grid.count, source)
    raw, coded = _check_column_set(message, columns, source)
    gaussians = GaussianMap.new(
        means=_decode_positions(columns["position"].codes, grid, source),
        log_scales=_linear(columns["log_scale"], source),
        quats=_decode_rotations(columns.get("rotation"), grid.count),
        opacity_logits=_linear(columns["opacity"], source)[:, 0].astype(np.float32),
        sh_dc=_linear(columns["f_dc"], source),
        sh_rest=_decode_sh_rest(columns.get("f_rest"), message.sh_degree, source),
        **_decode_pwas(columns, raw, coded, grid.count, source),
        **_decode_ids(columns.get("id")),
    )
    try:
        return gaussians.validate()
    except MapError as exc:
        raise _failure(source, str(exc)) from None


def _failure(source: str, what: str) -> MapError:
    """The error of a compact map that is not readable."""
    return MapError(f"{source}: compact map {what}")


@dataclass(frozen=True)
class _Grid:
    """A compact message's count and position grid, checked."""

    count: int
    origin: np.ndarray
    step: float
    bits: int


@dataclass(frozen=True)
class _Column:
    """A column's codes [count, components] and the message column they came from."""

    codes: np.ndarray
    spec: Message


def _check_header(message: Message, message_bytes: int, source: str) -> _Grid:
    """The version, the SH degree, the count (against `MAX_GAUSSIANS` and what the message's
    bytes may decode to: `gscompress.io.decode_budget`) and the position grid of a message."""
    if message.version != COMPACT_VERSION:
        raise _failure(
            source, f"has version {message.version}; this gscompress reads {COMPACT_VERSION}"
        )
    n = int(message.count)
    if message.sh_degree not in SH_REST_COUNTS:
        raise _failure(source, f"has SH degree {message.sh_degree}")
    if n > MAX_GAUSSIANS:
        raise _failure(source, f"declares {n} Gaussians, more than the {MAX_GAUSSIANS} read here")
    DecodeBudget("compact", message_bytes, f"{source}: compact map", MapError).check_map(
        n, message.sh_degree
    )
    origin = np.array(message.origin, dtype=np.float64)
    step = float(message.step)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise _failure(source, "has no finite grid origin of three numbers")
    if not (np.isfinite(step) and step > 0):
        raise _failure(source, f"has grid step {step}: not a positive number")
    bits = int(message.position_bits)
    if not 1 <= bits <= MAX_POSITION_BITS:
        raise _failure(source, f"has {bits} position bits (1..{MAX_POSITION_BITS})")
    return _Grid(n, origin, step, bits)


def _inflate_columns(message: Message, n: int, source: str) -> dict[str, _Column]:
    """Every column of a message by name, each checked (`_check_column`) before it is
    inflated to exactly the bytes its count and type take."""
    columns: dict[str, _Column] = {}
    for column in message.columns:
        name = column.name
        if name in columns:
            raise _failure(source, f"has column {name!r} twice")
        components, dtype = _check_column(column, message, n, source)
        planes = inflate_zstd(
            column.data, column.raw_bytes, f"{source}: compact map column {name!r}", MapError
        )
        columns[name] = _Column(_unshuffle(planes, n, components, dtype), column)
    return columns


def _check_column(column: Message, message: Message, n: int, source: str) -> tuple[int, np.dtype]:
    """A column's components and code dtype, refused unless its name, transform, dtype,
    components, size and range are what its kind takes."""
    name = column.name
    if name not in _SHAPES:
        raise _failure(source, f"has an unknown column {name[:40]!r}")
    transform, components = column.transform, _SHAPES[name][1](message)
    if transform not in _SHAPES[name][0] or column.dtype not in _DTYPES[transform]:
        raise _failure(source, f"column {name!r} is {transform[:40]!r} {column.dtype[:8]!r}")
    if column.components != components:
        raise _failure(
            source, f"column {name!r} has {column.components} components, not {components}"
        )
    dtype = np.dtype(column.dtype)
    expected = n * components * dtype.itemsize
    if column.raw_bytes != expected:
        raise _failure(
            source,
            f"column {name!r} declares {column.raw_bytes} bytes; {n} Gaussians take {expected}",
        )
    if transform in _RANGES:
        _check_range(column, components, dtype, source)
    return components, dtype


_RANGES = {
    "linear": FLOAT32_MAX,
    "sigmoid-linear": FLOAT32_MAX,
    "asinh-linear": MAX_ASINH,
    "log-linear": MAX_LOG_SCORE,
}
"""Quantised transform -> the largest |low| or |high| its column may record."""


def _check_range(column: Message, components: int, dtype: np.dtype, source: str) -> None:
    """A quantised column's low and high values (one per component, one for a log-linear
    column; finite, within the transform's bound, not inverted) and its bits."""
    name, transform = column.name, column.transform
    low, high = np.array(column.low), np.array(column.high)
    wanted = 1 if transform == "log-linear" else components
    if low.shape != (wanted,) or high.shape != (wanted,):
        raise _failure(source, f"column {name!r} lacks its low and high values")
    bound = _RANGES[transform]
    inside = np.all(np.abs(low) <= bound) and np.all(np.abs(high) <= bound)
    if not (inside and np.all(high >= low)):  # (also: not NaN)
        worst = float(np.max(np.abs(np.concatenate([low, high]))))
        raise _failure(
            source,
            f"column {name!r} has a range beyond +-{bound:g} or inverted "
            f"(largest |value| {worst:g})",
        )
    if not 1 <= column.bits <= dtype.itemsize * 8 or (
        transform == "log-linear" and column.bits < 2
    ):
        raise _failure(source, f"column {name!r} has {column.bits} bits in {column.dtype}")


def _check_column_set(
    message: Message, columns: dict[str, _Column], source: str
) -> tuple[set[str], set[str]]:
    """Refuse a message without the columns its kind requires, or with part of the PWAS state.

    Returns:
        (the PWAS sums stored as float32, the PWAS sums stored as codes).
    """
    required = ["position", "log_scale", "opacity", "f_dc"]
    required += [] if message.isotropic else ["rotation"]
    required += ["f_rest"] if message.sh_degree else []
    missing = [name for name in required if name not in columns]
    if missing:
        raise _failure(source, f"lacks column(s) {', '.join(missing)}")
    raw = {name for name in RAW_SUMS if name in columns and columns[name].spec.transform == "raw"}
    coded = {name for name in SUMS if name in columns} - raw
    if (raw and len(raw) != len(RAW_SUMS)) or (coded and len(coded) != len(SUMS)):
        raise _failure(source, "has some of the PWAS sums but not all of them")
    if coded and "importance" not in columns:
        raise _failure(source, "has the PWAS sums but not the score")
    if message.isotropic and "rotation" in columns:
        raise _failure(source, "is isotropic but has rotations")
    return raw, coded


def _decode_positions(codes: np.ndarray, grid: _Grid, source: str) -> np.ndarray:
    """[N, 3] float32 means of the Morton-delta column, refused off the grid or beyond float32."""
    deltas = codes[:, 0]
    total = np.cumsum(deltas, dtype=np.uint64)
    limit = np.uint64(1) << np.uint64(3 * grid.bits)
    if grid.count and (
        np.any(deltas >= limit) or np.any(total[1:] < total[:-1]) or total[-1] >= limit
    ):
        raise _failure(source, f"has positions outside its {grid.bits}-bit grid")
    positions = grid.origin + morton_grid(total) * grid.step
    if grid.count and not np.all(np.abs(positions) <= FLOAT32_MAX):
        raise _failure(source, "has positions beyond the float32 range (its grid's origin or step)")
    return positions.astype(np.float32)


def _codes(column: _Column, source: str) -> np.ndarray:
    """A quantised column's codes, checked to fit its bits."""
    if np.any(column.codes > (1 << column.spec.bits) - 1):
        raise _failure(
            source, f"column {column.spec.name!r} has codes beyond {column.spec.bits} bits"
        )
    return column.codes


def _linear(column: _Column, source: str) -> np.ndarray:
    """The values of a linear column, through its transform's inverse."""
    c = column.spec
    inverse = LINEAR_TRANSFORMS[c.transform][1]  # (f_dc: "linear" in older messages)
    codes = _codes(column, source)
    return inverse(dequantise_linear(codes, np.array(c.low), np.array(c.high), c.bits))


def _log_linear(column: _Column, source: str) -> np.ndarray:
    """The values [N] of a log-linear column."""
    c = column.spec
    return dequantise_log(_codes(column, source)[:, 0], c.low[0], c.high[0], c.bits)


def _decode_rotations(column: _Column | None, n: int) -> np.ndarray:
    """[N, 4] quaternions of the smallest-three column; the identity for an isotropic map."""
    if column is None:
        return np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1))
    return decode_smallest_three(column.codes[:, 0])


def _decode_sh_rest(column: _Column | None, degree: int, source: str) -> np.ndarray | None:
    """[N, K, 3] SH rest coefficients of the f_rest column (None at degree 0)."""
    k = SH_REST_COUNTS[degree]
    if column is None or not k:
        return None
    values = _linear(column, source)
    return values.reshape(len(values), k, 3)


def _decode_pwas(
    columns: dict[str, _Column], raw: set[str], coded: set[str], n: int, source: str
) -> dict[str, np.ndarray]:
    """The PWAS state a message carries: its float32 sums as they are, or its coded score with
    the coded sums (importance_sum = score x (weight + eps)), or its score alone."""
    if raw:
        return {name: columns[name].codes[:, 0] for name in raw}
    if "importance" not in columns:
        return {}
    score = _log_linear(columns["importance"], source)
    if not coded:
        return {"importance_sum": score, "importance_weight": np.ones(n, np.float32)}
    weight = _log_linear(columns["importance_weight"], source)
    return {
        "importance_sum": score * (weight + np.float32(PWAS_EPS)),
        "importance_weight": weight,
        "alpha_t_sum": _log_linear(columns["alpha_t_sum"], source),
    }


def _decode_ids(column: _Column | None) -> dict[str, np.ndarray]:
    """The ids of the delta-coded id column (none: the map numbers its Gaussians itself)."""
    if column is None:
        return {}
    return {"ids": np.cumsum(column.codes[:, 0], dtype=np.uint32)}
