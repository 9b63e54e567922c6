"""Recordings as sequences (`gscompress.datasets.recording`): ROS 1 / ROS 2 bags and Foxglove
MCAP give a folder's frames bit for bit, each encoding decodes, topics are chosen or refused with
the candidates named, colour and depth pair by stamp, /tf gives ground truth, and hostile
recordings are refused in one line. Every recording is made in the test."""

from __future__ import annotations

import io
import struct
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import gsc
from PIL import Image

from gscompress.camera import Intrinsics, make_transform, quat_to_rotmat
from gscompress.datasets import RecordingOptions, open_sequence, write_tum_sequence
from gscompress.datasets.recording import (
    ImageMessage,
    TopicInfo,
    TransformMessage,
    choose_topics,
    decode_color,
    decode_depth,
    ns_to_seconds,
    seconds_to_stamp_ns,
    tf_poses,
)
from gscompress.datasets.recording_writer import RECORDING_FORMATS, write_recording
from gscompress.datasets.synthetic import synthetic_sequence, write_synthetic_sequence
from gscompress.errors import DatasetError, OutputError
from gscompress.io.mcap_log import LogReader

FORMATS = list(RECORDING_FORMATS)
OUTPUT = {"ros2": "bag2", "ros2-sqlite": "bag2s", "ros1": "bag1.bag", "foxglove": "fox.mcap"}


