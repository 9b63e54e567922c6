"""Niantic's SPZ format: a compressed 3DGS map, read and written with numpy alone (no torch).

Layout (little-endian). A header: magic 0x5053474E ("NGSP"), version, the number of Gaussians,
SH degree, `fractional_bits`, flags (bit 0: antialiased; bit 1: extensions follow), then the
attributes stream by stream, each a flat array:

- positions: 3 x 24-bit signed fixed point with `fractional_bits` fraction bits (9 bytes);
- alphas: the opacity after the sigmoid, 8 bits: round(255 sigmoid(logit));
- colours: the SH DC term, 8 bits: round(255 (0.15 f_dc + 0.5));
- scales: the log scale, 8 bits: round(16 (log s + 10)), so log s in [-10, 5.94];
- rotations: version 2 stores x y z of the unit quaternion with w >= 0, 8 bits each; versions
  3 and 4 store the "smallest three": 2 bits naming the largest component (made positive),
  then for each other component a sign bit and 9 bits of |q| / sqrt(1/2), in 32 bits;
- SH rest: [N, K, 3] (colour innermost) 8-bit codes round(128 x + 128); the writer rounds the
  codes of degree 1 to multiples of 8 and higher degrees to multiples of 16 (the reference
  writer's defaults, which shrink the compressed stream).

Versions 2 and 3 gzip the 16-byte header and the streams as one; version 4 has a 32-byte plain
header (adding the stream count and the byte offset of a table of contents), optional
extension records, the table (compressed and uncompressed size of each stream, two uint64)
and each non-empty stream compressed on its own with zstd. We write version 4 by default (what
`@playcanvas/splat-transform` 3.7.0 writes and reads) and version 3 on request, and read 2-4.
The writer stores the Gaussians along a Morton curve of their positions (`storage_order`), which
shortens the compressed streams; SPZ has no ids, so nothing else sees the order.

Coordinates: the values are stored as the map holds them (3DGS PLY's RDF axes), with no axis
flip, as splat-transform and the reference library with an unspecified coordinate system do;
the reference command-line converter instead flips PLY maps into RUB ("y up", a rotation of
180 degrees about x), so its files read here upside down.

Every file is untrusted: the point count is checked against `MAX_SPZ_GAUSSIANS` and against the
input's size before anything is allocated, and decompression never produces more than the
header's count implies.
"""

from __future__ import annotations

import gzip
import io
import logging
import struct
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import IO

import numpy as np
import zstandard

from gscompress.errors import MapError, SpzFormatError
from gscompress.gaussians import SH_REST_COUNTS, GaussianMap
from gscompress.io.columns import map_from_columns
from gscompress.io.decode_budget import (
    DecodeBudget,
    FileSlice,
    GzipReader,
    file_size,
    inflate_zstd,
    read_slice,
)
from gscompress.io.files import check_input, check_output, write_bytes_atomic
from gscompress.io.quantise import (
    MAX_POSITION_BITS,
    decode_smallest_three,
    encode_smallest_three,
    morton_codes,
)

log = logging.getLogger(__name__)

MAGIC = 0x5053474E
"""The first four bytes of an SPZ header ("NGSP" little-endian)."""

VERSIONS_READ = (2, 3, 4)
VERSIONS_WRITTEN = (3, 4)

MAX_SPZ_GAUSSIANS = 1 << 26
"""Largest Gaussian count read or written (67M: about 1 GB of packed streams, 4 GB decoded)."""

COLOR_SCALE = 0.15
"""Colour code = 255 (COLOR_SCALE f_dc + 0.5)."""

FRACTIONAL_BITS = 12
"""Default fraction bits of positions (a step of 1/4096 m = 0.24 mm, positions to +-2048 m)."""

SH1_BUCKET, SH_REST_BUCKET = 8, 16
"""Multiples the writer rounds SH codes to (degree 1; degrees 2-3)."""

