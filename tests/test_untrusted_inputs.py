"""Hostile and foreign inputs: one regression test per reader defect found by fuzzing and per
real file that was refused or misread (MCAP chunks, PointCloud layouts, PLY headers and
values, output and input paths, depth images)."""

import io
import json
import logging
import os
import struct
import warnings

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import rewrite_log
from mcap.reader import make_reader
from mcap.writer import CompressionType, IndexType

from gscompress.errors import GscError, LogFormatError, MapError, PlyFormatError
from gscompress.gaussians import random_map
from gscompress.io.columns import MAX_ABS_OPACITY_LOGIT
from gscompress.io.mcap_log import (
    LogMetadata,
    LogReader,
    LogWriter,
    gaussians_to_pointcloud,
    pointcloud_to_gaussians,
    read_map,
)
from gscompress.io.ply import read_ply, write_ply
from gscompress_cli.main import cli


def _log(tmp_path, name="plain.mcap", n=40, snapshots=1):
    path = tmp_path / name
    with LogWriter(path, LogMetadata()) as log:
        for t in range(snapshots):
            log.write_gaussians(random_map(n, seed=t), t)
    return path


def _chunk_offsets(path):
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.chunk_indexes
    return [index.chunk_start_offset for index in summary.chunk_indexes]


def _patch(path, offset, fmt, value):
    data = bytearray(path.read_bytes())
    struct.pack_into(fmt, data, offset, value)
    path.write_bytes(bytes(data))


# a chunk record: opcode (1), length (8), start and end times (16), uncompressed size (8),
# crc (4), codec-name length (4), the name, then the records' length (8)
_NAME_LENGTH, _NAME = 9 + 16 + 8 + 4, 9 + 16 + 8 + 4 + 4


@pytest.mark.parametrize("length", [2**63, 2**64 - 1])
@pytest.mark.parametrize("indexed", [True, False])
def test_1_a_chunk_records_length_of_2_63_and_more_is_refused(tmp_path, length, indexed):
    path = _log(tmp_path)
    if not indexed:
        rewrite_log(path, tmp_path / "u.mcap", index_types=IndexType.NONE)
        path = tmp_path / "u.mcap"
    for offset in _chunk_offsets(path) if indexed else [_first_chunk(path)]:
        _patch(path, offset + _NAME + len("zstd"), "<Q", length)
    with pytest.raises(LogFormatError, match=r"overrun|runs past the end"):
        read_map(path)


def _first_chunk(path):
    data = path.read_bytes()
    offset = 8  # after the magic: the header record, then the first chunk (opcode 6)
    while data[offset] != 6:
        offset += 9 + struct.unpack_from("<Q", data, offset + 1)[0]
    return offset


@pytest.mark.parametrize("length", [2**32 + 1, 2**36, 2**40, 3 * 2**30])
def test_2_a_chunk_records_length_beyond_the_file_is_refused_before_allocating(tmp_path, length):
    path = _log(tmp_path)
    offset = _chunk_offsets(path)[0]
    _patch(path, offset + _NAME + len("zstd"), "<Q", length)
    with pytest.raises(LogFormatError, match=f"records of {length} bytes overrun"):
        LogReader(path)


def test_2_a_codec_name_length_of_zero_followed_by_garbage_is_refused(tmp_path):
    path = _log(tmp_path)
    offset = _chunk_offsets(path)[0]
    _patch(path, offset + _NAME_LENGTH, "<I", 0)  # "zstd" + the length now read as a length
    with pytest.raises(LogFormatError, match="overrun"):
        LogReader(path)


