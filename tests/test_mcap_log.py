"""The MCAP log profile: exact round trips, metadata, versioning and hostile files."""

import json

import jsonschema
import numpy as np
import pytest
from conftest import rewrite_log
from mcap.reader import make_reader
from mcap.writer import IndexType

from gscompress.camera import Intrinsics, make_transform, quat_to_rotmat
from gscompress.errors import LogFormatError, OutputError
from gscompress.gaussians import GaussianMap, random_map
from gscompress.io.mcap_bounds import LZ4_MAGIC, MAX_CHUNK_BYTES, ChunkHeader, check_chunk
from gscompress.io.mcap_log import (
    TOPIC_CALIBRATION,
    TOPIC_GAUSSIANS,
    TOPIC_POSE,
    TOPIC_POSE_GT,
    TOPIC_STATS,
    TOPIC_TF,
    LogMetadata,
    LogReader,
    LogWriter,
    gaussians_to_pointcloud,
    pointcloud_to_gaussians,
    read_map,
)
from gscompress_schemas import PROFILE_VERSION, load_schema


@pytest.mark.parametrize("isotropic", [True, False])
@pytest.mark.parametrize("sh_degree", [0, 1, 3])
def test_map_round_trip_is_bit_identical(tmp_path, isotropic, sh_degree):
    g = random_map(300, seed=sh_degree, isotropic=isotropic, sh_degree=sh_degree)
    path = tmp_path / "m.mcap"
    with LogWriter(path, LogMetadata()) as log:
        log.write_gaussians(g, 5)
    back = read_map(path)
    assert back.equals(g)
    assert back.isotropic == isotropic


def test_snapshots_are_indexed_from_both_ends(tmp_path):
    maps = [random_map(10 * (i + 1), seed=i) for i in range(5)]
    path = tmp_path / "m.mcap"
    with LogWriter(path, LogMetadata()) as log:
        for i, g in enumerate(maps):
            log.write_gaussians(g, 1000 * i)
    with LogReader(path) as log:
        assert log.snapshot_count == 5
        for i in range(-5, 5):
            assert log.read_map(i).equals(maps[i])
        with pytest.raises(LogFormatError, match="has 5 snapshot"):
            log.read_map(5)


def test_empty_map_round_trip(tmp_path):
    path = tmp_path / "e.mcap"
    with LogWriter(path, LogMetadata()) as log:
        log.write_gaussians(GaussianMap.empty(), 0)
    assert len(read_map(path)) == 0


@pytest.mark.parametrize("n", [0, 1, 2])
def test_a_read_map_owns_writable_arrays(tmp_path, n):
    """A field view of the file's buffer needing no conversion (0 or 1 rows) is copied."""
    path = tmp_path / "m.mcap"
    with LogWriter(path, LogMetadata()) as log:
        log.write_gaussians(random_map(n, seed=n), 0)
    back = read_map(path)
    for name, value in vars(back).items():
        assert value.flags.writeable, name
    back.opacity_logits[...] = 1.0  # raises on a read-only array


def test_full_profile_and_metadata(tmp_path):
    path = tmp_path / "run.mcap"
    meta = LogMetadata(
        command="gsc slam seq", config={"a": 1, "b": [1, 2]}, sequence="seq", frames="odd"
    )
    T = make_transform(quat_to_rotmat(np.array([0.9, 0.1, -0.2, 0.3])), np.array([1.0, 2.0, 3.0]))
    intr = Intrinsics(100.0, 101.0, 15.5, 11.5, 32, 24)
    stats = {"frame": 0, "gaussians": 10, "loss_mapping": 0.5, "ms": {"tracking": 3.0}}
    with LogWriter(path, meta) as log:
        log.write_calibration(intr, 0)
        for i in range(3):
            log.write_pose(T, i, ground_truth=False)
            log.write_pose(T, i, ground_truth=True)
            log.write_stats({**stats, "frame": i}, i)
        log.write_gaussians(random_map(10), 3)
    with LogReader(path) as log:
        counts = {c.topic: c.messages for c in log.channels}
        assert counts == {
            TOPIC_CALIBRATION: 1,
            TOPIC_POSE: 3,
            TOPIC_POSE_GT: 3,
            TOPIC_TF: 3,
            TOPIC_STATS: 3,
            TOPIC_GAUSSIANS: 1,
        }
        assert log.metadata == meta
        schema_check = load_schema("slam_stats.v1.schema.json")
        for schema, channel, message in log.iter_messages([TOPIC_STATS]):
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            jsonschema.validate(json.loads(message.data), schema_check)
    # poses decode to the same transform
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame

    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "gscompress"
        _, _, msg = next(reader.iter_messages(topics=[TOPIC_POSE]))
        pose = PoseInFrame()
        pose.ParseFromString(msg.data)
        q = pose.pose.orientation
        p = pose.pose.position
        R = quat_to_rotmat(np.array([q.w, q.x, q.y, q.z]))
        np.testing.assert_allclose(R, T[:3, :3], atol=1e-12)
        np.testing.assert_allclose([p.x, p.y, p.z], T[:3, 3])
        summary = reader.get_summary()
        assert all(c.compression == "zstd" for c in summary.chunk_indexes)
        assert [m.name for m in reader.iter_metadata()] == ["gscompress"]


