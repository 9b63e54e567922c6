"""The recording reader under the one decode budget: chunks that rosbags inflates stop at their
declared size (a ROS 2 MCAP chunk of several zstd frames, a ROS 1 chunk of several bz2
streams), and a frame's image is checked from its header by the code that checks a folder's
frames. The bombs are read by `gsc info` in a child process held to the fuzz policy's memory
bound (tests/bounded.py): inflating one fails the test even when the message is right."""

from __future__ import annotations

import bz2
import io
import zlib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import zstandard
from bounded import memory_bound, run_bounded
from fuzz_containers import bz2_zeros, replace_chunk, zstd_zeros
from fuzz_mcap import _inner_records, mcap_records, serialize_log
from PIL import Image

from gscompress.datasets import open_sequence
from gscompress.datasets.recording import (
    CameraMessage,
    ImageMessage,
    decode_color,
    decode_depth,
    intrinsics_of,
)
from gscompress.datasets.recording_writer import write_recording
from gscompress.datasets.synthetic import synthetic_sequence
from gscompress.errors import DatasetError
from gscompress.io.decode_budget import inflate_bz2, inflate_zstd

BOMB_BYTES = 1 << 30
"""What each bomb inflates to: far over the 300 MB the reads may take."""


@pytest.fixture(scope="module")
def sequence():
    return synthetic_sequence(2, (16, 12))


def _bag_with_bomb_chunk(folder: Path, sequence) -> Path:
    """A ROS 2 bag (MCAP) whose first chunk is its records' zstd frame, declaring their size,
    followed by a frame of `BOMB_BYTES` zeros; its size and CRC those of its records."""
    from mcap.records import Chunk

    bag = write_recording(sequence, folder / "bag", "ros2")
    mcap = next(bag.glob("*.mcap"))
    records = mcap_records(mcap.read_bytes())
    at = next(i for i, r in enumerate(records) if isinstance(r, Chunk))
    inner = _inner_records(records[at])
    frame = zstandard.ZstdCompressor().compress(inner)
    assert zstandard.frame_content_size(frame) == len(inner)
    replace_chunk(
        records, at, frame + zstd_zeros(BOMB_BYTES), "zstd", zlib.crc32(inner), len(inner)
    )
    mcap.write_bytes(serialize_log(records))
    return bag


def _refused_in_bound(tmp_path: Path, path: Path, match: str) -> None:
    input_bytes = (
        sum(p.stat().st_size for p in path.rglob("*")) if path.is_dir() else (path.stat().st_size)
    )
    bound = memory_bound(input_bytes)
    run = run_bounded(["info", str(path)], bound, cwd=tmp_path, preload=("rosbags.highlevel",))
    assert run.returncode != 0, run.stderr
    assert len(run.lines) == 1, run.stderr[-3000:]
    assert match in run.lines[0], run.lines[0]
    assert "out of memory" not in run.lines[0] and "more memory than" not in run.lines[0]
    assert 0 <= run.peak_above_base <= run.bound, (run.peak_above_base, run.bound)


def test_a_ros2_chunk_of_several_zstd_frames_stops_at_its_declared_size(tmp_path, sequence):
    """rosbags inflated every frame of the chunk (1 GiB) before comparing it with the chunk's
    size; the bounded reader had checked only the first frame's header."""
    bag = _bag_with_bomb_chunk(tmp_path, sequence)
    _refused_in_bound(tmp_path, bag, "a chunk's zstd data decompresses to")


def test_a_ros2_chunk_of_several_honest_zstd_frames_reads(tmp_path, sequence):
    """A chunk written as several frames (each declaring its own part) reads as rosbags read it."""
    from mcap.records import Chunk

    bag = write_recording(sequence, tmp_path / "bag", "ros2")
    plain = open_sequence(bag)
    expected = [plain.frame(i) for i in range(len(plain))]
    plain.close()
    mcap = next(bag.glob("*.mcap"))
    records = mcap_records(mcap.read_bytes())
    for at, record in enumerate(records):
        if isinstance(record, Chunk):
            inner = _inner_records(record)
            half = len(inner) // 2
            parts = (inner[:half], inner[half:])
            frames = b"".join(zstandard.ZstdCompressor().compress(p) for p in parts)
            replace_chunk(records, at, frames, "zstd", record.uncompressed_crc, len(inner))
    mcap.write_bytes(serialize_log(records))
    read = open_sequence(bag)
    for i, frame in enumerate(expected):
        assert np.array_equal(read.frame(i).color, frame.color)
        assert np.array_equal(read.frame(i).depth, frame.depth)


def test_zstd_frames_stop_at_the_declared_size():
    head = bytes(range(256)) * 4
    halves = [zstandard.ZstdCompressor().compress(p) for p in (head[:512], head[512:])]
    assert inflate_zstd(b"".join(halves), 1024, "z", DatasetError, several_frames=True) == head
    with pytest.raises(DatasetError, match="declares 512 bytes, not 1024"):
        inflate_zstd(b"".join(halves), 1024, "z", DatasetError)  # (the first frame alone)
    bomb = zstandard.ZstdCompressor().compress(head) + zstd_zeros(256 << 20)
    with pytest.raises(DatasetError, match="z decompresses to 1025 bytes, not 1024"):
        inflate_zstd(bomb, 1024, "z", DatasetError, several_frames=True)
    with pytest.raises(DatasetError, match="z decompresses to 1025 bytes, not 1024"):
        inflate_zstd(bomb, 1024, "z", DatasetError)


