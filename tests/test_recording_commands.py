"""The commands that open a log's sequence take a recording with the topic options (merge,
align, share --keyframes, prune --refine, experiment, view), and the logs that prune, share and
merge derive carry the topics their parent's run read, so that their sequence reopens alike.
Every recording and log is made in the test (a ROS 2 bag of the synthetic room, a tiny run)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from conftest import gsc

from gscompress.datasets import open_sequence
from gscompress.datasets.recording_writer import write_recording
from gscompress.datasets.synthetic import write_synthetic_sequence
from gscompress.io.mcap_log import LogReader

# runs SLAM (or another minutes-long pipeline): not in `make test-fast`
pytestmark = pytest.mark.slow

TOPICS = ("--rgb", "/camera/color/image_raw", "--depth", "/camera/aligned_depth_to_color/image_raw")
"""The bag's topics, given as a user would."""
GT = ("--gt-frames", "world", "camera_color_optical_frame")


def recorded(log: Path) -> Any:
    with LogReader(log) as reader:
        return reader.metadata.results.get("recording")


@pytest.fixture(scope="module")
def bag_run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A ROS 2 bag of the synthetic room (5 frames, 64x48, with /tf) and a tiny run on its
    first 3 frames with /tf ground truth."""
    root = tmp_path_factory.mktemp("recording-commands")
    room = write_synthetic_sequence(root / "room", 5, (64, 48))
    bag = write_recording(open_sequence(room), root / "bag", "ros2")
    log = root / "run.mcap"
    result = gsc("--threads", 1, "slam", bag, "-o", log, "--preset", "tiny", "--frames", "0:3", *GT)
    assert result.exit_code == 0, result.output
    return {"bag": bag, "log": log, "root": root}


def test_recording_options_without_a_recording_are_refused(bag_run, tmp_path):
    log = bag_run["log"]
    for args in (
        ("prune", log, "--keep", 0.5, "-o", tmp_path / "p.mcap", "--rgb", "/x"),
        ("share", log, tmp_path / "s.mcap", "--budget", 0.5, "--depth", "/x"),
        ("merge", log, log, "--iters", 0, "-o", tmp_path / "m.mcap", "--max-dt", 0.05),
        ("align", log, log, "-o", tmp_path / "t.txt", "--camera-info", "/x"),
        ("view", log, "--rgb", "/x"),
    ):
        result = gsc(*args)
        assert result.exit_code == 2, (args, result.output)
        assert "are for a recording given by --seq" in result.output


def test_experiment_opens_the_recording_with_the_topics_given(bag_run, tmp_path):
    result = gsc(
        "experiment",
        bag_run["bag"],
        "-o",
        tmp_path / "exp",
        "--preset",
        "tiny",
        "--rgb",
        "/camera/nothing",
    )
    assert result.exit_code == 1 and "no topic '/camera/nothing' (--rgb)" in result.output
    assert not (tmp_path / "exp").exists()


def test_prune_share_and_merge_carry_the_runs_topics(bag_run, tmp_path):
    """prune --refine, share --keyframes and merge read the bag with the topics given, and the
    logs they write record the parent's (with its /tf ground truth), so that `gsc eval` of a
    merged log reopens the bag as the run read it."""
    bag, log = bag_run["bag"], bag_run["log"]
    parent = recorded(log)
    assert parent["rgb"] == "/camera/color/image_raw" and parent["gt_frames"] == list(GT[1:])
    pruned = tmp_path / "pruned.mcap"
    result = gsc("prune", log, "--keep", 0.5, "--refine", 2, "--seq", bag, *TOPICS, "-o", pruned)
    assert result.exit_code == 0, result.output
    assert "refined 2 iterations" in result.output and recorded(pruned) == parent
    share = tmp_path / "share.mcap"
    result = gsc("share", log, share, "--budget", 0.5, "--keyframes", 2, "--seq", bag, *TOPICS)
    assert result.exit_code == 0, result.output
    assert "with 2 keyframes" in result.output and recorded(share) == parent
    wrong = gsc(
        "share",
        log,
        tmp_path / "x.mcap",
        "--budget",
        0.5,
        "--keyframes",
        2,
        "--seq",
        bag,
        "--depth",
        "/camera/nothing",
    )
    assert wrong.exit_code == 1 and "no topic '/camera/nothing' (--depth)" in wrong.output
    merged = tmp_path / "merged.mcap"
    result = gsc("merge", log, share, "--seq", bag, *TOPICS, "--iters", 2, "-o", merged)
    assert result.exit_code == 0, result.output
    assert recorded(merged) == parent
    wrong = gsc(
        "merge",
        log,
        share,
        "--seq",
        bag,
        "--rgb",
        "/camera/nothing",
        "--iters",
        2,
        "-o",
        tmp_path / "x.mcap",
    )
    assert wrong.exit_code == 1 and "no topic '/camera/nothing' (--rgb)" in wrong.output
    assert not (tmp_path / "x.mcap").exists()
    result = gsc("eval", merged, "--seq", bag, "--no-lpips", "--json")
    assert result.exit_code == 0, result.output
    scores = json.loads(result.output)
    # (the 3 frames but the 2 the share carried, which eval leaves out of a merge)
    assert scores["frames_evaluated"] == 1 and scores["ate_rmse_cm"] is not None


def test_align_refines_on_a_recordings_frames(bag_run, tmp_path):
    pytest.importorskip("open3d", reason="the aligner needs Open3D: pip install '.[align]'")
    bag, log = bag_run["bag"], bag_run["log"]
    out = tmp_path / "T.txt"
    result = gsc("align", log, log, "-o", out, "--seq", bag, *TOPICS, "--json")
    assert result.exit_code == 0, result.output
    on_frames = json.loads(result.output)["on_frames"]
    assert on_frames["views"] >= 1 and on_frames["seq"] == str(bag)
    assert out.is_file()
    wrong = gsc(
        "align",
        log,
        log,
        "-o",
        tmp_path / "U.txt",
        "--seq",
        bag,
        "--camera-info",
        "/camera/nothing",
    )
    assert wrong.exit_code == 1
    assert "no topic '/camera/nothing' (--camera-info)" in wrong.output
    assert not (tmp_path / "U.txt").exists()