def test_metadata_record_matches_its_schema(tmp_path):
    meta = LogMetadata(command="c").derive({"name": "prune", "keep": 0.3}, __file__, "d")
    assert meta.command == "d"  # the derived file's own command
    jsonschema.validate(meta.to_record(), load_schema("metadata.v1.schema.json"))
    step = meta.provenance[-1]
    assert step["parent"] == "test_mcap_log.py" and len(step["parent_sha256"]) == 64


def test_newer_major_profile_is_refused():
    major = int(PROFILE_VERSION.split(".")[0])
    record = LogMetadata().to_record()
    record["profile_version"] = f"{major + 1}.0"
    with pytest.raises(LogFormatError, match="newer than this gscompress"):
        LogMetadata.from_record(record)
    record["profile_version"] = f"{major}.9"
    assert LogMetadata.from_record(record).profile_version == f"{major}.9"


@pytest.mark.parametrize(
    "field, value",
    [
        ("provenance", "[1]"),
        ("provenance", '[{"operation": "prune", "parent": "a", "parent_sha256": "0"}]'),
        ("provenance", '{"operation": {}}'),
        ("config", "[]"),
        ("results", '"done"'),
    ],
)
def test_metadata_of_the_wrong_shape_is_a_format_error(field, value):
    """Hand-edited metadata is refused when read, not met later as a crash (`gsc info`)."""
    record = LogMetadata(command="c").derive({"name": "prune"}, __file__, "d").to_record()
    assert LogMetadata.from_record(record).provenance[-1]["operation"] == {"name": "prune"}
    record[field] = value
    with pytest.raises(LogFormatError, match="metadata config and results must be JSON"):
        LogMetadata.from_record(record)


def test_writer_exception_leaves_no_file(tmp_path):
    path = tmp_path / "x.mcap"
    with pytest.raises(RuntimeError):
        with LogWriter(path, LogMetadata()) as log:
            log.write_gaussians(random_map(10), 0)
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_writer_refuses_existing_output_and_inputs(tmp_path):
    path = tmp_path / "x.mcap"
    path.write_bytes(b"keep me")
    with pytest.raises(OutputError, match="pass `force`"):
        LogWriter(path, LogMetadata())
    with pytest.raises(OutputError, match="also an input"):
        LogWriter(path, LogMetadata(), inputs=[path], force=True)
    assert path.read_bytes() == b"keep me"


def _cloud_with(**changes):
    cloud = gaussians_to_pointcloud(random_map(8))
    for key, value in changes.items():
        setattr(cloud, key, value)
    return cloud


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda c: setattr(c, "point_stride", 0), "point_stride is 0"),
        (lambda c: setattr(c, "data", c.data[:-3]), "not a multiple"),
        (lambda c: setattr(c.fields[3], "offset", 10_000), "outside"),
        (lambda c: setattr(c.fields[0], "type", 42), "unknown numeric type"),
        (lambda c: setattr(c.fields[1], "name", "x"), "appears twice"),
        (lambda c: setattr(c.fields[10], "name", "alpha"), "lacks required field"),
    ],
)
def test_inconsistent_point_clouds_are_refused(mutate, message):
    cloud = gaussians_to_pointcloud(random_map(8))
    mutate(cloud)
    with pytest.raises(Exception, match=message):
        pointcloud_to_gaussians(cloud)


def test_non_finite_parameters_are_refused():
    g = random_map(8)
    g.opacity_logits[2] = np.inf
    with pytest.raises(Exception, match="non-finite"):
        pointcloud_to_gaussians(gaussians_to_pointcloud(g))


@pytest.mark.parametrize("version", ["1", " 1.0", "-1.0", "\u0661.0", "1.0.0", ""])
def test_a_malformed_profile_version_is_refused(version):
    record = LogMetadata().to_record()
    record["profile_version"] = version
    with pytest.raises(LogFormatError, match="bad profile_version"):
        LogMetadata.from_record(record)