def test_bz2_streams_stop_at_the_declared_size():
    head = bytes(range(256)) * 4
    streams = bz2.compress(head[:100]) + bz2.compress(head[100:])
    assert inflate_bz2(streams, 1024, "b", DatasetError) == head
    with pytest.raises(DatasetError, match="b inflates beyond 1024 bytes"):
        inflate_bz2(bz2.compress(head) + bz2_zeros(256 << 20), 1024, "b", DatasetError)
    with pytest.raises(DatasetError, match="b is cut short"):
        inflate_bz2(bz2.compress(head)[:-10], 1024, "b", DatasetError)
    with pytest.raises(DatasetError, match="b is corrupt"):
        inflate_bz2(b"BZh9" + bytes(64), 1024, "b", DatasetError)


def _png(array: np.ndarray) -> bytes:
    out = io.BytesIO()
    Image.fromarray(array).save(out, format="PNG")
    return out.getvalue()


def test_a_frame_is_checked_by_the_code_that_checks_a_folders_frames(tmp_path, monkeypatch):
    """A recording's compressed frame and a folder's frame file are refused by one check, in
    one message, when their pixels are more than their bytes may decode to (here a budget of
    half their bytes, so that a flat 16x12 PNG is over it)."""
    from gscompress.datasets.base import load_color
    from gscompress.io import decode_budget

    monkeypatch.setattr(decode_budget, "FLOOR_BYTES", 0)
    tight = decode_budget.Format("image", 0.5, "the pixels")
    monkeypatch.setitem(decode_budget.FORMATS, "image", tight)
    flat = _png(np.full((12, 16, 3), 90, np.uint8))
    message = ImageMessage(1, "cam", "png", True, data=np.frombuffer(flat, np.uint8))
    with pytest.raises(DatasetError) as from_recording:
        decode_color(message, (16, 12), "rec: /camera/color frame 0")
    (tmp_path / "0.png").write_bytes(flat)
    with pytest.raises(DatasetError) as from_folder:
        load_color(tmp_path / "0.png", (16, 12))
    for refused, where in (
        (from_recording, "rec: /camera/color frame 0"),
        (from_folder, str(tmp_path / "0.png")),
    ):
        assert str(refused.value) == (
            f"{where}: colour image of 16x12 RGB (576 bytes), more than its {len(flat)} bytes "
            "may decode to (0.5 times as many, 8 GiB at most)"
        )
    depth = ImageMessage(1, "cam", "png", True, data=_png(np.zeros((12, 16), np.uint16)))
    with pytest.raises(DatasetError, match="depth image of 16x12 I;16"):
        decode_depth(depth, (16, 12), "rec: /camera/depth frame 0")


def test_a_camera_info_is_checked_as_a_folders_intrinsics():
    """A focal length no RGB-D camera has (a million pixels on a 4x3 image) was read; it is now
    refused as a folder's intrinsics.json would be."""
    info = CameraMessage("cam", 4, 3, (1e6, 0, 1.5, 0, 1e6, 1.0, 0, 0, 1), "plumb_bob", (0.0,))
    with pytest.raises(DatasetError, match=r"camera info /info: fx 1000000.0 is not plausible"):
        intrinsics_of(info, "/info")
    wide = replace(info, width=9000)
    with pytest.raises(DatasetError, match=r"camera info /info: width 9000 is outside 1\.\.8192"):
        intrinsics_of(wide, "/info")
    ok = replace(info, K=(50.0, 0, 1.5, 0, 50.0, 1.0, 0, 0, 1))
    assert intrinsics_of(ok, "/info").fx == 50.0


class _CountingIndex(list):
    """A ROS 1 connection's index that counts the entries read from it."""

    read = 0

    def __iter__(self):
        for entry in super().__iter__():
            _CountingIndex.read += 1
            yield entry


def test_a_ros1_frame_is_read_without_walking_the_index(tmp_path):
    """Frame i of a ROS 1 bag used to walk rosbags' index from its start (i entries a frame,
    quadratic over a bag); now the entry at its place is read, in any order."""
    bag = write_recording(synthetic_sequence(12, (16, 12)), tmp_path / "long.bag", "ros1")
    seq = open_sequence(bag)
    frames = [seq.frame(i) for i in range(len(seq))]
    reader = seq._container._reader.readers[0]
    for cid in list(reader.indexes):
        reader.indexes[cid] = _CountingIndex(reader.indexes[cid])
    for i in (11, 0, 7, 11, 3):
        _CountingIndex.read = 0
        again = seq.frame(i)
        assert _CountingIndex.read <= 2, (i, _CountingIndex.read)  # colour and depth
        assert np.array_equal(again.color, frames[i].color)
        assert np.array_equal(again.depth, frames[i].depth)
        assert again.timestamp == frames[i].timestamp