@pytest.fixture(scope="module")
def folders(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The synthetic room (`gsc synth`, 5000 units per metre) and a TUM folder of the room at
    1000 units per metre (millimetres, as 16UC1 carries), both 64x48."""
    root = tmp_path_factory.mktemp("recordings")
    room = write_synthetic_sequence(root / "room", 5, (64, 48))
    mm = root / "room_mm"
    write_tum_sequence(synthetic_sequence(5, (64, 48), seed=3), mm, depth_scale=1000.0)
    return {"room": room, "mm": mm, "root": root}


def _recording(folders: dict[str, Path], name: str, fmt: str, **codings: str) -> Path:
    out = folders["root"] / f"{name}_{OUTPUT[fmt]}"
    if not out.exists():
        write_recording(open_sequence(folders[name]), out, fmt, **codings)
    return out


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize(("name", "depth"), [("room", "32FC1"), ("mm", "16UC1")])
def test_a_recording_gives_the_folders_frames_bit_for_bit(folders, fmt, name, depth):
    folder = open_sequence(folders[name])
    rec_path = _recording(folders, name, fmt, depth=depth)
    gt = RecordingOptions(gt=folders[name] / "groundtruth.txt")
    recording = open_sequence(rec_path, recording=gt)
    assert len(recording) == len(folder) == 5
    assert recording.intrinsics == folder.intrinsics
    assert np.array_equal(recording.timestamps, folder.timestamps)
    for i in range(len(folder)):
        a, b = folder.frame(i), recording.frame(i)
        assert a.timestamp == b.timestamp and a.index == b.index
        assert a.color.dtype == b.color.dtype and np.array_equal(a.color, b.color)
        assert a.depth.dtype == b.depth.dtype and np.array_equal(a.depth, b.depth)
        assert np.array_equal(a.T_world_cam, b.T_world_cam)
    # --frames selects as it does for a folder
    subset = open_sequence(rec_path, frames="1:5:2")
    assert list(subset.indices) == [1, 3]
    assert np.array_equal(subset.frame(1).color, folder.frame(3).color)


def test_16uc1_refuses_depth_finer_than_a_millimetre(folders, tmp_path):
    with pytest.raises(OutputError, match="finer than a millimetre"):
        write_recording(open_sequence(folders["room"]), tmp_path / "x.bag", "ros1", depth="16UC1")
    assert not (tmp_path / "x.bag").exists() and not list(tmp_path.iterdir())


@pytest.mark.slow
def test_slam_maps_and_poses_are_equal_from_a_folder_and_each_recording(folders, tmp_path):
    from gscompress.pipeline import slam_file
    from gscompress.pipeline.slam_run.options import SlamOptions

    def run(seq: Path, name: str, **options: Any) -> tuple[Any, Any, dict[str, Any]]:
        out = tmp_path / f"{name}.mcap"
        slam_file(seq, out, SlamOptions(preset="tiny", frames="0:3", **options))
        with LogReader(out) as reader:
            return reader.read_map(), reader.read_poses(), reader.metadata.results

    room = folders["room"]
    base_map, base_poses, _ = run(room, "folder")
    gt = RecordingOptions(gt=room / "groundtruth.txt")
    for fmt in FORMATS:
        gaussians, poses, results = run(_recording(folders, "room", fmt), fmt, recording=gt)
        for f in fields(gaussians):
            value = getattr(gaussians, f.name)
            if isinstance(value, np.ndarray):
                assert np.array_equal(value, getattr(base_map, f.name)), (fmt, f.name)
        assert np.array_equal(poses[0], base_poses[0]) and np.array_equal(poses[1], base_poses[1])
        assert results["recording"]["rgb"] == (
            "/camera/color" if fmt == "foxglove" else "/camera/color/image_raw"
        )


# ---------------------------------------------------------------------------------------------
# Encodings


def _raw(encoding: str, pixels: np.ndarray, step_pad: int = 0, big: bool = False) -> ImageMessage:
    h, w = pixels.shape[:2]
    rows = pixels.astype(pixels.dtype.newbyteorder(">" if big else "<")).reshape(h, -1)
    rows = rows.view(np.uint8)
    padded = np.concatenate([rows, np.full((h, step_pad), 7, np.uint8)], axis=1)
    return ImageMessage(1, "cam", encoding, False, w, h, padded.shape[1], big, padded.tobytes())


def _compressed(fmt: str, data: bytes) -> ImageMessage:
    return ImageMessage(1, "cam", fmt, True, data=data)


def _png(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG")
    return buf.getvalue()


RNG = np.random.default_rng(0)
RGB = RNG.integers(0, 256, (6, 5, 3), dtype=np.uint8)
EXPECTED = RGB.astype(np.float32) / np.float32(255.0)


@pytest.mark.parametrize(
    ("encoding", "pixels", "expected"),
    [
        ("rgb8", RGB, EXPECTED),
        ("bgr8", RGB[..., ::-1], EXPECTED),
        ("rgba8", np.dstack([RGB, np.full((6, 5), 9, np.uint8)]), EXPECTED),
        ("bgra8", np.dstack([RGB[..., ::-1], np.full((6, 5), 9, np.uint8)]), EXPECTED),
        ("mono8", RGB[..., 0], np.repeat(EXPECTED[..., :1], 3, axis=2)),
    ],
)
def test_raw_colour_encodings(encoding, pixels, expected):
    for pad in (0, 3):  # rows padded past width x channels (step)
        got = decode_color(_raw(encoding, pixels, pad), (5, 6), "t")
        assert got.dtype == np.float32 and np.array_equal(got, expected)


def test_compressed_colour_png_exact_and_jpeg_close():
    assert np.array_equal(decode_color(_compressed("png", _png(RGB)), (5, 6), "t"), EXPECTED)
    smooth = np.stack(np.meshgrid(np.arange(16) * 16, np.arange(8) * 30), -1)
    smooth = np.dstack([smooth, np.full((8, 16), 128)]).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(smooth).save(buf, format="JPEG", quality=95)
    jpeg = decode_color(_compressed("rgb8; jpeg compressed bgr8", buf.getvalue()), (16, 8), "t")
    assert jpeg.shape == (8, 16, 3) and np.abs(jpeg * 255 - smooth).mean() < 3


MM = np.array([[0, 1, 999, 65535], [1000, 2500, 4000, 65534]], dtype=np.uint16)
MM_METRES = np.where((MM == 65535), 0.0, MM / 1000.0).astype(np.float32)


def test_depth_encodings():
    assert np.array_equal(decode_depth(_raw("16UC1", MM), (4, 2), "t"), MM_METRES)
    assert np.array_equal(decode_depth(_raw("16UC1", MM, 2, big=True), (4, 2), "t"), MM_METRES)
    metres = np.array([[0.5, np.nan, -1.0, np.inf], [0.0, 1.25, 3.0, 1e-3]], dtype=np.float32)
    expect = np.array([[0.5, 0, 0, 0], [0, 1.25, 3.0, 1e-3]], dtype=np.float32)
    assert np.array_equal(decode_depth(_raw("32FC1", metres), (4, 2), "t"), expect)
    # image_transport's compressedDepth: a 12-byte header, then a 16-bit PNG of millimetres
    header = struct.pack("<iff", 0, 0.0, 0.0)
    message = _compressed("16UC1; compressedDepth png", header + _png(MM))
    assert np.array_equal(decode_depth(message, (4, 2), "t"), MM_METRES)
    # ... or for 32FC1 of quantised inverse depth, v = A / d + B
    a, b = 100.0, 10.0
    depth = np.array([[0.5, 1.0], [2.0, 0.0]])
    v = np.where(depth > 0, np.rint(a / np.where(depth > 0, depth, 1) + b), 0).astype(np.uint16)
    message = _compressed("32FC1; compressedDepth png", struct.pack("<iff", 0, a, b) + _png(v))
    got = decode_depth(message, (2, 2), "t")
    assert np.allclose(got, depth, rtol=1e-6) and got[1, 1] == 0
    # a plain 16-bit PNG (a Foxglove CompressedImage of depth) is millimetres
    assert np.array_equal(decode_depth(_compressed("png", _png(MM)), (4, 2), "t"), MM_METRES)


@pytest.mark.parametrize(
    ("decode", "message", "match"),
    [
        (decode_color, _raw("yuv422", RGB), "colour encoding"),
        (decode_depth, _raw("8UC1", RGB[..., 0]), "depth encoding"),
        (decode_color, _raw("rgb8", RGB[:5]), "camera info says 5x6"),
        (decode_depth, _compressed("16UC1; compressedDepth rvl", b"\0" * 40), "RVL"),
        (decode_depth, _compressed("png", _png(RGB)), "16-bit PNG"),
        (decode_color, _compressed("jpeg", b"\xff\xd8 not really"), "not a PNG or JPEG"),
    ],
)
def test_unreadable_images_are_refused_in_one_line(decode, message, match):
    with pytest.raises(DatasetError, match=match) as info:
        decode(message, (5, 6), "t")
    assert "\n" not in str(info.value)


def test_a_large_image_header_is_refused_before_its_pixels(monkeypatch):
    """A 9000x9000 PNG of a few hundred KB claiming to be a 5x6 frame: its header is read, its
    pixels never decoded."""
    big = Image.new("L", (9000, 9000))
    buf = io.BytesIO()
    big.save(buf, format="PNG")
    loaded = []
    monkeypatch.setattr(Image.Image, "load", lambda self: loaded.append(1))
    with pytest.raises(DatasetError, match="9000x9000 but the camera info says 5x6"):
        decode_color(_compressed("png", buf.getvalue()), (5, 6), "t")
    assert loaded == []


# ---------------------------------------------------------------------------------------------
# Topics


def _topics(*names: str, info: tuple[str, ...] = ("/camera/color/camera_info",)) -> list[Any]:
    kinds = [TopicInfo(n, "sensor_msgs/msg/Image", "image", 3) for n in names]
    return kinds + [TopicInfo(n, "sensor_msgs/msg/CameraInfo", "camera_info", 3) for n in info]


def test_topics_chosen_when_unambiguous():
    realsense = _topics(
        "/camera/color/image_raw",
        "/camera/depth/image_rect_raw",
        "/camera/aligned_depth_to_color/image_raw",
        "/camera/infra1/image_raw",
    )
    choice = choose_topics(realsense, RecordingOptions(), "rec")
    assert (choice.rgb, choice.depth) == (
        "/camera/color/image_raw",
        "/camera/aligned_depth_to_color/image_raw",
    )
    assert choice.camera_info == "/camera/color/camera_info" and "RealSense" in choice.reason
    kinect = _topics(
        "/rgb/image_raw",
        "/depth_to_rgb/image_raw",
        "/depth/image_raw",
        info=("/rgb/camera_info", "/depth/camera_info"),
    )
    choice = choose_topics(kinect, RecordingOptions(), "rec")
    assert (choice.rgb, choice.depth, choice.camera_info) == (
        "/rgb/image_raw",
        "/depth_to_rgb/image_raw",
        "/rgb/camera_info",
    )
    # only a compressed transport recorded: it stands for its base topic
    compressed = [
        TopicInfo(
            "/camera/rgb/image_color/compressed", "sensor_msgs/msg/CompressedImage", "compressed", 3
        ),
        *_topics("/camera/depth_registered/image_raw", info=("/camera/rgb/camera_info",)),
    ]
    choice = choose_topics(compressed, RecordingOptions(), "rec")
    assert choice.rgb == "/camera/rgb/image_color/compressed" and "OpenNI" in choice.reason
    generic = _topics("/front/color", "/front/depth", info=("/front/info",))
    assert choose_topics(generic, RecordingOptions(), "rec").depth == "/front/depth"


def test_ambiguous_topics_name_the_candidates():
    topics = _topics("/left/image", "/right/image", "/left/depth")
    with pytest.raises(DatasetError) as info:
        choose_topics(topics, RecordingOptions(), "rec")
    assert "candidates: /left/image, /right/image; pass `rgb` TOPIC" in str(info.value)
    choice = choose_topics(topics, RecordingOptions(rgb="/right/image"), "rec")
    assert (choice.rgb, choice.depth) == ("/right/image", "/left/depth")
    with pytest.raises(DatasetError, match="no topic '/nope' \\(`depth`\\)"):
        choose_topics(topics, RecordingOptions(depth="/nope"), "rec")
    two_infos = _topics("/a/image", "/b/depth", info=("/c/info", "/d/info"))
    with pytest.raises(DatasetError, match="candidates: /c/info, /d/info; pass `camera_info`"):
        choose_topics(two_infos, RecordingOptions(), "rec")
    with pytest.raises(DatasetError, match="no camera info"):
        choose_topics(_topics("/a/image", "/b/depth", info=()), RecordingOptions(), "rec")


# ---------------------------------------------------------------------------------------------
# A bag written by rosbags itself, pairing and ground truth from /tf


def _write_bag(
    path: Path,
    color_stamps: list[int],
    depth_stamps: list[int],
    *,
    depth_frame: str = "rgb_camera_link",
    width: int = 4,
    info_width: int = 4,
    distortion: tuple[float, ...] = (0.0,) * 5,
    info: bool = True,
    encoding: str = "bgr8",
) -> None:
    """An Azure Kinect-style ROS 2 bag written with rosbags' own writer (not ours)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    t = store.types

    def header(ns: int, frame: str) -> Any:
        return t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
            frame_id=frame,
        )

    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        rgb = writer.add_connection("/rgb/image_raw", "sensor_msgs/msg/Image", typestore=store)
        depth = writer.add_connection("/depth/image_raw", "sensor_msgs/msg/Image", typestore=store)
        cam = writer.add_connection(
            "/rgb/camera_info", "sensor_msgs/msg/CameraInfo", typestore=store
        )
        for k, ns in enumerate(color_stamps):
            pixels = np.full((3, width, 3), [10 * k, 20, 30], dtype=np.uint8)  # b, g, r
            msg = t["sensor_msgs/msg/Image"](
                header=header(ns, "rgb_camera_link"),
                height=3,
                width=width,
                encoding=encoding,
                is_bigendian=0,
                step=width * 3,
                data=pixels.reshape(-1),
            )
            writer.write(rgb, ns + 5, store.serialize_cdr(msg, "sensor_msgs/msg/Image"))
            if info:
                K = np.array([50.0, 0, 1.5, 0, 50.0, 1.0, 0, 0, 1])
                roi = t["sensor_msgs/msg/RegionOfInterest"](
                    x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
                )
                ci = t["sensor_msgs/msg/CameraInfo"](
                    header=header(ns, "rgb_camera_link"),
                    height=3,
                    width=info_width,
                    distortion_model="plumb_bob",
                    d=np.array(distortion),
                    k=K,
                    r=np.eye(3).ravel(),
                    p=np.zeros(12),
                    binning_x=0,
                    binning_y=0,
                    roi=roi,
                )
                writer.write(cam, ns + 5, store.serialize_cdr(ci, "sensor_msgs/msg/CameraInfo"))
        for k, ns in enumerate(depth_stamps):
            mm = np.full((3, width), 1000 + k, dtype="<u2")
            msg = t["sensor_msgs/msg/Image"](
                header=header(ns, depth_frame),
                height=3,
                width=width,
                encoding="16UC1",
                is_bigendian=0,
                step=width * 2,
                data=mm.view(np.uint8).reshape(-1),
            )
            writer.write(depth, ns + 7, store.serialize_cdr(msg, "sensor_msgs/msg/Image"))


