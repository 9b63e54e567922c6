"""Keyframes a share carries: written and read back, bounded, counted in the budget, refined on
by the merge and left out of its scores."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from PIL import Image

from gscompress.camera import Intrinsics, make_transform
from gscompress.errors import BudgetError, InputError, LogFormatError
from gscompress.gaussians import random_map
from gscompress.io.keyframes import (
    TOPIC_KEYFRAME_COLOR,
    TOPIC_KEYFRAME_DEPTH,
    CarriedFrame,
    read_carried,
    write_carried,
)
from gscompress.io.mcap_log import LogMetadata, LogReader, LogWriter, pose_message
from gscompress.pipeline import evaluate_log, merge_logs, resume_slam_file, share_log, slam_file
from gscompress.pipeline.images import ImageOptions
from gscompress.pipeline.logs import carried_keyframes
from gscompress.pipeline.slam_run.options import SlamOptions

# runs SLAM (or another minutes-long pipeline): not in `make test-fast`
pytestmark = pytest.mark.slow

CAMERA = Intrinsics(40.0, 40.0, 16.0, 12.0, 32, 24)


def smooth_frame(t_ns: int, seed: int) -> CarriedFrame:
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:24, 0:32] / 32.0
    color = np.stack([x, y, 0.5 + 0.3 * np.sin(6 * x + seed)], -1).astype(np.float32)
    depth = (1.0 + x + y).astype(np.float32)
    depth[0, :5] = 0.0  # invalid pixels stay invalid
    rotation = make_transform(np.eye(3), rng.normal(size=3))
    return CarriedFrame(t_ns, color, depth, rotation)


def written(path: Path, frames: list[CarriedFrame], extra: list[tuple[str, object]] = ()) -> Path:
    with LogWriter(path, LogMetadata()) as out:
        out.write_gaussians(random_map(5, seed=1), 0, "compact")
        write_carried(out, frames, CAMERA)
        for topic, message in extra:
            out.write_protobuf(topic, message, 7)  # type: ignore[arg-type]
    return path


def test_a_byte_budget_share_encodes_its_keyframes_once(tmp_path: Path, monkeypatch) -> None:
    """The search tries many counts, each a share file with the keyframes in it: their images
    are encoded once, not once a count (the bytes are the same either way)."""
    from gscompress.io import keyframes

    src = tmp_path / "a.mcap"
    with LogWriter(src, LogMetadata()) as out:
        out.write_gaussians(random_map(3000, seed=2), 0)
    frames = [smooth_frame(1_000_000_000 * (k + 1), k) for k in range(2)]
    encoded = []
    encode_depth = keyframes.encode_depth
    monkeypatch.setattr(keyframes, "encode_depth", lambda d: encoded.append(1) or encode_depth(d))
    result = share_log(src, tmp_path / "s.mcap", "20kB", carry=(frames, CAMERA))
    assert 0 < result["selected"] < 3000 and result["file_bytes"] <= 20_000
    assert len(encoded) == len(frames) and result["keyframes"] == len(frames)
    with LogWriter(None, LogMetadata()) as alone:
        assert result["keyframe_bytes"] == write_carried(alone, frames, CAMERA)


def test_carried_frames_read_back_as_written(tmp_path: Path) -> None:
    frames = [smooth_frame(1_000_000_000 * (k + 1), k) for k in range(3)]
    with LogReader(written(tmp_path / "s.mcap", frames)) as reader:
        back, camera = read_carried(reader)
    assert camera == CAMERA
    assert [f.time_ns for f in back] == [f.time_ns for f in frames]
    for got, sent in zip(back, frames, strict=True):
        assert np.abs(got.color - sent.color).max() < 0.05  # JPEG at quality 90
        assert np.abs(got.depth - sent.depth).max() <= 0.0005 + 1e-6  # 1 mm units
        assert np.all((got.depth == 0) == (sent.depth == 0))
        assert np.allclose(got.T_world_cam, sent.T_world_cam, atol=1e-9)
    with LogReader(written(tmp_path / "none.mcap", [])) as reader:
        assert read_carried(reader) == ([], None)


def png(size: tuple[int, int]) -> bytes:
    out = io.BytesIO()
    Image.fromarray(np.zeros(size[::-1], np.uint16)).save(out, format="PNG")
    return out.getvalue()


@pytest.mark.parametrize(
    ("image", "needle"),
    [
        (CompressedImage(data=png((64, 48)), format="png"), "not a png of the share's camera"),
        (CompressedImage(data=b"\x89PNG not really", format="png"), "not a readable png"),
        (CompressedImage(data=b"", format="png"), "not a readable png"),
    ],
)
def test_hostile_carried_images_are_refused_before_decoding(
    tmp_path: Path, image: CompressedImage, needle: str
) -> None:
    # one colour-and-pose frame at t=7 whose depth is the hostile image
    frame = smooth_frame(7, 0)
    with LogWriter(tmp_path / "h.mcap", LogMetadata()) as out:
        out.write_gaussians(random_map(5, seed=1), 0, "compact")
        out.write_calibration(CAMERA, 7)
        good = io.BytesIO()
        Image.fromarray(np.zeros((24, 32, 3), np.uint8)).save(good, format="JPEG")
        out.write_protobuf(
            TOPIC_KEYFRAME_COLOR, CompressedImage(data=good.getvalue(), format="jpeg"), 7
        )
        out.write_protobuf(TOPIC_KEYFRAME_DEPTH, image, 7)
        out.write_protobuf("/share/keyframe/pose", pose_message(frame.T_world_cam, 7), 7)
    with LogReader(tmp_path / "h.mcap") as reader, pytest.raises(LogFormatError, match=needle):
        read_carried(reader)


def test_a_camera_too_large_for_a_keyframe_is_refused(tmp_path: Path) -> None:
    frame = smooth_frame(9, 0)
    huge = Intrinsics(1e4, 1e4, 5e3, 5e3, 20_000, 20_000)  # 400 Mpx: 800 MB of depth
    with LogWriter(tmp_path / "b.mcap", LogMetadata()) as out:
        out.write_gaussians(random_map(5, seed=1), 0, "compact")
        write_carried(out, [frame], CAMERA)
        out.write_calibration(huge, 10)  # the last calibration is the camera
    with LogReader(tmp_path / "b.mcap") as reader, pytest.raises(LogFormatError, match="more"):
        read_carried(reader)


def test_a_carried_frame_without_its_depth_is_refused(tmp_path: Path) -> None:
    frame = smooth_frame(9, 0)
    path = written(tmp_path / "s.mcap", [frame])
    with LogReader(path) as reader:
        assert len(read_carried(reader)[0]) == 1
    # the same colour at another time, with no depth or pose there
    with LogReader(path) as reader:
        color = next(m for _s, _c, m in reader.iter_messages([TOPIC_KEYFRAME_COLOR])).data
    lonely = written(
        tmp_path / "l.mcap", [frame], [(TOPIC_KEYFRAME_COLOR, CompressedImage.FromString(color))]
    )
    with LogReader(lonely) as reader, pytest.raises(LogFormatError, match="has no depth"):
        read_carried(reader)


@pytest.fixture(scope="module")
def agents(tmp_path_factory: pytest.TempPathFactory, seq_dir_8: Path) -> dict[str, Path]:
    root, seq = tmp_path_factory.mktemp("carry"), seq_dir_8
    a, b = root / "a.mcap", root / "b.mcap"
    slam_file(seq, a, SlamOptions(preset="tiny", frames="0:5"))
    slam_file(seq, b, SlamOptions(preset="tiny", frames="3:8"))
    return {"seq": seq, "a": a, "b": b, "root": root}


def test_a_byte_budget_counts_the_keyframes(agents: dict[str, Path]) -> None:
    root = agents["root"]
    carry = carried_keyframes(agents["a"], 2, agents["seq"])
    assert len(carry[0]) == 2
    whole = share_log(agents["a"], root / "whole.mcap", 1.0, carry=carry, force=True)
    assert whole["keyframes"] == 2 and whole["keyframe_bytes"] > 1000
    budget = whole["file_bytes"] - whole["keyframe_bytes"] // 2  # not all the map fits
    plain = share_log(agents["a"], root / "plain.mcap", f"{budget}B", force=True)
    carried = share_log(agents["a"], root / "kf.mcap", f"{budget}B", carry=carry, force=True)
    assert carried["file_bytes"] <= budget and plain["file_bytes"] <= budget
    assert plain["selected"] == whole["selected"]  # the map alone fits
    assert carried["selected"] < plain["selected"]  # the frames took bytes from the Gaussians
    with pytest.raises(BudgetError):  # the frames alone overfill it
        share_log(agents["a"], root / "x.mcap", f"{carried['keyframe_bytes'] // 2}B", carry=carry)


def test_merge_refines_on_carried_keyframes_and_eval_leaves_them_out(
    agents: dict[str, Path],
) -> None:
    root, seq = agents["root"], agents["seq"]
    carry = carried_keyframes(agents["a"], 2, seq)
    share = root / "whole_kf.mcap"
    share_log(agents["a"], share, 1.0, carry=carry, force=True)
    merged = root / "m.mcap"
    result = merge_logs(agents["b"], share, merged, seq=seq, iters=6, force=True)
    assert result["refine_carried_views"] == 2
    assert result["refine_views"] == 5 + 2  # B's five frames and A's two keyframes
    times = [f.time_ns for f in carry[0]]
    with LogReader(merged) as log:
        operation = log.metadata.provenance[-1]["operation"]
    assert operation["carried_ns"] == times
    # with the sender's views, the merge stacks and refines every Gaussian alike
    assert operation["resolve"] == "stack" and operation["share_rate"] == 1.0
    told = merge_logs(
        agents["b"],
        share,
        root / "t.mcap",
        seq=seq,
        iters=2,
        merge={"resolve": "evidence"},
        force=True,
    )
    with LogReader(root / "t.mcap") as log:
        operation = log.metadata.provenance[-1]["operation"]
    assert operation["resolve"] == "evidence" and operation["share_rate"] == 1.0
    assert told["refine_carried_views"] == 2

    scored = evaluate_log(
        merged, seq, ImageOptions(frames="0:5", poses_from=agents["a"], lpips=False)
    )
    assert scored["frames_carried_left_out"] == 2 and scored["frames_evaluated"] == 3
    assert all(r["timestamp"] * 1e9 not in times for r in scored["per_frame"])
    # the same frames left out of another map's scores on request
    other = evaluate_log(agents["a"], seq, ImageOptions(lpips=False), leave_out=[share])
    assert other["frames_carried_left_out"] == 2 and other["frames_evaluated"] == 3

    plain = merge_logs(
        agents["b"], share, root / "p.mcap", seq=seq, iters=6, keyframes=False, force=True
    )
    assert plain["refine_carried_views"] == 0 and plain["refine_views"] == 5
    with LogReader(root / "p.mcap") as log:  # the merge of a share without views
        assert log.metadata.provenance[-1]["operation"]["resolve"] == "evidence"


def test_keyframes_of_another_camera_are_refused(agents: dict[str, Path]) -> None:
    root, seq = agents["root"], agents["seq"]
    share = root / "kf_cam.mcap"
    share_log(agents["a"], share, 1.0, carry=carried_keyframes(agents["a"], 1, seq), force=True)
    with pytest.raises(InputError, match=r"another camera.*merge with `no_keyframes`"):
        merge_logs(agents["b"], share, root / "c.mcap", seq=seq, iters=2, size=(32, 24))
    assert not (root / "c.mcap").exists()
    # an injected run has no --no-keyframes: the message names what it can do
    with pytest.raises(InputError, match=r"another camera.*sender's `size`") as refused:
        slam_file(
            seq,
            root / "i.mcap",
            SlamOptions(preset="tiny", frames="3:5", size=(32, 24), inject=share),
        )
    assert "no_keyframes" not in str(refused.value)
    assert not (root / "i.mcap").exists()


def test_share_and_merge_commands_carry_keyframes(agents: dict[str, Path]) -> None:
    from click.testing import CliRunner

    from gscompress_cli.main import cli

    root, seq = agents["root"], str(agents["seq"])
    share = str(root / "cli_kf.mcap")
    runner = CliRunner()
    refused = runner.invoke(cli, ["share", str(agents["a"]), share, "--keyframes", "2"])
    assert refused.exit_code == 2 and "--seq" in refused.output
    done = runner.invoke(
        cli, ["share", str(agents["a"]), share, "--budget", "1", "--keyframes", "2", "--seq", seq]
    )
    assert done.exit_code == 0, done.output
    assert "with 2 keyframes" in done.output
    merged = str(root / "cli_m.mcap")
    done = runner.invoke(
        cli, ["merge", str(agents["b"]), share, "--seq", seq, "--iters", "3", "-o", merged]
    )
    assert done.exit_code == 0, done.output
    assert "2 of them the sender's keyframes" in done.output
    done = runner.invoke(
        cli,
        [
            "eval",
            merged,
            "--seq",
            seq,
            "--frames",
            "0:5",
            "--poses-from",
            str(agents["a"]),
            "--no-lpips",
        ],
    )
    assert done.exit_code == 0, done.output
    assert "2 left out: carried by a share" in done.output


def test_an_injected_share_brings_its_keyframes_into_the_run(agents: dict[str, Path]) -> None:
    from gscompress.slam.system import SlamSystem

    root, seq = agents["root"], agents["seq"]
    carry = carried_keyframes(agents["a"], 2, seq)
    share = root / "inject_kf.mcap"
    share_log(agents["a"], share, 0.5, carry=carry, force=True)
    received: list[int] = []
    original = SlamSystem.receive

    def spy(self: SlamSystem, gaussians: object, views: object = None) -> int:
        added = original(self, gaussians, views)  # type: ignore[arg-type]
        received.append(len(self.keyframes))
        return added

    out = root / "b_inject.mcap"
    SlamSystem.receive = spy  # type: ignore[method-assign]
    try:
        slam_file(seq, out, SlamOptions(preset="tiny", frames="3:8", inject=share), force=True)
    finally:
        SlamSystem.receive = original  # type: ignore[method-assign]
    assert received == [2]  # A's two keyframes were keyframes before B's first frame
    with LogReader(out) as log:
        step = log.metadata.provenance[0]["operation"]
    assert step["name"] == "inject" and step["carried_ns"] == [f.time_ns for f in carry[0]]
    scored = evaluate_log(out, seq, ImageOptions(frames="0:5", poses_from=agents["a"], lpips=False))
    assert scored["frames_carried_left_out"] == 2
    with pytest.raises(InputError, match="afresh"):
        resume_slam_file(seq, out)