ZSTD_LEVEL = 9
"""zstd level of version-4 streams (the reference writes 12: on a SLAM map barely smaller and
much slower; docs/codecs.md, "PLY, SPZ and SOG")."""

_FLAG_ANTIALIASED, _FLAG_EXTENSIONS = 0x1, 0x2
_LEGACY_HEADER = struct.Struct("<IIIBBBB")  # magic version count degree fraction flags reserved
_HEADER = struct.Struct("<IIIBBBBI12x")  # ... degree fraction flags streams toc_offset reserved
_TOC_ENTRY = struct.Struct("<QQ")
_CODE_REACH = np.float32(1e30)


# ------------------------------------------------------------------ public API


def encode_bytes(
    gaussians: GaussianMap,
    *,
    version: int = 4,
    fractional_bits: int | None = None,
    ordered: bool = True,
) -> bytes:
    """The SPZ file of a map.

    Args:
        gaussians: the map (ids and importance are not stored: SPZ has no field for them).
        version: 4 (per-stream zstd) or 3 (one gzip stream).
        fractional_bits: fraction bits of the fixed-point positions; None: `FRACTIONAL_BITS`,
            or fewer when the map reaches beyond the +-2^23 steps that 24 bits hold.
        ordered: store the Gaussians in `storage_order` (along a Morton curve: neighbours in
            space share their positions' high bytes, and the streams compress better) rather
            than in the map's order. SPZ keeps no ids, so a reader sees no difference.

    Raises:
        MapError: an empty map, more than `MAX_SPZ_GAUSSIANS`, or positions beyond the range
            of 24-bit fixed point even without fraction bits (+-8388 km).
    """
    if version not in VERSIONS_WRITTEN:
        raise MapError(f"SPZ version {version} cannot be written; choose 3 or 4")
    n = len(gaussians)
    if n == 0:
        raise MapError("an SPZ file cannot hold an empty map (readers refuse a count of 0)")
    if n > MAX_SPZ_GAUSSIANS:
        raise MapError(f"{n} Gaussians exceed the {MAX_SPZ_GAUSSIANS} an SPZ file may hold here")
    bits = _fraction_bits(gaussians.means, fractional_bits)
    streams = _pack(gaussians, bits, ordered)
    degree = gaussians.sh_degree
    if version == 3:
        header = _LEGACY_HEADER.pack(MAGIC, 3, n, degree, bits, 0, 0)
        raw = b"".join([header, *streams])
        return gzip.compress(raw, compresslevel=6, mtime=0)
    filled = [s for s in streams if len(s)]
    with ThreadPoolExecutor(len(filled)) as pool:  # (zstd releases the GIL)
        chunks = list(
            pool.map(lambda s: zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress(s), filled)
        )
    sizes = [len(s) for s in filled]
    header = _HEADER.pack(MAGIC, 4, n, degree, bits, 0, len(chunks), _HEADER.size)
    toc = b"".join(_TOC_ENTRY.pack(len(c), u) for c, u in zip(chunks, sizes, strict=True))
    return b"".join([header, toc, *chunks])


def decode_bytes(data: bytes, source: str = "SPZ data") -> GaussianMap:
    """The map in an SPZ file's bytes (versions 2-4), validated.

    Ids are 0..N-1 and the map is unscored (SPZ stores neither); a map whose three log-scale
    codes agree in every row comes back isotropic.

    Raises:
        SpzFormatError: naming `source` and what is wrong (not SPZ, an unsupported version or
            SH degree, a count beyond the limits or the input, truncated or corrupt streams).
    """
    return _read(io.BytesIO(data), source)


def write_spz(
    gaussians: GaussianMap,
    path: str | Path,
    *,
    version: int = 4,
    inputs: tuple[str | Path, ...] = (),
    force: bool = False,
) -> Path:
    """Write a map as an SPZ file (atomically: temporary file, then rename).

    Returns:
        The output path.
    """
    path = check_output(path, inputs, force, suffix=".spz")
    return write_bytes_atomic(path, encode_bytes(gaussians, version=version))