SECOND = 10**9


def test_a_bag_written_by_rosbags_own_writer_reads(tmp_path):
    bag = tmp_path / "kinect"
    stamps = [SECOND + k * 33_333_333 for k in range(4)]
    _write_bag(bag, stamps, stamps)
    seq = open_sequence(bag)
    assert len(seq) == 4 and seq.choice.depth == "/depth/image_raw"  # same frame and size
    assert seq.intrinsics == Intrinsics(50.0, 50.0, 1.5, 1.0, 4, 3)
    f = seq.frame(2)
    assert np.array_equal(f.color[0, 0], np.array([30, 20, 20], np.float32) / np.float32(255))
    assert np.all(f.depth == np.float32(1.002)) and f.timestamp == ns_to_seconds(stamps[2])
    assert f.T_world_cam is None and not seq.has_ground_truth


def test_pairing_with_jittered_dropped_and_duplicated_stamps(tmp_path, caplog):
    period = 33_333_333
    colour = [SECOND + k * period for k in range(6)] + [SECOND + 5 * period]  # last repeated
    jitter = [3_000_000, -4_000_000, 19_000_000, 0, -25_000_000, -1_000_000]
    depth = [SECOND + k * period + j for k, j in enumerate(jitter)]  # frame 4's is 25 ms early
    _write_bag(tmp_path / "jitter", colour, depth)
    with caplog.at_level("INFO", logger="gscompress"):
        seq = open_sequence(tmp_path / "jitter")
    assert [round(t * 30) for t in seq.timestamps - 1.0] == [0, 1, 2, 3, 5]
    assert seq.skipped == {"rgb": 2, "depth": 1}
    assert "skipped 2 colour and 1 depth messages" in caplog.text
    assert len(open_sequence(tmp_path / "jitter", recording=RecordingOptions(max_dt=0.03))) == 6