def _padded_log(tmp_path, monkeypatch, codec, pad, honest_size):
    """A log whose chunks decompress to their records followed by `pad` zero bytes; the
    chunk's uncompressed size says so when `honest_size`, else names the records only."""
    import lz4.frame
    import mcap.writer
    import zstandard

    source = _log(tmp_path, "source.mcap")
    real_zstd, real_lz4 = zstandard.compress, lz4.frame.compress
    if codec == "zstd":
        monkeypatch.setattr(
            mcap.writer.zstandard, "compress", lambda data: real_zstd(data + bytes(pad))
        )
    else:  # a frame without a content size, as other writers make
        monkeypatch.setattr(
            mcap.writer.lz4.frame,
            "compress",
            lambda data: real_lz4(data + bytes(pad), store_size=False),
        )
    path = tmp_path / f"padded-{codec}.mcap"
    compression = CompressionType.ZSTD if codec == "zstd" else CompressionType.LZ4
    rewrite_log(source, path, compression=compression)
    monkeypatch.undo()
    if honest_size:  # the chunk records' uncompressed size counts the padding
        for offset in _chunk_offsets(path):
            size = struct.unpack_from("<Q", path.read_bytes(), offset + 25)[0]
            _patch(path, offset + 25, "<Q", size + pad)
            _patch(path, offset + 33, "<I", 0)  # no CRC recorded
    return path


def test_3_an_lz4_frame_without_a_size_that_inflates_beyond_its_chunk_is_refused(
    tmp_path, monkeypatch
):
    path = _padded_log(tmp_path, monkeypatch, "lz4", pad=4 << 20, honest_size=False)
    assert path.stat().st_size < 200_000
    with LogReader(path) as log:  # (the size is said only by the frame's end)
        with pytest.raises(LogFormatError, match="lz4 data inflates beyond"):
            log.read_map()


def test_3_lz4_chunks_of_other_writers_still_read(tmp_path):
    source = _log(tmp_path, "source.mcap", snapshots=2)
    path = tmp_path / "lz4.mcap"
    rewrite_log(source, path, compression=CompressionType.LZ4)
    assert read_map(path).equals(read_map(source))


@pytest.mark.parametrize("codec", ["zstd", "lz4"])
def test_4_an_honest_zero_padded_chunk_below_64_mib_is_refused_by_its_ratio(
    tmp_path, monkeypatch, codec
):
    path = _padded_log(tmp_path, monkeypatch, codec, pad=8 << 20, honest_size=True)
    with pytest.raises(LogFormatError, match=r"claims .* bytes uncompressed"):
        LogReader(path)


def test_4_padding_records_inside_a_chunk_are_refused(tmp_path, monkeypatch):
    """Below the ratio ceiling, padding with records a chunk may not hold is refused too."""
    path = _padded_log(tmp_path, monkeypatch, "zstd", pad=64, honest_size=True)
    with LogReader(path) as log:
        with pytest.raises(LogFormatError, match="opcode 0x00"):
            log.read_map()


def test_5_a_bare_property_line_is_refused(tmp_path):
    path = tmp_path / "bare.ply"
    path.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty\nend_header\n"
    )
    with pytest.raises(PlyFormatError, match="line 4: bad property line 'property'"):
        read_ply(path)


@pytest.mark.parametrize("count", [2**63, 10**19 - 1])
def test_6_a_huge_vertex_count_without_properties_is_refused(tmp_path, count):
    path = tmp_path / "huge.ply"
    path.write_bytes(
        f"ply\nformat binary_little_endian 1.0\nelement vertex {count}\nend_header\n".encode()
    )
    with pytest.raises(PlyFormatError, match=r"has .* rows but no properties"):
        read_ply(path)


def test_6_an_element_count_of_more_than_19_digits_is_refused(tmp_path):
    path = tmp_path / "long.ply"
    count = "9" * 5000  # (int() refuses over 4300 digits)
    path.write_bytes(
        f"ply\nformat binary_little_endian 1.0\nelement vertex {count}\nend_header\n".encode()
    )
    with pytest.raises(PlyFormatError, match="bad element line"):
        read_ply(path)


def test_7_an_output_that_is_a_symbolic_link_loop_is_refused(tmp_path):
    source = _log(tmp_path)
    loop = tmp_path / "loop.mcap"
    os.symlink(loop.name, loop)  # a link to itself
    r = CliRunner().invoke(cli, ["prune", str(source), "--keep", "0.5", "-o", str(loop)])
    assert r.exit_code == 1, r.output
    assert "cannot follow its links" in r.output and "Traceback" not in r.output
    assert os.path.islink(loop)
    inside = tmp_path / "a"
    os.symlink("b", inside)
    os.symlink("a", tmp_path / "b")
    r = CliRunner().invoke(cli, ["export-ply", str(source), "-o", str(inside / "m.ply")])
    assert r.exit_code == 1 and "cannot follow its links" in r.output, r.output