def test_metadata_json_nested_too_deep_is_a_format_error():
    record = LogMetadata().to_record()
    record["config"] = "[" * 100_000 + "]" * 100_000
    with pytest.raises(LogFormatError, match="nested too deep"):
        LogMetadata.from_record(record)


def test_a_zstd_frame_declaring_more_than_its_chunk_is_refused_before_decompressing(
    tmp_path, monkeypatch
):
    """A decompression bomb: zstandard allocates the size a frame declares, whatever the chunk
    record says; the reader compares the two first."""
    import io

    import mcap.writer
    import zstandard

    def bomb(data: bytes) -> bytes:  # the chunk's records, then 64 MiB of zeros in the frame
        out = io.BytesIO()
        pad = 64 * 2**20
        with zstandard.ZstdCompressor(level=1).stream_writer(
            out, size=len(data) + pad, closefd=False
        ) as w:
            w.write(data)
            w.write(bytes(pad))
        return out.getvalue()

    path = tmp_path / "bomb.mcap"
    monkeypatch.setattr(mcap.writer.zstandard, "compress", bomb)
    with LogWriter(path, LogMetadata()) as log:
        log.write_gaussians(random_map(20), 0)
    monkeypatch.undo()
    assert path.stat().st_size < 2**20
    with pytest.raises(LogFormatError, match=r"zstd frame declares \d+ bytes, its record"):
        LogReader(path)
    with pytest.raises(LogFormatError, match="claims"):  # 100 times its compressed size
        _check(200 * 2**20, 1_000_000, "lz4", b"")
    _check(200 * 2**20, 3_000_000, "lz4", b"")
    with pytest.raises(LogFormatError, match="claims"):  # too large at any ratio
        _check(MAX_CHUNK_BYTES + 1, MAX_CHUNK_BYTES, "lz4", b"")


def _check(size, compressed, compression, head):
    check_chunk(ChunkHeader(size, 0, compression, 0, compressed), head, "f.mcap")


def _plain_log(tmp_path, snapshots=1):
    path = tmp_path / "plain.mcap"
    with LogWriter(path, LogMetadata()) as log:
        for t in range(snapshots):
            log.write_gaussians(random_map(10, seed=t), t)
    return path


def test_a_log_without_statistics_counts_its_snapshots(tmp_path):
    source = _plain_log(tmp_path, snapshots=3)
    path = tmp_path / "no_stats.mcap"  # the same messages, written without a Statistics record
    rewrite_log(source, path, use_statistics=False)
    with LogReader(path) as log:
        assert log.snapshot_count == 3
        assert np.array_equal(log.read_map().means, random_map(10, seed=2).means)


@pytest.mark.parametrize("options", [{"use_chunking": False}, {"index_types": IndexType.NONE}])
def test_an_unindexed_log_gives_its_last_snapshot(tmp_path, options):
    """mcap reads a file without chunk indexes forwards only, whatever `reverse` says."""
    source = _plain_log(tmp_path, snapshots=3)
    path = tmp_path / "unindexed.mcap"
    rewrite_log(source, path, **options)
    with LogReader(path) as log:
        assert not log._summary.chunk_indexes
        assert np.array_equal(log.read_map().means, random_map(10, seed=2).means)
        assert np.array_equal(log.read_map(-2).means, random_map(10, seed=1).means)
        _, _, last = next(iter(log.iter_messages([TOPIC_GAUSSIANS], reverse=True)))
        assert last.log_time == 2


def test_an_lz4_frame_declaring_more_than_its_chunk_is_refused(tmp_path):
    head = LZ4_MAGIC + bytes([0x68, 0x40]) + (2**40).to_bytes(8, "little") + bytes(4)
    with pytest.raises(LogFormatError, match=r"lz4 frame declares 1099511627776 bytes"):
        _check(1000, 500, "lz4", head)
    _check(1000, 500, "lz4", head[:4] + bytes([0x60]) + head[5:])  # no size


@pytest.mark.parametrize(("w", "readable"), [(1e-7, False), (2e-6, True), (1e300, True)])
def test_a_logged_pose_takes_the_same_quaternions_for_zero_as_text_files(tmp_path, w, readable):
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame

    from gscompress.errors import LogFormatError

    pose = PoseInFrame(frame_id="world")
    pose.pose.orientation.w = w
    with LogWriter(tmp_path / "p.mcap", LogMetadata()) as log:
        log.write_protobuf(TOPIC_POSE, pose, 1)
    with LogReader(tmp_path / "p.mcap") as log:
        if not readable:
            with pytest.raises(LogFormatError, match="zero-length pose"):
                log.read_poses()
        else:
            np.testing.assert_allclose(log.read_poses()[1][0], np.eye(4))