def test_tf_ground_truth_is_interpolated_along_the_chain():
    def pose(yaw: float, x: float) -> np.ndarray:
        c, s = np.cos(yaw / 2), np.sin(yaw / 2)
        return make_transform(quat_to_rotmat(np.array([c, 0, 0, s])), [x, 0, 0])

    static = make_transform(np.eye(3), [0, 0, 1.0])
    samples = [
        TransformMessage(0, "map", "base", pose(0.0, 0.0), False),
        TransformMessage(SECOND, "map", "base", pose(0.4, 2.0), False),
        TransformMessage(0, "base", "camera", static, True),
    ]
    got = tf_poses(samples, "/map", "camera", [SECOND // 4, SECOND, 2 * SECOND])
    assert np.allclose(got[0], pose(0.1, 0.5) @ static)
    assert np.allclose(got[1], pose(0.4, 2.0) @ static)
    assert got[2] is None  # after the last sample: no extrapolation
    back = tf_poses(samples, "camera", "map", [SECOND])[0]
    assert np.allclose(back @ got[1], np.eye(4))
    with pytest.raises(DatasetError, match=r"no chain from .map. to .elsewhere."):
        tf_poses(samples, "map", "elsewhere", [0])


def test_ground_truth_from_tf_matches_the_folders(folders):
    folder = open_sequence(folders["room"])
    frames = ("world", "camera_color_optical_frame")
    for fmt in FORMATS:
        seq = open_sequence(
            _recording(folders, "room", fmt), recording=RecordingOptions(gt_frames=frames)
        )
        stamps, poses = seq.ground_truth()
        assert np.array_equal(stamps, folder.ground_truth()[0])
        assert np.allclose(poses, folder.ground_truth()[1], atol=1e-12)


def test_stamps_round_trip_through_nanoseconds():
    for t in (0.0, 0.033333, 1305031102.175304, 1.7e9 + 0.123456789):
        assert ns_to_seconds(seconds_to_stamp_ns(t)) == t


# ---------------------------------------------------------------------------------------------
# Bad recordings, each refused in one line


def _one_line(path: Path, match: str, **options: Any) -> str:
    with pytest.raises(DatasetError, match=match) as info:
        seq = open_sequence(path, recording=RecordingOptions(**options))
        seq.frame(0)
    assert "\n" not in str(info.value)
    return str(info.value)


def test_image_size_other_than_the_camera_infos_is_refused(tmp_path):
    _write_bag(tmp_path / "b", [SECOND], [SECOND], info_width=8)
    _one_line(tmp_path / "b", "is 4x3 but the camera info says 8x3")


def test_missing_camera_info_and_distortion_are_refused(tmp_path):
    _write_bag(tmp_path / "noinfo", [SECOND], [SECOND], info=False)
    _one_line(tmp_path / "noinfo", "no camera info")
    _write_bag(tmp_path / "distorted", [SECOND], [SECOND], distortion=(0.1, 0, 0, 0, 0))
    _one_line(tmp_path / "distorted", "distortion 'plumb_bob' .* is not undone here")


def test_unknown_encoding_and_unregistered_depth_are_refused(tmp_path):
    _write_bag(tmp_path / "yuv", [SECOND], [SECOND], encoding="yuv422")
    _one_line(tmp_path / "yuv", "colour encoding 'yuv422'")
    _write_bag(tmp_path / "apart", [SECOND], [SECOND], depth_frame="depth_camera_link")
    _one_line(
        tmp_path / "apart", "depth /depth/image_raw .* is not registered to colour /rgb/image_raw"
    )


@pytest.mark.parametrize("fmt", FORMATS)
def test_a_truncated_recording_is_refused(folders, tmp_path, fmt):
    source = _recording(folders, "room", fmt)
    files = (
        sorted(p for p in source.iterdir() if p.suffix != ".yaml") if source.is_dir() else [source]
    )
    target = tmp_path / source.name
    if source.is_dir():
        target.mkdir()
        (target / "metadata.yaml").write_bytes((source / "metadata.yaml").read_bytes())
    for f in files:
        data = f.read_bytes()
        (target / f.name if source.is_dir() else target).write_bytes(data[: len(data) * 2 // 3])
    print("REFUSED", _one_line(target, str(target)))


def test_millions_of_declared_messages_without_data_are_refused(tmp_path):
    """A bag whose metadata declares 5,000,000 images of which its storage holds none."""
    bag = tmp_path / "empty"
    _write_bag(bag, [SECOND], [SECOND])
    meta = (bag / "metadata.yaml").read_text()
    (bag / "metadata.yaml").write_text(meta.replace("message_count: 1", "message_count: 5000000"))
    mcap = next(bag.glob("*.mcap"))
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(mcap, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    with open(mcap, "wb") as f:  # the same schemas and channels, no message
        w = Writer(f)
        w.start(profile="ros2")
        ids = {k: w.register_schema(s.name, s.encoding, s.data) for k, s in summary.schemas.items()}
        for c in summary.channels.values():
            w.register_channel(c.topic, c.message_encoding, ids[c.schema_id], c.metadata)
        w.finish()
    print("REFUSED", _one_line(bag, "holds no message"))


def test_a_compressed_bag_folder_is_refused_before_it_is_inflated(tmp_path):
    bag = tmp_path / "zipped"
    _write_bag(bag, [SECOND], [SECOND])
    meta = (bag / "metadata.yaml").read_text()
    (bag / "metadata.yaml").write_text(
        meta.replace("compression_mode: ''", "compression_mode: FILE")
    )
    _one_line(bag, "compressed per file")


def test_a_gsc_log_is_not_taken_for_a_recording(run):
    _one_line(run["log"], "is a gscompress log, not a recording")


# ---------------------------------------------------------------------------------------------
# Commands


def test_gsc_info_says_what_each_mcap_is(folders, run):
    ros2_file = next(_recording(folders, "room", "ros2").glob("*.mcap"))
    for path, kind in (
        (ros2_file, "ROS 2 bag (MCAP)"),
        (_recording(folders, "room", "foxglove"), "Foxglove recording (MCAP)"),
        (_recording(folders, "room", "ros1"), "ROS 1 bag"),
        (run["log"], "gscompress log"),
    ):
        result = gsc("info", path)
        assert result.exit_code == 0, result.output
        assert f"({kind}" in result.output.splitlines()[0]
    result = gsc("info", _recording(folders, "room", "ros2-sqlite"), "--json")
    import json

    found = json.loads(result.output)
    assert found["kind"] == "ROS 2 bag (sqlite)"
    color = next(t for t in found["topics"] if t["topic"] == "/camera/color/image_raw")
    assert (color["messages"], color["encoding"], color["size"]) == (5, "rgb8", [64, 48])
    assert abs(color["rate_hz"] - 30.0) < 0.1
    assert found["slam_would_read"]["frames"] == 5


def test_gsc_info_names_the_candidates_of_an_ambiguous_recording(tmp_path):
    bag = tmp_path / "two"
    _write_bag(bag, [SECOND], [SECOND])
    meta = bag / "metadata.yaml"
    meta.write_text(meta.read_text())  # (unchanged: a second colour topic comes by rename)
    result = gsc("info", bag, "--rgb", "/nope")
    assert result.exit_code == 0 and "reads nothing: " in result.output
    assert "no topic '/nope' (--rgb)" in result.output


def test_convert_and_synth_write_recordings(folders, tmp_path):
    result = gsc(
        "convert",
        folders["mm"],
        "-o",
        tmp_path / "mm.bag",
        "--format",
        "ros1",
        "--depth-encoding",
        "compressedDepth",
        "--color-encoding",
        "png",
    )
    assert result.exit_code == 0, result.output
    seq, folder = open_sequence(tmp_path / "mm.bag"), open_sequence(folders["mm"])
    assert np.array_equal(seq.frame(4).depth, folder.frame(4).depth)
    assert np.array_equal(seq.frame(4).color, folder.frame(4).color)
    result = gsc("synth", tmp_path / "syn", "--format", "ros2", "--frames", 2, "--size", "32x24")
    assert result.exit_code == 0, result.output
    rendered = synthetic_sequence(2, (32, 24)).frame(1)
    assert np.array_equal(open_sequence(tmp_path / "syn").frame(1).depth, rendered.depth)
    again = gsc("synth", tmp_path / "syn", "--format", "ros2", "--frames", 2, "--size", "32x24")
    assert again.exit_code != 0 and "--force" in again.output
    bad = gsc("convert", folders["mm"], "-o", tmp_path / "x.mcap", "--format", "ros1")
    assert bad.exit_code != 0 and "a ros1 recording is a .bag file" in bad.output


@pytest.mark.slow
def test_every_seq_command_takes_a_recording(folders, tmp_path):
    """slam, eval, render and score on a ROS 2 bag through the CLI; the topics the run read
    are recorded and reused by eval and render."""
    bag = _recording(folders, "room", "ros2")
    log = tmp_path / "run.mcap"
    result = gsc(
        "--threads",
        1,
        "slam",
        bag,
        "-o",
        log,
        "--preset",
        "tiny",
        "--frames",
        "0:3",
        "--gt-frames",
        "world",
        "camera_color_optical_frame",
    )
    assert result.exit_code == 0, result.output
    assert "ATE RMSE" in result.output
    result = gsc("eval", log, "--seq", bag, "--no-lpips", "--json")
    assert result.exit_code == 0, result.output
    assert '"frames_evaluated": 3' in result.output
    result = gsc("render", log, "--seq", bag, "-o", tmp_path / "pictures", "--every", 2)
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (tmp_path / "pictures" / "rgb").iterdir()) == [
        "000000.png",
        "000002.png",
    ]
    result = gsc("score", log, "--seq", bag, "-o", tmp_path / "scored.mcap")
    assert result.exit_code == 0, result.output
    wrong = gsc("eval", log, "--seq", bag, "--rgb", "/camera/nothing")
    assert wrong.exit_code != 0 and "no topic '/camera/nothing' (--rgb)" in wrong.output
