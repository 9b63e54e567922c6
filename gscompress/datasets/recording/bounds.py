"""Bounds on what rosbags inflates of a bag: a ROS 1 bag's chunks are checked against the
decode budget from their headers and inflated by a decompressor that stops at their declared
size."""

from __future__ import annotations

import bz2
from collections.abc import Callable
from typing import Any

from gscompress.errors import DatasetError


def bound_ros1_chunks(reader: Any) -> None:
    """Give each chunk of a ROS 1 bag a decompressor bounded by the chunk's declared size,
    itself checked against the chunk's compressed size (`check_chunk_size`) before anything
    is inflated. rosbags inflates a chunk whole; a bomb would otherwise be inflated first."""
    from rosbags.rosbag1.reader import Header, RecordType
    from rosbags.rosbag1.reader import Reader as Reader1

    for sub in reader.readers:
        bio = sub.bio if isinstance(sub, Reader1) else None
        if bio is None:
            continue
        for info in sub.chunk_infos:
            bio.seek(info.pos)
            header = Header.read(bio, RecordType.CHUNK)
            size, compression = header.get_uint32("size"), header.get_string("compression")
            chunk = sub.chunks[info.pos]
            check_chunk_size(size, chunk.datasize, compression, str(sub.path))
            sub.chunks[info.pos] = chunk._replace(
                decompressor=_bounded_inflate(compression, size, str(sub.path))
            )


def check_chunk_size(size: int, compressed: int, compression: str, source: str) -> None:
    """Refuse a ROS 1 chunk that declares more than the decode budget of an MCAP chunk allows
    (`gscompress.io.decode_budget`, format `mcap-chunk`), before it is inflated."""
    from gscompress.io.decode_budget import DecodeBudget
    from gscompress.io.mcap_bounds import MAX_CHUNK_BYTES

    if compression == "none" and size != compressed:
        raise DatasetError(f"{source}: a chunk of {compressed} bytes claims {size} uncompressed")
    if size > MAX_CHUNK_BYTES:
        raise DatasetError(
            f"{source}: a chunk of {compressed} bytes claims {size} bytes uncompressed, more "
            f"than the {MAX_CHUNK_BYTES >> 30} GiB a chunk may hold"
        )
    budget = DecodeBudget("mcap-chunk", compressed, source, DatasetError)
    budget.check(size, f"a chunk of {compressed} bytes claims {size} bytes uncompressed")


def _bounded_inflate(compression: str, size: int, source: str) -> Callable[[bytes], bytes]:
    """A decompressor that stops at `size` + 1 bytes and refuses anything but `size`."""

    def inflate(data: bytes) -> bytes:
        if compression == "none":
            out = bytes(data)
        elif compression == "bz2":
            d = bz2.BZ2Decompressor()
            try:
                out = d.decompress(data, max_length=size + 1)
            except (OSError, ValueError) as exc:
                raise DatasetError(f"{source}: a chunk's bz2 data is corrupt ({exc})") from None
        elif compression == "lz4":
            from gscompress.io.decode_budget import inflate_lz4

            out = inflate_lz4(data, size, f"{source}: a chunk's lz4 data", DatasetError)
        else:
            raise DatasetError(f"{source}: a chunk is compressed with unknown {compression!r}")
        if len(out) != size:
            raise DatasetError(f"{source}: a chunk inflates to other than its declared {size} B")
        return out

    return inflate
