"""Bounds on what rosbags inflates of a bag, through the decode budget's inflaters
(`gscompress.io.decode_budget`), whose running limit stops a stream the moment it produces more
than it declared:

- a ROS 1 bag's chunks are checked against the decode budget from their headers when the bag
  is opened (`check_chunk_size`), and each is given a decompressor bounded by its declared size
  (`bound_ros1_chunks`);
- a ROS 2 bag's MCAP chunks have had their headers checked by the bounded MCAP reader, which
  sees the declared size of a chunk's first zstd frame only; rosbags inflates every frame of a
  chunk before it compares the total with the chunk's size, so its MCAP inflaters are replaced
  by bounded ones that stop at the chunk's declared size over all its frames
  (`bound_mcap_inflates`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from gscompress.errors import DatasetError


class ChunkRefused(DatasetError):
    """A chunk that inflates to other than its declared size, refused while rosbags reads it
    (the container names the file: `gscompress.datasets.recording.containers`)."""


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
                decompressor=_ros1_inflater(compression, size, str(sub.path))
            )


def check_chunk_size(size: int, compressed: int, compression: str, source: str) -> None:
    """Refuse a ROS 1 chunk that declares more than the decode budget of an MCAP chunk allows
    (`gscompress.io.decode_budget`, format `mcap-chunk`), before it is inflated."""
    from gscompress.io.mcap_bounds import check_chunk_claim

    if compression == "none" and size != compressed:
        raise DatasetError(f"{source}: a chunk of {compressed} bytes claims {size} uncompressed")
    check_chunk_claim(size, compressed, source, DatasetError)


def _ros1_inflater(compression: str, size: int, source: str) -> Callable[[bytes], bytes]:
    """A ROS 1 chunk's decompressor that stops at `size` + 1 bytes and refuses anything but
    `size` (bz2 and lz4 through the decode budget's inflaters)."""
    from gscompress.io.decode_budget import inflate_bz2, inflate_lz4

    inflaters = {"bz2": inflate_bz2, "lz4": inflate_lz4}
    if compression not in (*inflaters, "none"):
        raise DatasetError(f"{source}: a chunk is compressed with unknown {compression!r}")

    def inflate(data: bytes) -> bytes:
        if compression == "none":
            out = bytes(data)
        else:
            where = f"{source}: a chunk's {compression} data"
            out = inflaters[compression](data, size, where, DatasetError)
        if len(out) != size:
            raise DatasetError(f"{source}: a chunk inflates to other than its declared {size} B")
        return out

    return inflate


def _inflate_zstd_chunk(data: bytes, size: int) -> bytes:
    """rosbags' MCAP zstd inflater, bounded: every frame of the chunk, at most `size` bytes."""
    from gscompress.io.decode_budget import inflate_zstd

    return bytes(inflate_zstd(data, size, "a chunk's zstd data", ChunkRefused, several_frames=True))


def _inflate_lz4_chunk(data: bytes, size: int) -> bytes:
    """rosbags' MCAP lz4 inflater, bounded: every frame of the chunk, at most `size` bytes."""
    from gscompress.io.decode_budget import inflate_lz4

    return inflate_lz4(data, size, "a chunk's lz4 data", ChunkRefused)


BOUNDED_MCAP_INFLATERS: dict[str, Callable[[bytes, int], bytes]] = {
    "zstd": _inflate_zstd_chunk,
    "lz4": _inflate_lz4_chunk,
}
"""The inflaters rosbags' MCAP storage is given, by chunk compression (their signature is
rosbags' own: the compressed bytes and the chunk's declared size)."""


def bound_mcap_inflates() -> None:
    """Make rosbags' MCAP storage inflate chunks with `BOUNDED_MCAP_INFLATERS` (idempotent).

    rosbags looks its inflaters up in one table of its MCAP storage module
    (`rosbags.rosbag2.storage_mcap.DECOMPRESSORS`, called with the chunk's bytes and declared
    size) for every chunk it reads; the bounded ones return what rosbags' own return for every
    chunk that inflates to its declared size, and refuse the others at that size, so the
    replacement holds for any reader of the process."""
    from rosbags.rosbag2 import storage_mcap

    storage_mcap.DECOMPRESSORS.update(BOUNDED_MCAP_INFLATERS)