def read_spz(path: str | Path) -> GaussianMap:
    """Read an SPZ file into a validated GaussianMap (see `decode_bytes`).

    Raises:
        SpzFormatError: missing, unreadable, or not a valid SPZ map.
    """
    path = check_input(path, SpzFormatError)
    try:
        with open(path, "rb") as f:
            return _read(f, str(path))
    except OSError as exc:
        raise SpzFormatError(f"{path}: cannot read ({exc.strerror or exc})") from None


def opacity_logits(alphas: np.ndarray) -> np.ndarray:
    """Logits of opacities read from 8-bit codes; codes 0 and 255 read as a quarter step
    inside (0, 1), so that every logit is finite and encodes back to its code."""
    alphas = np.clip(alphas, np.float32(0.25 / 255), np.float32(1 - 0.25 / 255))
    return np.log(alphas / (1 - alphas)).astype(np.float32)


def is_spz(head: bytes) -> bool:
    """Whether a file beginning with `head` looks like SPZ (gzip, or an NGSP header)."""
    return head[:2] == b"\x1f\x8b" or head[:4] == struct.pack("<I", MAGIC)


# ------------------------------------------------------------------ encoding


def storage_order(means: np.ndarray, fractional_bits: int = FRACTIONAL_BITS) -> np.ndarray:
    """[N] indices that sort positions along a Morton (Z-order) curve of their fixed-point
    codes (the order `encode_bytes` stores Gaussians in)."""
    return _morton_order(_fixed(means, fractional_bits))


def _fixed(means: np.ndarray, bits: int) -> np.ndarray:
    """[N, 3] int32 fixed-point positions with `bits` fraction bits."""
    return np.round(means.astype(np.float64) * (1 << bits)).astype(np.int32)


def _morton_order(fixed: np.ndarray) -> np.ndarray:
    """Indices sorting fixed-point positions along a Morton curve (of their top 21 bits per
    axis: `gscompress.io.quantise.morton_codes`)."""
    fixed = fixed.astype(np.int64)
    cells = fixed - fixed.min(axis=0) if len(fixed) else fixed
    top = int(cells.max()).bit_length() if len(cells) else 0
    return np.argsort(morton_codes(cells >> max(0, top - MAX_POSITION_BITS)), kind="stable")


def _fraction_bits(means: np.ndarray, requested: int | None) -> int:
    """Fraction bits that keep every position within 24-bit fixed point."""
    reach = float(np.max(np.abs(means))) if len(means) else 0.0
    limit = (1 << 23) - 1
    if requested is not None:
        if not 0 <= requested <= 24:
            raise MapError(f"fractional_bits {requested} is outside 0..24")
        if reach * (1 << requested) > limit:
            raise MapError(
                f"positions reach {reach:g} m, beyond 24-bit fixed point with {requested} "
                "fraction bits"
            )
        return requested
    for bits in range(FRACTIONAL_BITS, -1, -1):
        if reach * (1 << bits) <= limit:
            if bits < FRACTIONAL_BITS:
                log.warning("positions reach %g m: SPZ positions get %d fraction bits", reach, bits)
            return bits
    raise MapError(f"positions reach {reach:g} m, beyond the range of SPZ's 24-bit positions")


def _codes(values: np.ndarray, scale: float, offset: float) -> np.ndarray:
    """uint8 codes round(values * scale + offset), clipped to 0..255 (halves round up, as the
    reference writer's rounding does for these non-negative codes). Values are first held
    within +-1e30, where every code is already 0 or 255, so that a float32 product cannot
    overflow (a colour of 3.4e38 is a valid map's)."""
    held = np.clip(values, -_CODE_REACH, _CODE_REACH)
    return np.clip(np.floor(held * np.float32(scale) + np.float32(offset + 0.5)), 0, 255).astype(
        np.uint8
    )


