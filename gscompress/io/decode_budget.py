"""The decode budget: how much an untrusted input may decode to, asked before it is decoded.

Every reader of a file from elsewhere (SPZ, SOG, PLY and compressed PLY, a log's chunks, maps
and keyframes, the frames of a sequence) asks here before it allocates what the file declares:
at most `FORMATS[format].ratio` times the input's own bytes (below `FLOOR_BYTES` no ratio
applies) and never more than `MAX_DECODED_BYTES`. What counts as decoded is what the reader
builds: for a map, `map_bytes` of its declared count at its declared SH degree; for an image,
its pixels at their declared size (`check_image`, from the header, before the pixels); for a
compressed stream, its inflated bytes. Each ratio sits beside the largest one measured on
legitimate files in docs/fuzzing.md (`bench/decode_ratios.py` measures them).

Inflating (zstd, gzip, lz4, bz2; zip members are read with a bound) runs with a running limit: a
stream stops the moment it produces more than it declared, whatever its frame says.
"""

from __future__ import annotations

import bz2
import io
import os
import threading
import zlib
from dataclasses import dataclass
from typing import IO, TYPE_CHECKING

import zstandard

from gscompress.errors import GscError
from gscompress.gaussians import SH_REST_COUNTS

if TYPE_CHECKING:
    from PIL.Image import Image

FLOOR_BYTES = 1 << 20
"""Below this many decoded bytes no ratio is asked (a tiny file's headers and tables)."""

MAX_DECODED_BYTES = 8 << 30
"""The most any one input may decode to, whatever its size: a map of some 34 million Gaussians
at SH degree 3 (110 million at degree 0), an image of 2.9 billion RGB pixels."""

BLOCK_BYTES = 1 << 20
"""Compressed bytes read from a file at a time while inflating."""


@dataclass(frozen=True)
class Format:
    """A format's decode budget.

    Attributes:
        name: the key in `FORMATS`.
        ratio: the most decoded bytes per byte of input.
        decoded: what counts as decoded, for messages and docs.
    """

    name: str
    ratio: float
    decoded: str


FORMATS: dict[str, Format] = {
    f.name: f
    for f in (
        Format("spz", 64, "the map"),
        Format("sog", 64, "the map"),
        Format("ply", 8, "the map"),
        Format("compressed-ply", 8, "the map"),
        Format("compact", 64, "the map"),
        Format("log", 64, "a map or the keyframes of an MCAP log"),
        Format("mcap-chunk", 100, "a chunk's records"),
        Format("image", 1100, "the pixels"),
    )
}
"""Every format's ratio; docs/fuzzing.md lists each beside the largest measured on real files."""


def map_bytes(count: int, sh_degree: int) -> int:
    """Bytes of a decoded map of `count` Gaussians at `sh_degree` (anisotropic, with ids and the
    PWAS sums: 72 + 12 x K bytes per Gaussian, K the SH rest coefficients per channel)."""
    return count * (72 + 12 * SH_REST_COUNTS.get(sh_degree, 15))


@dataclass(frozen=True)
class DecodeBudget:
    """What one input may decode to.

    Attributes:
        format: a key of `FORMATS`.
        input_bytes: the input's size (a file's, a message's, a compressed stream's).
        source: the input, leading every message.
        error: the GscError raised for an input over budget.
    """

    format: str
    input_bytes: int
    source: str
    error: type[GscError]

    @property
    def limit(self) -> int:
        """The most bytes the input may decode to."""
        ratio = FORMATS[self.format].ratio
        return int(min(MAX_DECODED_BYTES, max(FLOOR_BYTES, ratio * self.input_bytes)))

    def check(self, decoded_bytes: int, what: str) -> int:
        """`decoded_bytes`, when the input may decode to that many (`what` the input declares,
        for the message: "declares 1048576 Gaussians at SH degree 3 (264241152 bytes)").

        Raises:
            error: more than `limit`.
        """
        if decoded_bytes > self.limit:
            ratio = FORMATS[self.format].ratio
            raise self.error(
                f"{self.source}: {what}, more than its {self.input_bytes} bytes may decode to "
                f"({ratio:g} times as many, {MAX_DECODED_BYTES >> 30} GiB at most)"
            )
        return decoded_bytes

    def check_map(self, count: int, sh_degree: int) -> int:
        """`check` of a map of `count` Gaussians at `sh_degree` (`map_bytes`)."""
        decoded = map_bytes(count, sh_degree)
        return self.check(
            decoded, f"declares {count} Gaussians at SH degree {sh_degree} ({decoded} bytes)"
        )