def _ply_with_face(tmp_path, faces, present):
    g = random_map(10)
    plain = write_ply(g, tmp_path / "plain.ply", importance=False, force=True)
    data = plain.read_bytes()
    header_end = data.index(b"end_header\n")
    header = data[:header_end] + f"element face {faces}\nproperty int a\n".encode()
    path = tmp_path / f"face{faces}.ply"
    path.write_bytes(header + data[header_end:] + bytes(4 * present))
    return path


def test_8_an_element_after_the_vertices_whose_bytes_are_absent_is_refused(tmp_path):
    path = _ply_with_face(tmp_path, 10**12, present=3)
    with pytest.raises(PlyFormatError, match="1000000000000 rows of element 'face'"):
        read_ply(path)
    assert len(read_ply(_ply_with_face(tmp_path, 3, present=3))) == 10  # present: read


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda c: setattr(c.fields[1], "offset", c.fields[0].offset + 2), "overlap"),
        (lambda c: setattr(c.fields[1], "offset", c.fields[0].offset), "overlap"),
        (lambda c: setattr(c, "point_stride", 2 * c.point_stride), "stride"),
        (lambda c: setattr(c, "point_stride", c.point_stride + 4), "stride"),
    ],
)
def test_9_overlapping_fields_or_a_stride_other_than_the_fields_are_refused(mutate, message):
    cloud = gaussians_to_pointcloud(random_map(8))
    if "stride" in message:  # keep the data a whole number of the new records
        mutate(cloud)
        cloud.data = cloud.data + bytes(-len(cloud.data) % cloud.point_stride)
    else:
        mutate(cloud)
    with pytest.raises(MapError, match=message):
        pointcloud_to_gaussians(cloud)


def _ply_with_opacity(tmp_path, values):
    g = random_map(len(values), seed=3)
    g.opacity_logits[:] = 0
    path = write_ply(g, tmp_path / "o.ply")
    data = bytearray(path.read_bytes())
    body = data.index(b"end_header\n") + len(b"end_header\n")
    stride = (len(data) - body) // len(values)
    opacity_at = 4 * (3 + 3 + 3)  # x y z, nx ny nz, f_dc_0..2
    for i, value in enumerate(values):
        struct.pack_into("<f", data, body + i * stride + opacity_at, value)
    path.write_bytes(bytes(data))
    return path


def test_10_a_huge_finite_opacity_logit_is_clamped_without_numpy_warnings(tmp_path, caplog):
    path = _ply_with_opacity(tmp_path, [-1e30, 1e30, 2.0, -3.0e38])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a numpy RuntimeWarning fails the test
        with caplog.at_level(logging.WARNING):
            g = read_ply(path)
            opacities = g.opacities()
    limit = MAX_ABS_OPACITY_LOGIT
    assert g.opacity_logits.tolist() == [-limit, limit, 2.0, -limit]
    assert opacities[1] == 1.0 and opacities[0] < 1e-30
    notes = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(notes) == 1 and "3 beyond +-80 opacity logit(s) read as +-80" in notes[0]


def test_11_a_device_or_a_fifo_is_not_called_missing(tmp_path):
    fifo = tmp_path / "pipe.mcap"
    os.mkfifo(fifo)
    for reader in (LogReader, read_ply):
        for path in (fifo, "/dev/zero"):
            with pytest.raises(GscError, match="is not a regular file"):
                reader(path)
        with pytest.raises(GscError, match="no such file"):
            reader(tmp_path / "absent")
        with pytest.raises(GscError, match="is a directory"):
            reader(tmp_path)
    r = CliRunner().invoke(cli, ["info", "/dev/zero"])
    assert r.exit_code == 1 and "is not a regular file" in r.output, r.output