def _pack(g: GaussianMap, bits: int, ordered: bool) -> list[bytes]:
    """The six attribute streams (the SH one empty at degree 0), in `storage_order` when
    `ordered` (the codes are permuted, not the map: bytes move, not floats)."""
    n = len(g)
    fixed = _fixed(g.means, bits)
    order = _morton_order(fixed) if ordered else slice(None)
    positions = fixed[order].astype("<i4").view(np.uint8).reshape(n, 3, 4)[:, :, :3]
    clipped = int(np.count_nonzero((g.log_scales < -10.0) | (g.log_scales > 5.9375 + 1 / 32)))
    if clipped:
        log.warning(
            "%d log-scale values lie outside SPZ's range [-10, 5.94] and are clipped", clipped
        )
    scales = _codes(np.broadcast_to(g.log_scales, (n, 3)), 16.0, 160.0)
    alphas = _codes(0.5 + 0.5 * np.tanh(0.5 * g.opacity_logits), 255.0, 0.0)  # (no overflow)
    colors = _codes(g.sh_dc, COLOR_SCALE * 255.0, 127.5)
    quats = g.quats.astype(np.float64)  # (float64: the squares of tiny float32 stay normal)
    rotations = encode_smallest_three(quats / np.linalg.norm(quats, axis=1, keepdims=True))
    sh = _sh_codes(g.sh_rest)
    return [
        np.ascontiguousarray(positions).tobytes(),
        alphas[order].tobytes(),
        colors[order].tobytes(),
        scales[order].tobytes(),
        rotations[order].astype("<u4").tobytes(),
        sh[order].tobytes(),
    ]