def file_size(stream: IO[bytes]) -> int:
    """The size of a seekable binary stream (its position kept)."""
    position = stream.tell()
    size = stream.seek(0, os.SEEK_END)
    stream.seek(position)
    return size


class FileSlice(io.RawIOBase):
    """`length` bytes of a seekable stream from `offset`, read on demand, a block at a time and
    never past them. Slices of one stream read in several threads share its `lock`."""

    def __init__(
        self, stream: IO[bytes], offset: int, length: int, lock: threading.Lock | None = None
    ):
        self.stream, self.position, self.end = stream, offset, offset + length
        self.lock = lock or threading.Lock()

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: bytearray | memoryview) -> int:  # type: ignore[override]
        """Fill `buffer` from the slice; 0 at its end."""
        n = min(len(buffer), self.end - self.position)
        if n <= 0:
            return 0
        with self.lock:
            self.stream.seek(self.position)
            data = self.stream.read(n)
        buffer[: len(data)] = data
        self.position += len(data)
        return len(data)


def read_slice(
    stream: IO[bytes], offset: int, length: int, where: str, error: type[GscError]
) -> bytes:
    """Exactly `length` bytes at `offset` of a seekable stream, refused (before reading) when
    they run past its end."""
    size = file_size(stream)
    if offset < 0 or length < 0 or offset + length > size:
        raise error(f"{where}: {length} bytes at offset {offset} run past the end ({size} bytes)")
    stream.seek(offset)
    return stream.read(length)


def inflate_zstd(
    data: bytes | bytearray | memoryview | IO[bytes],
    size: int,
    where: str,
    error: type[GscError],
    several_frames: bool = False,
) -> bytes | bytearray:
    """A zstd frame (bytes, or a stream read in blocks) inflated to exactly `size` bytes, never
    more: refused (`error`, led by `where`) when it is not zstd, declares another size, is
    corrupt, or holds more or less. Frames that follow the first are inflated too, under the
    same running limit (a frame that declares the whole size followed by a bomb stops one byte
    past it); with `several_frames` the first may declare fewer bytes than `size`, the frames
    after it holding the rest (a stream written a frame at a time)."""
    source = io.BytesIO(data) if isinstance(data, bytes | bytearray | memoryview) else data
    head = source.read(18)  # (a zstd frame header's longest)
    if size == 0 and not head:
        return b""
    try:
        declared = zstandard.frame_content_size(head)
    except zstandard.ZstdError:
        raise error(f"{where} is not a zstd frame") from None
    if declared > size or (declared not in (-1, size) and not several_frames):
        raise error(f"{where} declares {declared} bytes, not {size}")
    joined = io.BufferedReader(_Prefixed(head, source))
    try:
        with zstandard.ZstdDecompressor().stream_reader(
            joined, read_size=BLOCK_BYTES, closefd=False
        ) as reader:
            out = _read_at_most(reader, size + 1)
    except zstandard.ZstdError as exc:
        raise error(f"{where} is corrupt ({' '.join(str(exc).split())[:80]})") from None
    if len(out) != size:
        raise error(f"{where} decompresses to {len(out)} bytes, not {size}")
    return out