def test_12_infinite_opacity_logits_read_as_the_bounds_with_one_note(tmp_path, caplog):
    values = [np.inf] * 5 + [-np.inf] * 2 + [1.5]
    with caplog.at_level(logging.WARNING):
        g = read_ply(_ply_with_opacity(tmp_path, values))
    limit = MAX_ABS_OPACITY_LOGIT
    assert g.opacity_logits.tolist() == [limit] * 5 + [-limit] * 2 + [1.5]
    assert np.all(g.opacities()[:5] == 1.0) and np.all(g.opacities()[5:7] < 1e-30)
    notes = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert notes == [
        f"{tmp_path / 'o.ply'}: 7 infinite opacity logit(s) read as +-80 (opacity 1 or 0)"
    ]


def test_12_a_nan_opacity_logit_is_still_refused(tmp_path):
    with pytest.raises(PlyFormatError, match="non-finite"):
        read_ply(_ply_with_opacity(tmp_path, [np.nan, np.inf, 0.0]))


def test_12_infinite_opacity_in_a_log_is_still_refused():
    g = random_map(8)
    g.opacity_logits[2] = -np.inf
    with pytest.raises(MapError, match="non-finite"):
        pointcloud_to_gaussians(gaussians_to_pointcloud(g))


def test_a_damaged_compressed_ply_is_refused_in_one_line(tmp_path):
    """A compressed PLY is read by its own reader (tests/test_spz.py); one that lacks its
    chunk bounds is refused, not misread as a plain PLY missing its properties."""
    header = (
        "ply\nformat binary_little_endian 1.0\nelement chunk 1\n"
        + "".join(f"property float {n}\n" for n in ("min_x", "min_y", "min_z"))
        + "element vertex 2\nproperty uint packed_position\nproperty uint packed_rotation\n"
        "property uint packed_scale\nproperty uint packed_color\nend_header\n"
    )
    path = tmp_path / "scene.compressed.ply"
    path.write_bytes(header.encode() + bytes(12 + 2 * 16))
    with pytest.raises(PlyFormatError) as caught:
        read_ply(path)
    assert "\n" not in str(caught.value) and "lacks required field" not in str(caught.value)
    r = CliRunner().invoke(cli, ["import-ply", str(path), "-o", str(tmp_path / "x.mcap")])
    assert r.exit_code == 1 and r.output.count("\n") == 1
    assert not (tmp_path / "x.mcap").exists()


def test_readers_reject_io_of_a_bounded_stream_past_its_end():
    from gscompress.io.mcap_bounds import BoundedStream

    stream = BoundedStream(io.BytesIO(b"abcdef"), "buffer")
    assert stream.read(4) == b"abcd"
    with pytest.raises(LogFormatError, match="a field of 3 bytes at offset 4 runs past the end"):
        stream.read(3)
    with pytest.raises(LogFormatError, match="shorter than its own fields"):
        stream.read(-1)


def _depth_sequence(tmp_path, raw, intrinsics_extra=None):
    """A 2-frame 8x6 TUM folder whose depth PNGs hold `raw` (uint16) in every frame."""
    from PIL import Image

    folder = tmp_path / "seq"
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    for i in range(2):
        Image.fromarray(np.zeros((6, 8, 3), np.uint8)).save(folder / "rgb" / f"{i}.png")
        Image.fromarray(raw).save(folder / "depth" / f"{i}.png")
    (folder / "rgb.txt").write_text("".join(f"{i}.0 rgb/{i}.png\n" for i in range(2)))
    (folder / "depth.txt").write_text("".join(f"{i}.0 depth/{i}.png\n" for i in range(2)))
    k = {"fx": 8, "fy": 8, "cx": 3.5, "cy": 2.5, "width": 8, "height": 6, "depth_scale": 1000}
    (folder / "intrinsics.json").write_text(json.dumps({**k, **(intrinsics_extra or {})}))
    return folder


def _raw_depth():
    raw = np.full((6, 8), 1500, np.uint16)  # 1.5 m
    raw[0, :3] = 65535  # saturated: no measurement
    raw[1, 0] = 0
    raw[2, 0] = 9000  # 9 m
    return raw


def test_13_saturated_16_bit_depth_reads_as_no_depth(tmp_path):
    from gscompress.datasets import open_sequence

    depth = open_sequence(_depth_sequence(tmp_path, _raw_depth())).frame(0).depth
    assert depth[0, :3].tolist() == [0.0, 0.0, 0.0] and depth[1, 0] == 0.0
    assert depth[2, 0] == pytest.approx(9.0) and depth[5, 7] == pytest.approx(1.5)