def _sh_codes(sh_rest: np.ndarray) -> np.ndarray:
    """[N, K, 3] uint8 SH codes, degree 1 rounded to multiples of 8, the rest to 16."""
    if sh_rest.shape[1] == 0:
        return np.zeros((len(sh_rest), 0, 3), np.uint8)
    q = np.round(sh_rest * np.float32(128)).clip(-1 << 20, 1 << 20).astype(np.int32) + 128
    bucket = np.full(sh_rest.shape[1], SH_REST_BUCKET, np.int32)
    bucket[:3] = SH1_BUCKET
    q = (q + bucket[None, :, None] // 2) // bucket[None, :, None] * bucket[None, :, None]
    return np.clip(q, 0, 255).astype(np.uint8)


# ------------------------------------------------------------------ decoding


class _Streams:
    """The header fields and the raw attribute streams of one file."""

    def __init__(self, version: int, count: int, degree: int, antialiased: bool) -> None:
        self.version = version
        self.count = count
        self.degree = degree
        self.antialiased = antialiased
        self.data: list[np.ndarray] = []

    def sizes(self) -> list[int]:
        """Byte sizes of the six streams this header implies."""
        n, k = self.count, SH_REST_COUNTS[self.degree]
        return [9 * n, n, 3 * n, 3 * n, (3 if self.version == 2 else 4) * n, 3 * k * n]


def _check_header(source: str, version: int, count: int, degree: int, input_bytes: int) -> None:
    """Refuse versions, degrees and counts this reader does not take, and a count whose map is
    more than the input's bytes may decode to (`gscompress.io.decode_budget`)."""
    if version not in VERSIONS_READ:
        raise SpzFormatError(
            f"{source}: SPZ version {version} is not supported (versions 2, 3 and 4 are)"
        )
    if degree not in SH_REST_COUNTS:
        raise SpzFormatError(f"{source}: SH degree {degree} is not supported (0 to 3 are)")
    if count == 0:
        raise SpzFormatError(f"{source}: declares no Gaussians")
    if count > MAX_SPZ_GAUSSIANS:
        raise SpzFormatError(
            f"{source}: declares {count} Gaussians, more than the {MAX_SPZ_GAUSSIANS} read here"
        )
    DecodeBudget("spz", input_bytes, source, SpzFormatError).check_map(count, degree)


def _read(stream: IO[bytes], source: str) -> GaussianMap:
    """The validated map of an SPZ file open in `stream` (read by checked slices, a stream at a
    time, never whole)."""
    streams, bits = _unpack_streams(stream, source)
    try:
        return _decode(streams, bits, source).validate()
    except MapError as exc:
        raise SpzFormatError(f"{source}: {exc}") from None


def _unpack_streams(stream: IO[bytes], source: str) -> tuple[_Streams, int]:
    """The streams of a file and its fraction bits."""
    size = file_size(stream)
    stream.seek(0)
    head = stream.read(_HEADER.size)
    if head[:2] == b"\x1f\x8b":
        stream.seek(0)
        return _unpack_gzip(stream, size, source)
    if len(head) < 4 or head[:4] != struct.pack("<I", MAGIC):
        raise SpzFormatError(f"{source}: not an SPZ file (neither gzip nor an NGSP header)")
    if len(head) < _HEADER.size:
        raise SpzFormatError(f"{source}: truncated: {size} bytes, the header needs 32")
    _magic, version, count, degree, bits, flags, n_streams, toc = _HEADER.unpack(head)
    if version < 4:
        raise SpzFormatError(f"{source}: an ungzipped SPZ header says version {version}; needs 4")
    _check_header(source, version, count, degree, size)
    streams = _Streams(version, count, degree, bool(flags & _FLAG_ANTIALIASED))
    blocks = _stream_table(stream, size, streams, n_streams, toc, flags, source)
    with ThreadPoolExecutor(len(blocks)) as pool:  # (zstd releases the GIL)
        inflated = iter(pool.map(lambda block: _stream(*block), blocks))
    streams.data = [next(inflated) if size else np.zeros(0, np.uint8) for size in streams.sizes()]
    return streams, bits


def _stream_table(
    stream: IO[bytes],
    size: int,
    streams: _Streams,
    n_streams: int,
    toc: int,
    flags: int,
    source: str,
) -> list[tuple[IO[bytes], int, str]]:
    """The compressed streams of a version-4 file (each a slice of the file), with the bytes each
    must inflate to and its name, once the table of contents agrees with the header and
    accounts for every byte of the file."""
    sizes = [s for s in streams.sizes() if s]
    if n_streams != len(sizes):
        raise SpzFormatError(f"{source}: {n_streams} streams, expected {len(sizes)}")
    if toc < _HEADER.size or toc + n_streams * _TOC_ENTRY.size > size:
        raise SpzFormatError(f"{source}: truncated or corrupt: the stream table lies outside")
    if toc > _HEADER.size and not flags & _FLAG_EXTENSIONS:
        raise SpzFormatError(f"{source}: {toc - _HEADER.size} unexplained bytes before the table")
    table = read_slice(stream, toc, n_streams * _TOC_ENTRY.size, source, SpzFormatError)
    entries = [_TOC_ENTRY.unpack_from(table, i * _TOC_ENTRY.size) for i in range(n_streams)]
    offset = toc + len(table)
    spans = []
    for i, ((packed, unpacked), expected) in enumerate(zip(entries, sizes, strict=True)):
        if unpacked != expected:
            raise SpzFormatError(
                f"{source}: stream {i} holds {unpacked} bytes, {streams.count} Gaussians need "
                f"{expected}"
            )
        if packed > size - offset:
            raise SpzFormatError(f"{source}: truncated: stream {i} runs past the end of the file")
        spans.append((offset, packed, expected))
        offset += packed
    if offset != size:
        raise SpzFormatError(f"{source}: {size - offset} bytes after the last stream")
    lock = threading.Lock()
    return [
        (
            io.BufferedReader(FileSlice(stream, start, packed, lock)),
            expected,
            f"{source}: stream {i}",
        )
        for i, (start, packed, expected) in enumerate(spans)
    ]


def _stream(block: IO[bytes], expected: int, what: str) -> np.ndarray:
    """One zstd stream of exactly `expected` bytes (read from the file as it inflates)."""
    return np.frombuffer(inflate_zstd(block, expected, what, SpzFormatError), np.uint8)


def _unpack_gzip(stream: IO[bytes], size: int, source: str) -> tuple[_Streams, int]:
    """The streams of a version 2-3 file (one gzip member, inflated as it is read)."""
    reader = GzipReader(stream, source, SpzFormatError)
    head = reader.read(_LEGACY_HEADER.size)
    if len(head) < _LEGACY_HEADER.size:
        raise SpzFormatError(f"{source}: truncated: the gzip stream ends inside the header")
    magic, version, count, degree, bits, flags, _ = _LEGACY_HEADER.unpack(head)
    if magic != MAGIC:
        raise SpzFormatError(f"{source}: not an SPZ file (gzip without an NGSP header)")
    _check_header(source, version, count, degree, size)
    streams = _Streams(version, count, degree, bool(flags & _FLAG_ANTIALIASED))
    total = sum(streams.sizes())
    body = reader.read(total)
    if len(body) < total:
        raise SpzFormatError(
            f"{source}: truncated: {len(body)} bytes of attributes, {count} Gaussians need {total}"
        )
    extra = reader.read(1)
    if not extra and not reader.eof:
        raise SpzFormatError(f"{source}: truncated: the gzip stream does not end")
    if extra and not flags & _FLAG_EXTENSIONS:
        raise SpzFormatError(f"{source}: data after the {count} Gaussians the header declares")
    array = np.frombuffer(body, np.uint8)
    ends = np.cumsum(streams.sizes())
    streams.data = [
        array[end - size : end] for end, size in zip(ends, streams.sizes(), strict=True)
    ]
    return streams, bits


def _decode(s: _Streams, bits: int, source: str) -> GaussianMap:
    """The map of decoded streams."""
    n = s.count
    raw = s.data[0].reshape(n, 3, 3).astype(np.int32)
    fixed = raw[..., 0] | raw[..., 1] << 8 | raw[..., 2] << 16
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    means = (fixed * np.float64(2.0**-bits)).astype(np.float32)
    logits = opacity_logits(s.data[1].astype(np.float32) / 255)
    sh_dc = (s.data[2].reshape(n, 3).astype(np.float32) / 255 - 0.5) / np.float32(COLOR_SCALE)
    log_scales = s.data[3].reshape(n, 3).astype(np.float32) / 16 - 10
    if s.version == 2:
        xyz = s.data[4].reshape(n, 3).astype(np.float32) / np.float32(127.5) - 1
        w = np.sqrt(np.maximum(0, 1 - np.square(xyz).sum(axis=1)))
        quats = np.concatenate([w[:, None], xyz], axis=1)
    else:
        quats = decode_smallest_three(s.data[4].view("<u4"))
    k = SH_REST_COUNTS[s.degree]
    rest = (s.data[5].reshape(n, k, 3).astype(np.float32) - 128) / 128
    if s.antialiased:
        log.debug("%s was made for antialiased rendering; it is read as an ordinary map", source)
    cols: dict[str, np.ndarray] = {"x": means[:, 0], "y": means[:, 1], "z": means[:, 2]}
    cols.update({f"scale_{i}": log_scales[:, i] for i in range(3)})
    cols.update({f"rot_{i}": quats[:, i] for i in range(4)})
    cols.update({"opacity": logits, **{f"f_dc_{i}": sh_dc[:, i] for i in range(3)}})
    by_channel = rest.transpose(0, 2, 1).reshape(n, 3 * k)
    cols.update({f"f_rest_{i}": by_channel[:, i] for i in range(3 * k)})
    return map_from_columns(cols, source)