class GzipReader:
    """A gzip stream inflated as it is read: `read(n)` returns at most `n` bytes, reading the
    compressed stream in blocks (never all of it at once).

    Raises (from `read`): `error`, led by `where`, for corrupt data.
    """

    def __init__(self, source: IO[bytes], where: str, error: type[GscError]):
        self.source, self.where, self.error = source, where, error
        self.inflater = zlib.decompressobj(16 + zlib.MAX_WBITS)
        self.pending = b""

    def read(self, n: int) -> bytearray:
        """Up to `n` inflated bytes (fewer only at the stream's end)."""
        out = bytearray()
        try:
            while len(out) < n and not self.inflater.eof:
                if not self.pending:
                    self.pending = self.source.read(BLOCK_BYTES)
                    if not self.pending:
                        break
                out += self.inflater.decompress(self.pending, n - len(out))
                self.pending = self.inflater.unconsumed_tail
        except zlib.error as exc:
            raise self.error(f"{self.where}: corrupt gzip stream ({exc})") from None
        return out

    @property
    def eof(self) -> bool:
        """Whether the gzip stream has ended."""
        return self.inflater.eof


def inflate_lz4(data: bytes | bytearray, size: int, where: str, error: type[GscError]) -> bytes:
    """lz4 frames (one or more in a row) inflated to at most `size` + 1 bytes: refused when they
    are corrupt, cut short, or produce more than `size`."""
    import lz4.frame  # (a dependency of mcap; only lz4 chunks of other writers need it)

    parts: list[bytes] = []
    produced = 0
    rest = data
    while rest:
        decompressor = lz4.frame.LZ4FrameDecompressor()
        try:  # (lz4 reports corrupt data as a RuntimeError)
            part = decompressor.decompress(rest, max_length=size + 1 - produced)
        except RuntimeError as exc:
            raise error(f"{where} is corrupt ({exc})") from None
        parts.append(part)
        produced += len(part)
        if produced > size or (not decompressor.needs_input and not decompressor.eof):
            raise error(f"{where} inflates beyond {size} bytes")
        if not decompressor.eof:
            raise error(f"{where} is cut short")
        rest = decompressor.unused_data or b""
    return b"".join(parts)


def inflate_bz2(data: bytes | bytearray, size: int, where: str, error: type[GscError]) -> bytes:
    """bz2 streams (one or more in a row) inflated to at most `size` + 1 bytes: refused when they
    are corrupt, cut short, or produce more than `size`."""
    parts: list[bytes] = []
    produced = 0
    rest = bytes(data)
    while rest:
        decompressor = bz2.BZ2Decompressor()
        try:
            part = decompressor.decompress(rest, max_length=size + 1 - produced)
        except (OSError, ValueError) as exc:
            raise error(f"{where} is corrupt ({exc})") from None
        parts.append(part)
        produced += len(part)
        if produced > size:
            raise error(f"{where} inflates beyond {size} bytes")
        if not decompressor.eof:  # (output left at the limit was refused above)
            raise error(f"{where} is cut short")
        rest = decompressor.unused_data
    return b"".join(parts)


def check_image(image: Image, budget: DecodeBudget, what: str = "image") -> int:
    """The bytes an opened (not yet decoded) image's pixels take by its header, refused before
    they are decoded when they are more than `budget` allows.

    Raises:
        budget.error: over budget.
    """
    width, height = image.size
    bands = len(image.getbands())
    bytes_per_band = 2 if image.mode.startswith("I;16") else 4 if image.mode in ("I", "F") else 1
    decoded = width * height * bands * bytes_per_band
    return budget.check(decoded, f"{what} of {width}x{height} {image.mode} ({decoded} bytes)")


class _Prefixed(io.RawIOBase):
    """`head` followed by the rest of `source` (what a frame-size peek already read)."""

    def __init__(self, head: bytes, source: IO[bytes]):
        self.head, self.source = head, source

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: bytearray | memoryview) -> int:  # type: ignore[override]
        """Fill `buffer` from the head, then from the source."""
        if self.head:
            n = min(len(buffer), len(self.head))
            buffer[:n], self.head = self.head[:n], self.head[n:]
            return n
        data = self.source.read(len(buffer))
        buffer[: len(data)] = data
        return len(data)


def _read_at_most(reader: IO[bytes], limit: int) -> bytearray:
    """At most `limit` bytes of a stream (less only at its end), read into one buffer."""
    out = bytearray(limit)
    view, filled = memoryview(out), 0
    while filled < limit and (n := reader.readinto(view[filled:])):  # type: ignore[attr-defined]
        filled += n
    view.release()
    del out[filled:]
    return out