def test_13_intrinsics_json_declares_invalid_values_and_a_maximum_depth(tmp_path):
    from gscompress.datasets import open_sequence

    listed = open_sequence(_depth_sequence(tmp_path / "a", _raw_depth(), {"invalid_depth": [1500]}))
    depth = listed.frame(1).depth
    assert depth[0, 0] == pytest.approx(65.535)  # 65535 is a measurement when not listed
    assert depth[5, 7] == 0.0 and depth[2, 0] == pytest.approx(9.0)
    bounded = open_sequence(_depth_sequence(tmp_path / "b", _raw_depth(), {"max_depth": 8.0}))
    depth = bounded.frame(1).depth
    assert depth[2, 0] == 0.0 and depth[0, 0] == 0.0 and depth[5, 7] == pytest.approx(1.5)


@pytest.mark.parametrize(
    "extra", [{"invalid_depth": [70000]}, {"invalid_depth": "65535"}, {"max_depth": -1}]
)
def test_13_bad_depth_declarations_are_refused(tmp_path, extra):
    from gscompress.datasets import open_sequence
    from gscompress.errors import DatasetError

    with pytest.raises(DatasetError, match=r"invalid_depth must be|max_depth must be"):
        open_sequence(_depth_sequence(tmp_path, _raw_depth(), extra))


def test_a_chunk_indexed_twice_is_read_twice_in_either_order(tmp_path):
    """Ties of a hostile index (two entries for one chunk) are broken without comparing
    records (which raised a TypeError)."""
    from fuzz_mcap import mcap_records, serialize_log
    from mcap.records import ChunkIndex

    source = _log(tmp_path, snapshots=2)
    records = mcap_records(source.read_bytes())
    at = next(i for i, r in enumerate(records) if isinstance(r, ChunkIndex))
    records.insert(at, records[at])
    path = tmp_path / "twice.mcap"
    path.write_bytes(serialize_log(records))
    with LogReader(path) as log:
        forward = [m.log_time for _, _, m in log.iter_messages()]
        backward = [m.log_time for _, _, m in log.iter_messages(reverse=True)]
    assert forward == [0, 0, 1, 1] and backward == [1, 1, 0, 0]


def test_a_metadata_index_pointing_at_a_chunk_is_refused(tmp_path):
    """mcap would open the chunk as if it were the metadata record, without bounds."""
    from fuzz_mcap import mcap_records, serialize_as_is, serialize_log
    from mcap.records import ChunkIndex, MetadataIndex

    records = mcap_records(_log(tmp_path).read_bytes())
    serialize_log(records)  # (the indexes' offsets as written)
    chunk = next(r for r in records if isinstance(r, ChunkIndex)).chunk_start_offset
    next(r for r in records if isinstance(r, MetadataIndex)).offset = chunk
    path = tmp_path / "misindexed.mcap"
    path.write_bytes(serialize_as_is(records))
    with pytest.raises(LogFormatError, match=f"record at offset {chunk} is not a metadata"):
        LogReader(path)


def test_a_log_says_where_its_poses_came_from_through_derivations():
    scored = LogMetadata(
        provenance=[
            {
                "operation": {"name": "score", "poses": "ground-truth"},
                "parent": "f.ply",
                "parent_sha256": "0",
            }
        ],
        results={"poses": "ground-truth"},
    )
    step = {"operation": {"name": "prune"}, "parent": "s.mcap", "parent_sha256": "1"}
    pruned = LogMetadata(provenance=[*scored.provenance, step], results={"selected": 3})
    assert scored.pose_origin() == pruned.pose_origin() == "ground-truth"
    mapping_only = LogMetadata(config={"tracking": {"use_ground_truth": True}})
    assert mapping_only.pose_origin() == "ground-truth"
    assert LogMetadata(config={"tracking": {"use_ground_truth": False}}).pose_origin() == (
        "estimated"
    )
    assert LogMetadata(results={"poses": 1}).pose_origin() == "estimated"  # (not a name)
